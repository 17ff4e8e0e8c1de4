"""Analyses of held-out episodes, behind ``lc-eval --breakdown`` and ``lc-eval oracle --bound``.

- :class:`CollisionBreakdown`: why a driver crashes. A hook of the episode loop
  (:func:`lcsim.episodes.run_episodes`) that sorts every collision, at the moment of contact, into

  - ``trapped``: the ego rear-ends its leader while keeping lane, and in the last ``window_s`` seconds no
    allowed side lane had a gap of ``front_gap_m`` ahead and ``rear_gap_m`` behind (the trap closed
    before; avoiding it takes planning further ahead);
  - ``missed_gap``: the same, but such a side gap was there in that window;
  - ``late_change``: the ego hits a vehicle of the lane it is leaving while changing lanes (it started late);
  - ``short_gap``: the ego hits a vehicle of its target lane while changing lanes (the gap was too short);
  - ``hit_from_behind``: a vehicle runs into the ego while the ego keeps lane.

- :func:`oracle_bound`: what the scenario allows. For each held-out episode the omniscient search
  (:func:`lcsim.planning.search_episode`) looks for a sequence of decisions that reaches the end of the
  route without a collision; every sequence found is replayed from a fresh reset and must end in success,
  so "winnable" is proven. No policy can beat the winnable share: it is the ceiling of the success rate.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from lckit.pool import WorkerPool
from lcmodels.policy.evaluate import wilson_interval
from lcsim.config import ScenarioConfig
from lcsim.core import KEEP, LaneChangeCore, StepResult
from lcsim.envs import episode_seed
from lcsim.episodes import EpisodeHook
from lcsim.planning import replay, search_episode

COLLISION_KINDS = ("trapped", "missed_gap", "late_change", "short_gap", "hit_from_behind")


def side_gap_open(core: LaneChangeCore, front_gap_m: float, rear_gap_m: float) -> np.ndarray:
    """``(E,)`` whether an allowed lane change would land in a gap of the given size right now."""
    gaps = core.lane_gaps()
    ok = (gaps["front_gap"] >= front_gap_m) & (gaps["rear_gap"] >= rear_gap_m) & core.action_mask()
    ok[:, KEEP] = False
    return ok.any(axis=1)


def classify_collision(core: LaneChangeCore, e: int, was_changing: bool, recent_gap: bool) -> str:
    """The kind of environment ``e``'s collision (:data:`COLLISION_KINDS`), from the state at contact."""
    sim = core.sim
    other = int(sim.collision_with[e])
    changing = was_changing or bool(sim.ego_lc_active[e])
    if changing:
        return "short_gap" if sim.lane[e, other] == sim.target_lane[e, 0] else "late_change"
    if sim.x[e, other] < sim.x[e, 0]:
        return "hit_from_behind"
    return "missed_gap" if recent_gap else "trapped"


class CollisionBreakdown(EpisodeHook):
    """Counts the collisions of the episodes it watches by kind (:attr:`counts`, every kind present)."""

    def __init__(self, *, window_s: float = 5.0, front_gap_m: float = 12.0, rear_gap_m: float = 5.0) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self.window_s, self.front_gap_m, self.rear_gap_m = window_s, front_gap_m, rear_gap_m
        self.counts: dict[str, int] = dict.fromkeys(COLLISION_KINDS, 0)
        self._recent: list[collections.deque[bool]] = []
        self._changing: np.ndarray | None = None

    def start(self, core: LaneChangeCore, user_seeds: Sequence[int], driver: Callable[..., np.ndarray]) -> None:
        window = max(1, round(self.window_s / core.config.decision_period_s)) + 1  # + the decision of the contact
        self._recent = [collections.deque(maxlen=window) for _ in user_seeds]

    def before_step(self, core: LaneChangeCore, obs: dict[str, np.ndarray], mask: np.ndarray, actions: np.ndarray,
                    running: np.ndarray) -> None:
        for i, is_open in enumerate(side_gap_open(core, self.front_gap_m, self.rear_gap_m)):
            self._recent[i].append(bool(is_open))
        self._changing = core.sim.ego_lc_active.copy()

    def after_step(self, core: LaneChangeCore, result: StepResult, running: np.ndarray) -> None:
        assert self._changing is not None
        for i in np.flatnonzero(running & (result.outcome == "collision")):
            kind = classify_collision(core, i, bool(self._changing[i]), any(list(self._recent[i])[:-1]))
            self.counts[kind] += 1


def _search_one(job: tuple[dict[str, Any], int, int, int, int]) -> dict[str, Any]:
    config_dict, index, user_seed, memory, max_nodes = job
    config = ScenarioConfig.from_dict(config_dict)
    seed = episode_seed(user_seed)
    t0 = time.process_time()
    r = search_episode(config, seed, memory_decisions=memory, max_nodes=max_nodes)
    replayed = replay(config, seed, r.actions) if r.winnable else None
    return {"episode": index, "user_seed": user_seed, "seed": seed, "winnable": r.winnable,
            "replay_outcome": replayed, "nodes": r.nodes, "deepest_decision": r.deepest,
            "pruned": r.outcomes, "actions": r.actions if r.winnable else None,
            "cpu_s": round(time.process_time() - t0, 3)}  # fmt: skip


def oracle_bound(config: ScenarioConfig, user_seeds: Sequence[int], *, indices: Sequence[int] | None = None,
                 memory_decisions: int = 8, max_nodes: int = 200_000, workers: int = 1,
                 progress: Callable[[int, int], None] | None = None) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The share of the episodes ``user_seeds`` an omniscient driver can win, proven by replay.

    Args:
        indices: only these episodes (positions in ``user_seeds``); default all.
        memory_decisions, max_nodes: the search's merging and budget (:func:`lcsim.planning.search_episode`).
        workers: processes searching at once.

    Returns:
        ``(summary, per-episode rows)``: the summary has ``winnable``, ``winnable_rate`` with its Wilson
        interval, ``replayed_success`` (must equal ``winnable``), ``not_winnable_episodes``,
        ``undecided_episodes`` (budget exhausted), ``nodes_total``, ``cpu_s_total`` and ``wall_s``.
    """
    if min(memory_decisions, max_nodes, workers) < 1:
        raise ValueError("memory_decisions, max_nodes and workers must be >= 1")
    picked = list(range(len(user_seeds))) if indices is None else list(indices)
    if any(not 0 <= i < len(user_seeds) for i in picked):
        raise ValueError(f"episode indices must be in [0, {len(user_seeds)})")
    jobs = [(config.to_dict(), i, int(user_seeds[i]), memory_decisions, max_nodes) for i in picked]
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    if workers == 1:
        for job in jobs:
            rows.append(_search_one(job))
            if progress is not None:
                progress(len(rows), len(jobs))
    else:
        with WorkerPool(workers) as pool:
            rows += pool.map(_search_one, jobs, progress=progress)
    n = len(rows)
    won = sum(r["winnable"] is True for r in rows)
    lo, hi = wilson_interval(won, n)
    summary = {
        "episodes": n, "memory_decisions": memory_decisions, "winnable": won,
        "winnable_rate": won / n if n else float("nan"), "winnable_rate_ci95": [lo, hi],
        "replayed_success": sum(r["replay_outcome"] == "success" for r in rows),
        "not_winnable_episodes": [r["episode"] for r in rows if r["winnable"] is False],
        "undecided_episodes": [r["episode"] for r in rows if r["winnable"] is None],
        "nodes_total": sum(r["nodes"] for r in rows), "cpu_s_total": round(sum(r["cpu_s"] for r in rows), 1),
        "wall_s": round(time.perf_counter() - t0, 1), "workers": workers,
    }  # fmt: skip
    return summary, rows
