#!/usr/bin/env python
"""How well the perceived planner's driver estimator recovers each driver in sight (the paper scenario, the
rule-based ego, 8 episodes of 30 s): log-RMSE of the posterior mean of each longitudinal parameter against the
traffic's median, and the desired speed's RMSE against the motion-based estimate the planner uses without it.

    python docs/results/safety-samples/scripts/driver_estimate_check.py
"""

import numpy as np

from experiments.imagined_drivers.estimate import LONGITUDINAL, DriverEstimator
from lcsim.core import RUNNING, LaneChangeCore
from lcsim.planning.perception import estimated_desired_speeds
from lcsim.registry import make_driver, scenario


def main() -> None:
    cfg, envs = scenario("paper"), 8
    core = LaneChangeCore(cfg, envs)
    core.reset(np.arange(envs), list(range(100, 100 + envs)))
    est = DriverEstimator(cfg.traffic, cfg.dt_s, cfg.steps_per_decision, cfg.sensing_range_m)
    rule = make_driver("rule")
    for _ in range(60):
        est.observe(core)
        core.step(rule(core.observe(), core.action_mask(), core))
        if (core.outcome != RUNNING).all():
            break
    est.observe(core)
    seen, sim = est.evidence, core.sim
    post = est.posterior()[seen]
    print(f"vehicles observed over at least one decision period: {int(seen.sum())}")
    for name in LONGITUDINAL:
        cand, true = getattr(est.candidates, name), np.log(getattr(sim.drivers, name)[seen])
        prior = np.sqrt(np.mean((np.log(cand.mean()) - true) ** 2))
        mean = np.sqrt(np.mean((np.log((post * cand).sum(-1)) - true) ** 2))
        print(f"{name:14s} log-rmse: median driver {prior:.3f}, estimate {mean:.3f}")
    v0 = sim.v0[seen]
    print(f"desired speed rmse (m/s): traffic's median {np.sqrt(np.mean((np.exp(est.log_prior) @ est.v0 - v0) ** 2)):.3f}, "
          f"from the last step's motion {np.sqrt(np.mean((estimated_desired_speeds(sim)[seen] - v0) ** 2)):.3f}, "
          f"estimate {np.sqrt(np.mean(((post * est.v0).sum(-1) - v0) ** 2)):.3f}")


if __name__ == "__main__":
    main()
