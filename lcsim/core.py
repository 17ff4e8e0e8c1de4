"""The lane-change task on top of :class:`~lcsim.sim.HighwaySim`: decisions, rewards, outcomes, observations.

One :class:`LaneChangeCore` serves the single environment (E = 1), the native vector environment and
the stable-baselines3 adapter, so all three run the same code and agree bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from lcsim import kernel
from lcsim.config import LANE_SLOTS, ScenarioConfig
from lcsim.render import BevRenderer
from lcsim.sim import HighwaySim
from lcsim.threads import run_shards, shard_count

# Outcomes (info["outcome"]); "" while the episode runs.
RUNNING, SUCCESS, COLLISION, OFF_ROAD, TIMEOUT = "", "success", "collision", "off_road", "timeout"
OUTCOMES = (SUCCESS, COLLISION, OFF_ROAD, TIMEOUT)
_OUTCOME_OF_CODE = np.array([RUNNING, SUCCESS, COLLISION, OFF_ROAD, TIMEOUT], dtype=object)  # by kernel code
# Actions (Table I of the paper).
RIGHT, KEEP, LEFT = 0, 1, 2
ACTION_NAMES = ("right", "keep", "left")
# Columns of the `current` observation (ego row 0, then the neighbour slots), in the ego frame.
CURRENT_FEATURES = ("x_m", "y_m", "vx_mps", "vy_mps", "yaw_rad", "speed_mps", "lane", "target_lane", "present")
ACCEL_FEATURE = "accel_mps2"
"""The column ``ScenarioConfig.observe_acceleration`` appends to :data:`CURRENT_FEATURES`."""
REWARD_COMPONENTS = ("collision", "off_road", "forward", "success")


def current_features(config: ScenarioConfig) -> tuple[str, ...]:
    """The columns of the ``current`` observation in ``config``."""
    return CURRENT_FEATURES + ((ACCEL_FEATURE,) if config.observe_acceleration else ())


@lru_cache(maxsize=32)
def _vehicle_range(n: int) -> np.ndarray:
    """``np.arange(n)`` (int64), shared: callers must not modify it."""
    out = np.arange(n, dtype=np.int64)
    out.flags.writeable = False
    return out


@dataclass(slots=True)
class StepResult:
    """What one decision step returns for E environments (arrays of shape (E,) unless noted)."""

    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    outcome: np.ndarray  # object array of str
    components: dict[str, np.ndarray]


class LaneChangeCore:
    """E lane-change episodes: apply decisions, run ``steps_per_decision`` simulation steps, score them."""

    def __init__(self, config: ScenarioConfig, num_envs: int, *, autopilot_ego: bool = False,
                 threads: int | None = None) -> None:
        """``threads``: how many threads simulate, observe and draw the batch, each a contiguous shard of
        environments (the same bits however many); None: the process's default (:mod:`lcsim.threads`), 1: the
        calling thread only."""
        self.config = config
        self.sim = HighwaySim(config, num_envs, autopilot_ego=autopilot_ego, threads=threads)
        self.num_envs = num_envs
        self.renderer = None
        if config.render_image:
            extent = max(config.traffic.length_m, config.ego.length_m) + max(config.traffic.width_m, config.ego.width_m)
            self.renderer = BevRenderer(config.road, config.render, vehicle_extent_m=extent)
        self.k = config.num_neighbours
        # The observation's neighbour slots: (lane offset, ahead, rank) rows, or the K nearest.
        self._nearest_mode = config.neighbour_selection == "nearest"
        slots = LANE_SLOTS[: self.k] if not self._nearest_mode else ()
        self._slots = np.array([[o, int(a), r] for o, a, r in slots], dtype=np.int64).reshape(-1, 3)
        self._range2 = config.sensing_range_m ** 2
        self._num_features = len(current_features(config))
        self.milestone_x = np.asarray(config.reward.milestones) * config.route_length_m
        self.milestone_r = np.asarray(config.reward.milestone_rewards, dtype=np.float64)
        self._milestone_x = np.asarray(self.milestone_x, dtype=np.float64)
        self.next_milestone = np.zeros(num_envs, dtype=np.int64)
        self._refuse_invalid = config.invalid_lane_change == "refuse"
        self._code = np.zeros(num_envs, dtype=np.int64)  # the outcome by kernel code (kernel.OUT_RUNNING, ...)
        self.outcome = np.full(num_envs, RUNNING, dtype=object)
        self.seeds = np.zeros(num_envs, dtype=np.int64)

    # ---------------------------------------------------------------- episode
    def reset(self, env_ids: np.ndarray | list[int], seeds: list[int]) -> None:
        env_ids = np.asarray(env_ids, dtype=np.int64)
        self.sim.reset(env_ids, seeds)
        self.next_milestone[env_ids] = 0
        self._code[env_ids] = kernel.OUT_RUNNING
        self.outcome[env_ids] = RUNNING
        self.seeds[env_ids] = seeds

    def replicate(self, rows: np.ndarray) -> LaneChangeCore:
        """A core whose environments are copies of environments ``rows`` (repeats allowed) in their present state,
        episodes and all, without hooks or renderer (:meth:`HighwaySim.replicate`): the planner imagines the
        futures of several decisions of several environments in one batch."""
        rows = np.asarray(rows, dtype=np.int64)
        new = object.__new__(LaneChangeCore)
        new.__dict__.update(self.__dict__)
        new.sim, new.num_envs, new.renderer = self.sim.replicate(rows), len(rows), None
        for name in ("next_milestone", "_code", "outcome", "seeds"):
            setattr(new, name, getattr(self, name)[rows])
        return new

    def action_mask(self) -> np.ndarray:
        """``(E, 3)`` bool: right / keep / left. A change in progress allows only keep; no lane, no change."""
        sim = self.sim
        mask = np.empty((self.num_envs, 3), dtype=bool)
        kernel.action_mask(sim.vi, sim.eb, sim.road.num_lanes, sim.autopilot_ego, mask)
        return mask

    def step(self, actions: np.ndarray) -> StepResult:
        """Apply one decision per environment and simulate until the next decision.

        An action during a lane change in progress is ignored (the change runs to its end). A change
        towards a lane that does not exist is refused with the ``off_road`` reward, or, with
        ``invalid_lane_change="leave_road"``, carried out: the ego leaves the road and the episode ends.
        Environments whose episode ends inside the decision period are frozen at that simulation step.
        """
        return self._step(actions, None)

    def step_observe(self, actions: np.ndarray) -> tuple[StepResult, dict[str, np.ndarray]]:
        """:meth:`step`, then :meth:`observe` of every environment: the same results, in one pass of the threads
        (each shard of environments is observed by the thread that simulated it, as soon as it has)."""
        _, cur, hist, image, observe = self._observe_plan(_vehicle_range(self.num_envs), image=True)
        res = self._step(actions, observe)
        obs = {"current": cur, "history": hist}
        if image is not None:
            obs["image"] = image
        return res, obs

    def _step(self, actions: np.ndarray, then: Callable[[int, int], None] | None) -> StepResult:
        sim, cfg, e = self.sim, self.config, self.num_envs
        actions = np.asarray(actions, dtype=np.int64).reshape(e)
        if actions.min() < 0 or actions.max() > 2:
            raise ValueError(f"actions must be in {{0, 1, 2}} (right, keep, left), got {actions.tolist()}")
        refused, x_before = np.empty(e, dtype=bool), np.empty(e)
        code = self._code
        kernel.begin_decision(actions, self._refuse_invalid, code, sim.params, sim.iparams, sim.vf, sim.vi, sim.ef,
                              sim.eb, x_before, refused)
        # Every environment runs to the next decision or to its first event (contact, road edge, route's end),
        # where it is frozen for the rest of the period; environments already finished stay frozen. (The
        # observation reads none of what the scoring below writes, so it may come first.)
        sim.advance(cfg.steps_per_decision, stop_on_event=True, then=then)
        components, reward = np.empty((len(REWARD_COMPONENTS), e)), np.empty(e)
        terminated, truncated = np.empty(e, dtype=bool), np.empty(e, dtype=bool)
        kernel.end_decision(code, refused, x_before, self.next_milestone, self._milestone_x, self.milestone_r,
                            sim.params, sim.vf, sim.ef, sim.ei, sim.eb, components, reward, terminated, truncated)
        self.outcome[:] = _OUTCOME_OF_CODE.take(code)
        return StepResult(reward, terminated, truncated, self.outcome.copy(), dict(zip(REWARD_COMPONENTS, components,
                                                                                        strict=True)))

    def lane_gaps(self) -> dict[str, np.ndarray]:
        """Exact gaps around the ego in the lanes right of, at and left of its (target) lane.

        Privileged information (a planner with perfect perception), used by the rule-based driver.
        Returns ``front_gap``, ``rear_gap`` (m, bumper to bumper; inf when the lane is empty that way,
        -inf when the lane does not exist), ``front_speed``, ``rear_speed`` (m/s), each ``(E, 3)``.
        """
        out = np.empty((4, self.num_envs, 3))
        kernel.lane_gaps(self.sim.vf, self.sim.vi, self.sim.road.num_lanes, out)
        return dict(zip(("front_gap", "rear_gap", "front_speed", "rear_speed"), out, strict=True))

    # ------------------------------------------------------------ observation
    def neighbours(self, ids: np.ndarray) -> np.ndarray:
        """``(len(ids), K)`` the vehicles of the observation's K slots, -1 where a slot is empty.

        As ``config.neighbour_selection`` says: ``lanes``, the slots of :data:`lcsim.config.LANE_SLOTS`
        (leader and follower in the ego's target lane and the lanes beside it, then the second leaders
        beside it); ``nearest``, the K nearest vehicles, nearest first. Only vehicles within
        ``sensing_range_m`` of the ego are shown.
        """
        return self._observe(np.asarray(ids, dtype=np.int64))[0]

    def _observe(self, ids: np.ndarray, image: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """The slots' vehicles, ``current``, ``history`` and (``image`` and a renderer) the images of environments
        ``ids``, in contiguous shards of environments on the simulator's threads (one compiled call per shard)."""
        *out, shard = self._observe_plan(ids, image)
        run_shards(shard, len(ids), shard_count(len(ids), self.sim.threads))
        return tuple(out)  # type: ignore[return-value]

    def _observe_plan(self, ids: np.ndarray, image: bool
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, Callable[[int, int], None]]:
        """The arrays :meth:`_observe` fills, and ``shard(i, j)`` that fills their rows ``i .. j - 1`` (environments
        ``ids[i:j]``) from the present state."""
        sim, b = self.sim, len(ids)
        every = ids is _vehicle_range(self.num_envs)  # (every environment, in order: nothing to check or gather)
        if b and not every and (ids.min() < 0 or ids.max() >= self.num_envs):
            raise IndexError(f"environment ids must be in [0, {self.num_envs}), got {ids.tolist()}")
        nb = np.empty((b, self.k), dtype=np.int64)
        cur = np.empty((b, 1 + self.k, self._num_features), dtype=np.float32)
        hist = np.empty((b, self.k, sim.history_len, 3), dtype=np.float32)
        renderer = self.renderer if image else None
        images = None
        if renderer is not None:
            poses = [a if every else a[ids] for a in (sim.x, sim.y, sim.yaw, sim.length, sim.width)]
            images = renderer.empty(b)
            extent = renderer.extent(poses[3], poses[4])

        def shard(i: int, j: int) -> None:
            whole = i == 0 and j == b  # (one shard: the arrays themselves)
            kernel.observe(ids if whole else ids[i:j], self._nearest_mode, self._slots, self._range2,
                           self.config.observe_acceleration, sim.road.num_lanes, sim.vf, sim.vi, sim.hist,
                           sim.hist_ptr, sim.hist_count, nb if whole else nb[i:j], cur if whole else cur[i:j],
                           hist if whole else hist[i:j])
            if renderer is not None:
                renderer.draw(images if whole else images[i:j], *(poses if whole else [a[i:j] for a in poses]),
                              extent)

        return nb, cur, hist, images, shard

    def observe(self, ids: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Batched observation of environments ``ids`` (all by default), B = len(ids).

        Returns ``current`` (B, 1+K, 9) with columns :data:`CURRENT_FEATURES` in the ego frame (row 0 is
        the ego: its own velocity, heading to the road, lane and target lane; a tenth column, each
        vehicle's own acceleration, with ``observe_acceleration``), ``history`` (B, K, H, 3):
        the last H positions of the same K vehicles in the ego frame of the current step, oldest first,
        with a validity flag, and ``image`` (B, 3, S, S) uint8 when rendering is on.
        """
        ids = _vehicle_range(self.num_envs) if ids is None else np.asarray(ids, dtype=np.int64)
        _, cur, hist, image = self._observe(ids, image=True)
        obs = {"current": cur, "history": hist}
        if image is not None:
            obs["image"] = image
        return obs
