"""The project's statistics, in one place and on well-kept libraries (scipy, rliable); nothing here is
derived by hand that those provide.

Which interval for which question:

- one evaluation (one policy, one set of episodes): the **Wilson** score interval of a rate over episodes,
  :func:`wilson_interval`;
- the same recipe over several training seeds: the **t** interval of the mean over seeds,
  :func:`t_interval` (two seeds give a wide one: that is the honest width);
- a method over several seeds and scenarios: the interquartile mean and mean of normalised scores with
  **stratified-bootstrap** intervals (rliable; Agarwal et al., "Deep RL at the Edge of the Statistical
  Precipice", 2021), :func:`aggregate_scores`;
- "A beats B": **McNemar's exact test** on the per-episode outcomes of the same episodes, :func:`mcnemar`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

CONFIDENCE = 0.95


def wilson_interval(k: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of the proportion ``k / n`` (``(nan, nan)`` when ``n == 0``)."""
    from scipy.stats import binomtest

    if n == 0:
        return (float("nan"), float("nan"))
    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return (float(ci.low), float(ci.high))


def normal_interval(values: Sequence[float], confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Normal-approximation interval of the mean of many values (episodes' returns): ``(nan, nan)`` for
    fewer than two."""
    from scipy.stats import norm

    v = np.asarray(values, dtype=np.float64)
    if len(v) < 2:
        return (float("nan"), float("nan"))
    half = float(norm.ppf(0.5 + confidence / 2)) * float(v.std(ddof=1)) / math.sqrt(len(v))
    return (float(v.mean()) - half, float(v.mean()) + half)


def t_interval(values: Sequence[float], confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Student-t interval of the mean of a few values (one per training seed): ``(nan, nan)`` for fewer
    than two."""
    from scipy.stats import t

    v = np.asarray(values, dtype=np.float64)
    if len(v) < 2:
        return (float("nan"), float("nan"))
    sem = float(v.std(ddof=1)) / math.sqrt(len(v))
    if sem == 0.0:
        return (float(v.mean()), float(v.mean()))
    lo, hi = t.interval(confidence, len(v) - 1, loc=float(v.mean()), scale=sem)
    return (float(lo), float(hi))


@dataclass(frozen=True, slots=True)
class McNemar:
    """McNemar's exact test of two drivers on the same episodes."""

    n: int
    """Episodes compared."""
    only_a: int
    """Episodes A won and B did not."""
    only_b: int
    """Episodes B won and A did not."""
    p_value: float
    """Two-sided exact p-value (binomial test of ``only_a`` out of ``only_a + only_b`` at 1/2)."""

    @property
    def p_text(self) -> str:
        """``p = 0.012``, or ``p < 1e-300`` where the p-value underflows."""
        return "p < 1e-300" if self.p_value < 1e-300 else f"p = {self.p_value:.2g}"

    def verdict(self, a: str = "A", b: str = "B", alpha: float = 0.05) -> str:
        """One phrase: which wins at level ``alpha``, or that the difference is not significant."""
        if self.p_value < alpha and self.only_a != self.only_b:
            winner, loser = (a, b) if self.only_a > self.only_b else (b, a)
            return f"{winner} beats {loser} (McNemar {self.p_text})"
        return f"no significant difference (McNemar {self.p_text})"

    def as_dict(self) -> dict[str, Any]:
        return {"n": self.n, "only_a": self.only_a, "only_b": self.only_b, "p_value": self.p_value}


def mcnemar(won_a: Sequence[bool] | np.ndarray, won_b: Sequence[bool] | np.ndarray) -> McNemar:
    """McNemar's exact test on paired per-episode outcomes (``won_a[i]``, ``won_b[i]``: the same episode).

    ``ValueError`` when the two are not the same length (they must be the same episodes)."""
    from scipy.stats import binomtest

    a, b = np.asarray(won_a, dtype=bool), np.asarray(won_b, dtype=bool)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"McNemar's test needs the same episodes for both: got {a.shape} and {b.shape}")
    only_a, only_b = int((a & ~b).sum()), int((b & ~a).sum())
    p = 1.0 if only_a + only_b == 0 else float(binomtest(only_a, only_a + only_b, 0.5).pvalue)
    return McNemar(n=len(a), only_a=only_a, only_b=only_b, p_value=min(1.0, p))


AGGREGATES = ("iqm", "mean")


def aggregate_scores(scores: np.ndarray, *, reps: int = 20_000, seed: int = 0,
                     confidence: float = CONFIDENCE) -> dict[str, dict[str, Any]]:
    """Interquartile mean and mean of normalised scores over runs and scenarios, with rliable's
    stratified-bootstrap intervals (runs resampled within each scenario).

    Args:
        scores: ``(runs, scenarios)`` normalised scores (a run: one training seed of one method).

    Returns:
        ``{"iqm": {"value", "ci95", "runs", "scenarios", "reps"}, "mean": {...}}``; ``ci95`` is ``None`` with
        one run, where the bootstrap over runs has nothing to resample.
    """
    from rliable import library as rly
    from rliable import metrics

    s = np.asarray(scores, dtype=np.float64)
    if s.ndim != 2 or s.size == 0 or not np.isfinite(s).all():
        raise ValueError(f"scores must be a finite (runs, scenarios) array, got shape {s.shape}")

    def func(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x), metrics.aggregate_mean(x)])

    point = func(s)
    intervals: list[list[float] | None] = [None, None]
    if s.shape[0] > 1:
        # rliable's stratified resampling draws from numpy's global generator whatever random_state says:
        # seed it for this call alone, so the same scores give the same interval, and restore it after
        state = np.random.get_state()  # noqa: NPY002 (rliable draws from it)
        np.random.seed(seed)  # noqa: NPY002
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # arch's notice about RandomState, which rliable passes
                _, ci = rly.get_interval_estimates({"m": s}, func, reps=reps, confidence_interval_size=confidence,
                                                   random_state=np.random.RandomState(seed))
        finally:
            np.random.set_state(state)  # noqa: NPY002
        intervals = [[float(ci["m"][0, i]), float(ci["m"][1, i])] for i in range(2)]
    meta = {"runs": int(s.shape[0]), "scenarios": int(s.shape[1]), "reps": reps if s.shape[0] > 1 else 0}
    return {k: {"value": float(point[i]), "ci95": intervals[i], **meta} for i, k in enumerate(AGGREGATES)}


__all__ = [
    "CONFIDENCE",
    "McNemar",
    "aggregate_scores",
    "mcnemar",
    "normal_interval",
    "t_interval",
    "wilson_interval",
]
