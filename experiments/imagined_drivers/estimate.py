"""Which driver each vehicle in sight is, read from its motion: a posterior over candidate drivers.

On human-like traffic every driver has its own car-following parameters (time headway, acceleration, comfortable
deceleration) and reaction time (:class:`~lcsim.traffic.DriverParams`), which no sensor shows. A perceived safety
layer that imagines every driver as the median one misjudges how a vehicle of the target lane will brake (what one
that knew each driver's parameters gains: ``docs/results/safety-samples``). :class:`DriverEstimator` infers them
from what the ego's sensors show at each
decision: each vehicle's speed and acceleration, its gap to its leader and the leader's speed, for vehicles whose
leader is within the sensing range too.

It keeps a fixed set of candidate drivers drawn from the traffic's distribution and, per environment and vehicle,
a log-likelihood of each. Between two decisions it replays the car-following model of each candidate with the
observed speeds, gaps and leader speeds interpolated over the period, from the acceleration observed at the first
decision, and compares the acceleration and speed change it predicts with those observed. The driver's own
acceleration noise, constant over a period, is the unknown that separates them (a Gaussian of the traffic's noise
scale, integrated out). Imagined futures then draw each vehicle's driver from its posterior
(:meth:`DriverEstimator.draw`): a vehicle seen for a while gets its own driver, one never seen a plausible one.
"""

from __future__ import annotations

import math

import numpy as np

from lcsim.config import TrafficConfig
from lcsim.core import LaneChangeCore
from lcsim.traffic import DriverParams

LONGITUDINAL: tuple[str, ...] = ("time_headway", "max_accel", "inv_2sqrt_ab", "lag")
"""The driver parameters the estimator infers (the others stay the median driver's)."""


class DriverEstimator:
    """A posterior over ``candidates`` drivers for every vehicle of every environment of one core, updated from
    the core's observable state at each decision (:meth:`observe`)."""

    def __init__(self, traffic: TrafficConfig, dt: float, steps_per_decision: int, range_m: float, *,
                 candidates: int = 48, speeds: int = 11, seed: int = 0, accel_sigma: float = 0.01,
                 speed_sigma: float = 0.005) -> None:  # fmt: skip
        if candidates < 1 or speeds < 1:
            raise ValueError(f"candidates and speeds must be >= 1, got {candidates}, {speeds}")
        self.traffic, self.dt, self.steps, self.range_m = traffic, dt, int(steps_per_decision), range_m
        drawn = DriverParams.nominal(traffic, (candidates,), dt)
        drawn.draw(slice(None), np.random.default_rng(seed), traffic, dt, candidates)
        # every drawn driver with every desired speed of a grid over the traffic's spread (+-2.5 sigma)
        z = np.linspace(-2.5, 2.5, speeds) if speeds > 1 else np.zeros(1)
        self.candidates = DriverParams(*(np.repeat(getattr(drawn, f), speeds) for f in DriverParams.__slots__))
        self.v0 = np.tile(np.maximum((traffic.speed_kmh + z * traffic.speed_spread_kmh) / 3.6, 1.0), candidates)
        prior = np.tile(np.exp(-0.5 * z * z), candidates)
        self.log_prior = np.log(prior / prior.sum())
        self.accel_sigma, self.speed_sigma = accel_sigma, speed_sigma
        self.loglik: np.ndarray | None = None  # (E, N, M)
        self._seen: np.ndarray | None = None
        self._prev: dict[str, np.ndarray] | None = None

    # -- what the sensors show ------------------------------------------------------------------------------------
    def _snapshot(self, core: LaneChangeCore) -> dict[str, np.ndarray]:
        sim = core.sim
        if sim.index is None:
            sim.rebuild_index()
        index = sim.index
        x, y = sim.x, sim.y
        seen = np.hypot(x - x[:, :1], y - y[:, :1]) <= self.range_m
        seen &= sim.is_traffic
        seen[:, 0] = False
        flat = index.lead_flat
        lead_seen = np.append(seen.ravel(), False)[flat].reshape(seen.shape)
        has_lead = index.lead >= 0
        return {
            "seeds": core.seeds.copy(), "steps": np.asarray(sim.step).copy(), "x": x.copy(), "speed": sim.speed.copy(),
            "accel": sim.accel.copy(), "gap": np.where(has_lead, index.gap, np.inf),
            "lead_speed": np.where(has_lead, index.lead_speed, 0.0), "lead": index.lead.copy(),
            "ok": seen & (~has_lead | lead_seen),
        }  # fmt: skip

    def observe(self, core: LaneChangeCore) -> None:
        """Update the posteriors with the state of ``core`` now (call once per decision, before imagining)."""
        now = self._snapshot(core)
        e, n = now["x"].shape
        m = len(self.candidates.lag)
        if self.loglik is None or self.loglik.shape[:2] != (e, n):
            self.loglik, self._prev = np.broadcast_to(self.log_prior, (e, n, m)).copy(), None
            self._mu, self._var = np.zeros((e, n, m)), np.full((e, n, m), self.traffic.accel_noise_mps2**2)
            self._seen = np.full((e, n), -1, dtype=np.int64)  # the step of each vehicle's last update
        prev = self._prev
        self._prev = now
        if prev is None:
            return
        new_episode = (prev["seeds"] != now["seeds"]) | (now["steps"] < prev["steps"])
        if new_episode.any():
            self.loglik[new_episode], self._mu[new_episode] = self.log_prior, 0.0
            self._var[new_episode], self._seen[new_episode] = self.traffic.accel_noise_mps2**2, -1
        moved = now["x"] - prev["x"]
        span = self.dt * self.steps
        advanced = ~new_episode & (now["steps"] == prev["steps"] + self.steps)  # one decision period later
        pair = (prev["ok"] & now["ok"] & (prev["lead"] == now["lead"]) & advanced[:, None]
                & (moved >= -0.5) & (moved <= (prev["speed"] + now["speed"]) * span + 5.0))  # fmt: skip
        if not pair.any():
            return
        rows = np.nonzero(pair)
        steps_now = np.broadcast_to(now["steps"][:, None], pair.shape)[rows]
        periods = np.where(self._seen[rows] >= 0, (steps_now - self._seen[rows]) // self.steps, -1)
        ll, mu, var = self._update(
            {k: v[rows] for k, v in prev.items() if v.ndim == 2}, {k: v[rows] for k, v in now.items() if v.ndim == 2},
            self._mu[rows], self._var[rows], periods)  # fmt: skip
        self.loglik[rows] += ll
        self._mu[rows], self._var[rows], self._seen[rows] = mu, var, steps_now

    def _update(self, a: dict[str, np.ndarray], b: dict[str, np.ndarray], mu: np.ndarray, var: np.ndarray,
                periods: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """For ``P`` vehicles observed at two decisions ``a``, ``b``: each candidate's log-likelihood ``(P, M)`` and
        its estimate of the driver's acceleration noise (mean, variance) after the period. The noise is an AR(1)
        process constant over each period: a Kalman filter per candidate (``periods``: periods since the
        vehicle's last update, -1 for its first)."""
        from lcsim.traffic import idm_accel

        tc, c = self.traffic, self.candidates
        lag = c.lag[None, :]
        shape = (len(a["x"]), len(c.lag))
        drivers = DriverParams(*(np.broadcast_to(getattr(c, f)[None, :], shape) for f in DriverParams.__slots__))
        acc = np.repeat(a["accel"][:, None], shape[1], axis=1)
        dv_pred = np.zeros(shape)
        respond = np.zeros(shape)  # how the period's constant noise shows in the final acceleration ...
        respond_v = np.zeros(shape)  # ... and in the speed change
        v0 = np.broadcast_to(self.v0[None, :], shape)
        free = ~np.isfinite(a["gap"]) | ~np.isfinite(b["gap"])
        gap_a, gap_b = np.where(free, 0.0, a["gap"]), np.where(free, 0.0, b["gap"])
        for k in range(self.steps):
            w = k / self.steps
            v = (1 - w) * a["speed"] + w * b["speed"]
            gap = np.where(free, np.inf, (1 - w) * gap_a + w * gap_b)
            ls = (1 - w) * a["lead_speed"] + w * b["lead_speed"]
            cmd = idm_accel(np.broadcast_to(v[:, None], shape), v0, np.broadcast_to(gap[:, None], shape),
                            np.broadcast_to((v - ls)[:, None], shape), tc, drivers)  # fmt: skip
            acc = acc + lag * (cmd - acc)
            respond = respond + lag * (1.0 - respond)
            dv_pred = dv_pred + acc * self.dt
            respond_v = respond_v + respond * self.dt
        r_a = b["accel"][:, None] - acc
        r_v = (b["speed"] - a["speed"])[:, None] - dv_pred
        # the noise's prior for this period: AR(1) from the last estimate, or the stationary one
        s2 = tc.accel_noise_mps2**2
        rho = math.exp(-tc.lane_change_check_period_s / tc.accel_noise_time_s) if tc.accel_noise_time_s > 0 else 0.0
        decay = np.where(periods >= 0, rho ** np.maximum(periods, 0).astype(np.float64), 0.0)[:, None]
        mu_p = decay * mu
        var_p = decay * decay * var + s2 * (1.0 - decay * decay)
        # r = noise * (respond, respond_v) + error: innovation y, its covariance S (2x2 per candidate)
        y_a, y_v = r_a - respond * mu_p, r_v - respond_v * mu_p
        saa = var_p * respond * respond + self.accel_sigma**2
        svv = var_p * respond_v * respond_v + self.speed_sigma**2
        sav = var_p * respond * respond_v
        det = saa * svv - sav * sav
        quad = (svv * y_a * y_a - 2.0 * sav * y_a * y_v + saa * y_v * y_v) / det
        ll = -0.5 * (quad + np.log(det)) - math.log(2.0 * math.pi)
        # gain K = var_p c^T S^-1
        k_a = var_p * (respond * svv - respond_v * sav) / det
        k_v = var_p * (respond_v * saa - respond * sav) / det
        mu_new = mu_p + k_a * y_a + k_v * y_v
        var_new = var_p * (1.0 - k_a * respond - k_v * respond_v)
        return ll, mu_new, np.maximum(var_new, 1e-12)

    # -- what the imagined futures use ------------------------------------------------------------------------------
    def posterior(self, rows: np.ndarray | None = None) -> np.ndarray:
        """``(R, N, M)`` each vehicle's posterior over the candidates (uniform for a vehicle never observed)."""
        if self.loglik is None:
            raise ValueError("observe a core first")
        return _normalised(self.loglik if rows is None else self.loglik[rows])

    @property
    def evidence(self) -> np.ndarray:
        """``(E, N)`` bool: the vehicles observed over at least one period (the others have only the prior)."""
        if self._seen is None:
            raise ValueError("observe a core first")
        return self._seen >= 0

    def draw(self, rows: np.ndarray, salt: np.ndarray, step: np.ndarray) -> tuple[DriverParams, np.ndarray, np.ndarray]:
        """For imagined copies of environments ``rows``: drivers ``(R, N)``, their desired speeds (m/s) and where
        they were drawn (the vehicles with :attr:`evidence`; the others are the median driver with a NaN desired
        speed). Each is drawn from its posterior by a generator seeded by the copy's ``salt`` and ``step`` and
        its row (the same state and salt give the same drivers)."""
        rows = np.asarray(rows)
        seen = self.evidence[rows]
        r, n = seen.shape
        u = np.empty((r, n))
        for i in range(r):
            u[i] = np.random.default_rng([int(salt[i]), int(step[i]), int(rows[i])]).random(n)
        post = np.cumsum(_normalised(self.loglik[rows][seen]), axis=-1)
        pick = np.minimum((post < u[seen][:, None]).sum(axis=-1), post.shape[-1] - 1)
        drawn = DriverParams.nominal(self.traffic, (r, n), self.dt)
        for name in LONGITUDINAL:
            getattr(drawn, name)[seen] = getattr(self.candidates, name)[pick]
        v0 = np.full((r, n), np.nan)
        v0[seen] = self.v0[pick]
        return drawn, v0, seen


def _normalised(loglik: np.ndarray) -> np.ndarray:
    """Probabilities over the last axis from log-likelihoods."""
    p = np.exp(loglik - loglik.max(axis=-1, keepdims=True))
    return p / p.sum(axis=-1, keepdims=True)


__all__ = ["LONGITUDINAL", "DriverEstimator"]
