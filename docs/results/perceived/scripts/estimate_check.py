"""One-off check (the perceived-planner study): how well HighwaySim.estimated_desired_speeds recovers the true desired speeds.

    python docs/results/perceived/scripts/estimate_check.py

20 paper-scenario episodes (seeds 500-519) after 40 decisions of the rule-based driver; prints the error of
the estimate with the full index and, within 80 m, after perceive(80), against the crude estimate
max(nominal, present speed), and how often each gets "blocked" (about to change lanes) right.
"""
import numpy as np

from lcsim.config import paper_scenario
from lcsim.core import LaneChangeCore
from lcsim.planning import estimated_desired_speeds, imagined_copy, perceive
from lcsim.registry import make_driver

cfg = paper_scenario(render_image=False)
core = LaneChangeCore(cfg, 20)
core.reset(range(20), list(range(500, 520)))
rule = make_driver("rule")
for _ in range(40):
    core.step(rule({}, core.action_mask(), core))
sim = core.sim
true = sim.v0[:, 1:]
est = estimated_desired_speeds(sim)[:, 1:]
err = np.abs(est - true) * 3.6
print("all vehicles, full index: median err km/h", np.median(err), "share within 0.5 km/h", (err < 0.5).mean(), "max", err.max())
c = imagined_copy(core)
perceive(c.sim, 80.0)
d = np.hypot(sim.x - sim.x[:, :1], sim.y - sim.y[:, :1])[:, 1:] <= 80
err2 = np.abs(c.sim.v0[:, 1:] - true)[d] * 3.6
print("within 80 m, after perceive: median", np.median(err2), "within 0.5", (err2 < 0.5).mean(), "n", d.sum())
nom = np.abs(np.maximum(sim.speed[:, 1:], cfg.traffic.speed_kmh / 3.6) - true)[d] * 3.6
print("old estimate max(speed, nominal): median", np.median(nom), "within 0.5", (nom < 0.5).mean())
# blocked classification agreement
tc = cfg.traffic
idx = sim.index
def blocked(v0):
    return (idx.gap < np.inf) & (idx.gap >= tc.blocked_gap_min_m) & (idx.gap <= tc.blocked_gap_max_m) & (idx.lead_speed < v0 - tc.blocked_speed_margin_kmh / 3.6)
bt = blocked(sim.v0)[:, 1:][d]
be = blocked(c.sim.v0)[:, 1:][d]
bn = blocked(np.maximum(sim.speed, tc.speed_kmh / 3.6))[:, 1:][d]
print("blocked true", bt.sum(), "inverted est agrees", (bt == be).mean(), "misses", (bt & ~be).sum(), "false", (~bt & be).sum())
print("old est agrees", (bt == bn).mean(), "misses", (bt & ~bn).sum(), "false", (~bt & bn).sum())
