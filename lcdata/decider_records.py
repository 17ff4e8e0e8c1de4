"""What the driver saw and thought at a decision: ``/prediction`` and ``/planner/decision``, written and read.

``/prediction`` (``lc.Prediction``) holds the trajectories a policy's predictor gave it; ``/planner/decision``
(``lc.PlannerDecision``) what a planning driver (the safety layer, :class:`lcsim.planning.DecisionReport`) scored
for each candidate decision at a decision where it had a choice, the decision proposed and the one executed, and
the ego's path in the imagined futures it was asked to keep. :class:`DeciderStreams` writes them (a part of
:class:`lcdata.writer.EpisodeWriter`); :func:`planner_decisions` and :func:`imagined_paths` read them back into
tables, refusing a message whose counts do not add up before anything is allocated from them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from lcdata import topics
from lcdata.proto import lc_pb2
from lcdata.wire import f_double, f_packed, f_varint

if TYPE_CHECKING:
    from lcsim.planning.report import ImaginedPaths

CANDIDATES = ("right", "keep", "left")
"""The candidate decisions, by action index (0 right, 1 keep, 2 left)."""
DECISION_COLUMNS = ["step", "t", "decision", "score_right", "score_keep", "score_left", "proposed", "executed",
                    "overridden", "paths"]  # fmt: skip
"""The columns of :func:`planner_decisions` (``paths``: the imagined paths kept at the decision)."""
IMAGINED_PATH_COLUMNS = ["step", "t", "path", "action", "future", "survived", "k", "x", "y"]
"""The columns of :func:`imagined_paths`: one row per point, ``k`` = 0 at the decision."""


class DeciderStreams:
    """``write_prediction`` and ``write_planner_decision`` for a writer with ``_write(topic, t_s, data)``."""

    def _write(self, topic: str, t_s: float, data: bytes) -> None:
        raise NotImplementedError

    def write_prediction(self, step: int, t_s: float, vehicle_ids: np.ndarray, xy: np.ndarray) -> None:
        """``/prediction``: ``vehicle_ids`` (S,) (-1 = empty slot), ``xy`` (S, F, 2) world frame."""
        xy = np.asarray(xy, dtype=np.float64)
        if xy.ndim != 3 or xy.shape[2] != 2 or xy.shape[0] != len(vehicle_ids):
            raise ValueError(f"xy must be (S, F, 2) with S = len(vehicle_ids), got {xy.shape}")
        data = b"".join(
            (
                f_varint(1, step), f_double(2, t_s), f_varint(3, xy.shape[1]),
                f_varint(4, xy.shape[0]), f_packed(5, vehicle_ids, "<i4"), f_packed(6, xy, "<f8"),
            )
        )  # fmt: skip
        self._write(topics.PREDICTION, t_s, data)

    def write_planner_decision(self, step: int, t_s: float, *, decision: int, scores: Sequence[float], proposed: int,
                               executed: int, overridden: bool, paths: ImaginedPaths | None = None) -> None:  # fmt: skip
        """``/planner/decision``: ``scores`` (3,) of right, keep, left (NaN: not scored), the decisions proposed and
        executed (0 right, 1 keep, 2 left), whether the planner overrode the proposal, and the imagined paths of
        this environment (:meth:`lcsim.planning.ImaginedPaths.of`) or None."""
        scores = np.asarray(scores, dtype=np.float64)
        if scores.shape != (3,):
            raise ValueError(f"scores must be (3,) (right, keep, left), got {scores.shape}")
        if not (0 <= proposed <= 2 and 0 <= executed <= 2):
            raise ValueError(f"proposed and executed must be 0, 1 or 2, got {proposed} and {executed}")
        msg = lc_pb2.PlannerDecision(step=int(step), t=float(t_s), decision=int(decision), scores=scores.tolist(),
                                     proposed=int(proposed), executed=int(executed), overridden=bool(overridden))  # fmt: skip
        if paths is not None and len(paths.action):
            offsets, xy = np.asarray(paths.offsets, dtype=np.int64), np.asarray(paths.xy, dtype=np.float64)
            n = len(paths.action)
            if len(offsets) != n + 1 or offsets[-1] != len(xy) or xy.shape[1:] != (2,):
                raise ValueError(f"imagined paths: {n} paths need {n + 1} offsets ending at the {len(xy)} points "
                                 f"(L, 2), got {len(offsets)} offsets and points {xy.shape}")  # fmt: skip
            msg.path_action.extend(np.asarray(paths.action).tolist())
            msg.path_future.extend(np.asarray(paths.future).tolist())
            msg.path_survived.extend(np.asarray(paths.survived, dtype=bool).tolist())
            msg.path_offsets.extend(offsets.tolist())
            msg.path_xy.extend(xy.ravel().tolist())
        self._write(topics.PLANNER_DECISION, t_s, msg.SerializeToString())


def _checked(m: lc_pb2.PlannerDecision) -> np.ndarray:
    """The point counts of ``m``'s paths, ``ValueError`` when its fields do not describe a decision and its paths."""
    if len(m.scores) != 3:
        raise ValueError(f"/planner/decision at step {m.step}: {len(m.scores)} scores, not 3 (right, keep, left)")
    if not (0 <= m.proposed <= 2 and 0 <= m.executed <= 2):
        raise ValueError(f"/planner/decision at step {m.step}: decisions {m.proposed} and {m.executed} are not "
                         "0, 1 or 2")
    n = len(m.path_action)
    if not n and (len(m.path_future) or len(m.path_survived) or len(m.path_offsets) > 1 or len(m.path_xy)):
        raise ValueError(f"/planner/decision at step {m.step}: path fields without paths")
    if not n:
        return np.zeros(0, dtype=np.int64)
    if len(m.path_future) != n or len(m.path_survived) != n or len(m.path_offsets) != n + 1:
        raise ValueError(f"/planner/decision at step {m.step}: {n} paths with {len(m.path_future)} futures, "
                         f"{len(m.path_survived)} outcomes and {len(m.path_offsets)} offsets")  # fmt: skip
    offsets = np.asarray(m.path_offsets, dtype=np.int64)
    counts = np.diff(offsets)
    actions, futures = np.asarray(m.path_action), np.asarray(m.path_future)
    if offsets[0] != 0 or (counts < 0).any() or 2 * offsets[-1] != len(m.path_xy):
        raise ValueError(f"/planner/decision at step {m.step}: path offsets that do not run from 0 up to the "
                         f"{len(m.path_xy) // 2} points")  # fmt: skip
    if ((actions < 0) | (actions > 2)).any() or (futures < 0).any():
        raise ValueError(f"/planner/decision at step {m.step}: a path of a candidate other than 0, 1, 2")
    return counts


def _messages(payloads: Sequence[bytes | memoryview]) -> list[tuple[lc_pb2.PlannerDecision, np.ndarray]]:
    out = []
    for p in payloads:
        m = lc_pb2.PlannerDecision.FromString(p)
        out.append((m, _checked(m)))
    return out


def planner_decisions(payloads: Sequence[bytes | memoryview]) -> pd.DataFrame:
    """``/planner/decision`` messages as one row per decision: :data:`DECISION_COLUMNS` (scores NaN where a
    candidate was not scored). ``ValueError`` for a message whose fields do not add up."""
    rows = _messages(payloads)
    scores = np.array([list(m.scores) for m, _ in rows], dtype=np.float64).reshape(-1, 3)
    data = {
        "step": np.array([m.step for m, _ in rows], dtype=np.int64),
        "t": np.array([m.t for m, _ in rows], dtype=np.float64),
        "decision": np.array([m.decision for m, _ in rows], dtype=np.int64),
        **{f"score_{name}": scores[:, k] for k, name in enumerate(CANDIDATES)},
        "proposed": np.array([m.proposed for m, _ in rows], dtype=np.int64),
        "executed": np.array([m.executed for m, _ in rows], dtype=np.int64),
        "overridden": np.array([m.overridden for m, _ in rows], dtype=bool),
        "paths": np.array([len(c) for _, c in rows], dtype=np.int64),
    }
    return pd.DataFrame(data, columns=DECISION_COLUMNS)


def imagined_paths(payloads: Sequence[bytes | memoryview]) -> pd.DataFrame:
    """The imagined paths of ``/planner/decision`` messages in long form: :data:`IMAGINED_PATH_COLUMNS`, one row per
    point (``path``: its index at the decision, ``k``: the point's, 0 at the decision). ``ValueError`` for a
    message whose fields do not add up (checked before the table is made)."""
    parts = []
    for m, counts in _messages(payloads):
        if not len(counts):
            continue
        xy = np.asarray(m.path_xy, dtype=np.float64).reshape(-1, 2)
        path = np.repeat(np.arange(len(counts)), counts)
        starts = np.repeat(np.asarray(m.path_offsets[:-1], dtype=np.int64), counts)
        parts.append(pd.DataFrame({
            "step": np.full(len(xy), m.step, dtype=np.int64), "t": m.t, "path": path,
            "action": np.asarray(m.path_action, dtype=np.int64)[path],
            "future": np.asarray(m.path_future, dtype=np.int64)[path],
            "survived": np.asarray(m.path_survived, dtype=bool)[path],
            "k": np.arange(len(xy)) - starts, "x": xy[:, 0], "y": xy[:, 1],
        }, columns=IMAGINED_PATH_COLUMNS))  # fmt: skip
    if not parts:
        empty = {name: np.zeros(0, dtype=bool if name == "survived" else np.float64 if name in ("t", "x", "y") else np.int64)
                 for name in IMAGINED_PATH_COLUMNS}  # fmt: skip
        return pd.DataFrame(empty, columns=IMAGINED_PATH_COLUMNS)
    return pd.concat(parts, ignore_index=True)


__all__ = ["CANDIDATES", "DECISION_COLUMNS", "IMAGINED_PATH_COLUMNS", "DeciderStreams", "imagined_paths",
           "planner_decisions"]  # fmt: skip
