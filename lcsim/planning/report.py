"""What a decider thought at its last decision: the score of each candidate and, when asked, the futures it imagined.

Every decider of :mod:`lcsim.planning` gives a :class:`DecisionReport` after each call (``last_report``): for every
environment of the batch the score of each candidate decision (right / keep / left), the decision its driver
proposed, the one executed and whether the decider overrode the proposal. A decider that imagines futures keeps,
when asked (``imagined_paths = K``, default 0: off, nothing is kept), the ego's path in up to ``K`` of the futures it
imagined for each candidate (:class:`ImaginedPaths`). Keeping them only reads the imagined copies: the decisions are
the same with and without (a test holds it to that). The recorder writes the reports (``/planner/decision``) and
``lc-view`` draws them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_IMAGINED_FUTURES = 16
"""The most imagined futures per candidate whose paths a decider keeps (``imagined_paths``)."""


def check_imagined_paths(futures: int) -> int:
    """``futures`` as the number of imagined futures per candidate to keep the paths of: an int in
    ``[0, MAX_IMAGINED_FUTURES]`` (0: none); ``ValueError`` naming the setting otherwise."""
    whole = isinstance(futures, int | np.integer) and not isinstance(futures, bool)
    if not whole or not 0 <= futures <= MAX_IMAGINED_FUTURES:
        raise ValueError(f"imagined_paths must be an int in [0, {MAX_IMAGINED_FUTURES}] (futures kept per "
                         f"candidate; 0: none), got {futures!r}")  # fmt: skip
    return int(futures)


@dataclass(frozen=True, slots=True, kw_only=True)
class ImaginedPaths:
    """The ego's paths in imagined futures, packed: path ``p`` is ``xy[offsets[p] : offsets[p + 1]]``.

    A path starts where the ego is at the decision and has one point after each imagined decision (the
    candidate's, then those of the driver followed), up to the horizon or the decision its imagined episode ended
    in (a collision, leaving the road, the goal): ``horizon_decisions + 2`` points at most.
    """

    env: np.ndarray
    """``(P,)`` int64: the environment of the batch each path belongs to."""
    action: np.ndarray
    """``(P,)`` int64: the candidate decision it follows (0 right, 1 keep, 2 left)."""
    future: np.ndarray
    """``(P,)`` int64: which imagined future of that candidate (0 .. K-1; the same index is the same redrawn
    future for every candidate)."""
    survived: np.ndarray
    """``(P,)`` bool: no collision and no leaving the road in it."""
    offsets: np.ndarray
    """``(P + 1,)`` int64: where each path's points start in ``xy``; ``offsets[-1] == len(xy)``."""
    xy: np.ndarray
    """``(L, 2)`` float64: the points, world frame (m)."""

    def of(self, env: int) -> ImaginedPaths:
        """The paths of environment ``env`` alone (``env`` all ``env``, offsets from 0)."""
        rows = np.flatnonzero(self.env == env)
        counts = np.diff(self.offsets)[rows]
        points = np.concatenate([np.arange(self.offsets[r], self.offsets[r + 1]) for r in rows]) if len(rows) else (
            np.zeros(0, dtype=np.int64))  # fmt: skip
        return ImaginedPaths(env=self.env[rows], action=self.action[rows], future=self.future[rows],
                             survived=self.survived[rows], offsets=np.concatenate([[0], np.cumsum(counts)]),
                             xy=self.xy[points])  # fmt: skip


@dataclass(frozen=True, slots=True, kw_only=True)
class DecisionReport:
    """What a decider scored at its last call, for every environment ``e`` of the batch."""

    scores: np.ndarray
    """``(E, 3)`` float64: each candidate's score (right, keep, left); for the safety layer the share of its
    imagined futures the candidate survived, in ``[0, 1]``. NaN where the candidate was not scored (not allowed,
    or no choice to make: a lane change under way, an ended episode)."""
    proposed: np.ndarray
    """``(E,)`` int64: the decision the driver behind the decider proposed."""
    executed: np.ndarray
    """``(E,)`` int64: the decision executed."""
    overridden: np.ndarray
    """``(E,)`` bool: the decider executed another decision than the proposal because the proposal scored worse."""
    paths: ImaginedPaths | None = None
    """The ego's paths in the imagined futures kept (``imagined_paths``), else None."""

    @property
    def choice(self) -> np.ndarray:
        """``(E,)`` bool: the environments where the decider scored something (it had a choice)."""
        return ~np.isnan(self.scores).all(axis=1)


__all__ = ["MAX_IMAGINED_FUTURES", "DecisionReport", "ImaginedPaths", "check_imagined_paths"]
