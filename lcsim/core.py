"""The lane-change task on top of :class:`~lcsim.sim.HighwaySim`: decisions, rewards, outcomes, observations.

One :class:`LaneChangeCore` serves the single environment (E = 1), the native vector environment and
the stable-baselines3 adapter, so all three run the same code and agree bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from lcsim.config import LANE_SLOTS, ScenarioConfig
from lcsim.render import BevRenderer
from lcsim.sim import HighwaySim

# Outcomes (info["outcome"]); "" while the episode runs.
RUNNING, SUCCESS, COLLISION, OFF_ROAD, TIMEOUT = "", "success", "collision", "off_road", "timeout"
OUTCOMES = (SUCCESS, COLLISION, OFF_ROAD, TIMEOUT)
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


def _k_smallest(a: np.ndarray, k: int) -> np.ndarray:
    """``np.argsort(a, axis=1, kind="stable")[:, :k]`` for a 2-D float array, via a partition on large batches.

    The k smallest of each row are found by ``argpartition`` and ordered by (value, index); rows with a
    tie at the k-th value (where the partition may pick a different index) are sorted in full.
    """
    e, n = a.shape
    if e < 8 or k >= n:
        return np.argsort(a, axis=1, kind="stable")[:, :k]
    part = np.sort(np.argpartition(a, k - 1, axis=1)[:, :k], axis=1)  # the k smallest, by index
    vals = np.take_along_axis(a, part, axis=1)
    out = np.take_along_axis(part, np.argsort(vals, axis=1, kind="stable"), axis=1)
    ties = np.flatnonzero((a <= vals.max(axis=1, keepdims=True)).sum(axis=1) != k)
    if ties.size:
        out[ties] = np.argsort(a[ties], axis=1, kind="stable")[:, :k]
    return out


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

    def __init__(self, config: ScenarioConfig, num_envs: int, *, autopilot_ego: bool = False) -> None:
        self.config = config
        self.sim = HighwaySim(config, num_envs, autopilot_ego=autopilot_ego)
        self.num_envs = num_envs
        self.renderer = None
        if config.render_image:
            extent = max(config.traffic.length_m, config.ego.length_m) + max(config.traffic.width_m, config.ego.width_m)
            self.renderer = BevRenderer(config.road, config.render, vehicle_extent_m=extent)
        self.k = config.num_neighbours
        # Lane slots: how many members each (lane offset, ahead) search must return.
        self._lane_searches: dict[tuple[int, bool], int] = {}
        for offset, ahead, rank in LANE_SLOTS[: self.k]:
            self._lane_searches[(offset, ahead)] = max(rank, self._lane_searches.get((offset, ahead), 0))
        self.milestone_x = np.asarray(config.reward.milestones) * config.route_length_m
        self.milestone_r = np.asarray(config.reward.milestone_rewards)
        self._next_x = np.append(self.milestone_x, np.inf)  # indexed by next_milestone: none left, none hit
        self.next_milestone = np.zeros(num_envs, dtype=np.int64)
        self.outcome = np.full(num_envs, RUNNING, dtype=object)
        self.seeds = np.zeros(num_envs, dtype=np.int64)

    # ---------------------------------------------------------------- episode
    def reset(self, env_ids: np.ndarray | list[int], seeds: list[int]) -> None:
        env_ids = np.asarray(env_ids, dtype=np.int64)
        self.sim.reset(env_ids, seeds)
        self.next_milestone[env_ids] = 0
        self.outcome[env_ids] = RUNNING
        self.seeds[env_ids] = seeds

    def action_mask(self) -> np.ndarray:
        """``(E, 3)`` bool: right / keep / left. A change in progress allows only keep; no lane, no change."""
        sim = self.sim
        lane = sim.target_lane[:, 0]
        idle = ~sim.ego_lc_active if not sim.autopilot_ego else np.ones(self.num_envs, dtype=bool)
        mask = np.ones((self.num_envs, 3), dtype=bool)
        mask[:, RIGHT] = idle & (lane > 0)
        mask[:, LEFT] = idle & (lane < sim.road.num_lanes - 1)
        return mask

    def step(self, actions: np.ndarray) -> StepResult:
        """Apply one decision per environment and simulate until the next decision.

        An action during a lane change in progress is ignored (the change runs to its end). A change
        towards a lane that does not exist is refused with the ``off_road`` reward, or, with
        ``invalid_lane_change="leave_road"``, carried out: the ego leaves the road and the episode ends.
        Environments whose episode ends inside the decision period are frozen at that simulation step.
        """
        sim, cfg = self.sim, self.config
        actions = np.asarray(actions, dtype=np.int64).reshape(self.num_envs)
        if ((actions < 0) | (actions > 2)).any():
            raise ValueError(f"actions must be in {{0, 1, 2}} (right, keep, left), got {actions.tolist()}")
        refused = np.zeros(self.num_envs, dtype=bool)
        if not sim.autopilot_ego:
            change = actions != KEEP
            direction = np.where(actions == LEFT, 1, -1)
            if cfg.invalid_lane_change == "refuse":
                target = sim.target_lane[:, 0] + direction
                refused = change & ~sim.ego_lc_active & (self.outcome == RUNNING) & (
                    (target < 0) | (target >= sim.road.num_lanes))
                change &= ~refused
            sim.start_lane_change(change, direction)
        x_before = sim.x[:, 0].copy()
        done = self.outcome != RUNNING  # environments already finished stay frozen
        sim.frozen[:] = done
        # Every environment runs to the next decision or to its first event (contact, road edge, route's end),
        # where it is frozen for the rest of the period.
        sim.advance(cfg.steps_per_decision, stop_on_event=True)
        collided = ~done & (sim.collision_with >= 0)
        left_road = ~done & ~collided & sim.off_road
        succeeded = ~done & ~collided & ~left_road & (sim.x[:, 0] >= cfg.route_length_m)
        if collided.any() or left_road.any() or succeeded.any():
            self.outcome[collided] = COLLISION
            self.outcome[left_road] = OFF_ROAD
            self.outcome[succeeded] = SUCCESS
        sim.frozen[:] = False
        progress = sim.x[:, 0] - x_before
        rc = cfg.reward
        milestone_reward = np.zeros(self.num_envs)
        reached = sim.x[:, 0]
        hit = ~(collided | left_road) & (reached >= self._next_x.take(self.next_milestone))
        while hit.any():  # milestones in order, each once (a short route can pass two in one decision)
            milestone_reward += np.where(hit, self.milestone_r.take(self.next_milestone, mode="clip"), 0.0)
            self.next_milestone += hit
            hit &= reached >= self._next_x.take(self.next_milestone)
        components = {
            "collision": np.where(collided, rc.collision, 0.0),
            "off_road": np.where(left_road | refused, rc.off_road, 0.0),
            "forward": rc.forward_per_m * progress,
            "success": milestone_reward,
        }
        reward = components["collision"] + components["off_road"] + components["forward"] + components["success"]
        terminated = self.outcome != RUNNING
        timeout = ~terminated & (sim.t_s >= cfg.time_limit_s - 1e-9)
        self.outcome[timeout] = TIMEOUT
        return StepResult(reward, terminated.copy(), timeout, self.outcome.copy(), components)

    def lane_gaps(self) -> dict[str, np.ndarray]:
        """Exact gaps around the ego in the lanes right of, at and left of its (target) lane.

        Privileged information (a planner with perfect perception), used by the rule-based driver.
        Returns ``front_gap``, ``rear_gap`` (m, bumper to bumper; inf when the lane is empty that way,
        -inf when the lane does not exist), ``front_speed``, ``rear_speed`` (m/s), each ``(E, 3)``.
        """
        sim = self.sim
        index = sim.index
        assert index is not None
        num_lanes = sim.road.num_lanes
        rows = np.arange(self.num_envs)[:, None]
        lanes = sim.target_lane[:, 0][:, None] + np.array([-1, 0, 1])[None, :]  # (E, 3)
        valid = (lanes >= 0) & (lanes < num_lanes)
        ego = np.zeros(3, dtype=np.int64)
        out: dict[str, np.ndarray] = {}
        ego_x, ego_len = sim.x[:, 0][:, None], sim.length[:, 0][:, None]
        for name, ahead, sign in (("front", True, 1.0), ("rear", False, -1.0)):
            veh = index.neighbour_in_lane(lanes, ahead, vehicles=ego)  # (E, 3), -1 when none or no lane
            found = veh >= 0
            v = np.maximum(veh, 0)
            gap = sign * (sim.x[rows, v] - ego_x) - 0.5 * (ego_len + sim.length[rows, v])
            out[f"{name}_gap"] = np.where(valid, np.where(found, gap, np.inf), -np.inf)
            out[f"{name}_speed"] = np.where(found & valid, sim.speed[rows, v], 0.0)
        return out

    # ------------------------------------------------------------ observation
    def neighbours(self, ids: np.ndarray) -> np.ndarray:
        """``(len(ids), K)`` the vehicles of the observation's K slots, -1 where a slot is empty.

        As ``config.neighbour_selection`` says: ``lanes``, the slots of :data:`lcsim.config.LANE_SLOTS`
        (leader and follower in the ego's target lane and the lanes beside it, then the second leaders
        beside it); ``nearest``, the K nearest vehicles, nearest first. Only vehicles within
        ``sensing_range_m`` of the ego are shown.
        """
        if self.config.neighbour_selection == "nearest":
            return self._nearest_neighbours(ids)
        if self.num_envs == 1:
            return self._lane_neighbours_one()
        return self._lane_neighbours(ids)

    def _lane_neighbours(self, ids: np.ndarray) -> np.ndarray:
        sim = self.sim
        index = sim.index
        assert index is not None
        n = sim.num_vehicles
        ego = ids * n  # flat index of each ego into (E, N)
        ego_lane = sim.target_lane.take(ego)
        found: dict[tuple[int, bool, int], np.ndarray] = {}
        out = np.empty((len(ids), self.k), dtype=np.int64)
        for j, (offset, ahead, rank) in enumerate(LANE_SLOTS[: self.k]):
            start = ego if rank == 1 else found[(offset, ahead, rank - 1)]
            veh = index.neighbour_flat(np.maximum(start, 0), ego_lane + offset, ahead)
            veh[start < 0] = -1
            found[(offset, ahead, rank)] = out[:, j] = veh
        present = out >= 0
        flat = np.maximum(out, 0)
        d2 = (sim.x.take(flat) - sim.x.take(ego)[:, None]) ** 2 + (sim.y.take(flat) - sim.y.take(ego)[:, None]) ** 2
        present &= d2 <= self.config.sensing_range_m ** 2
        return np.where(present, out - ego[:, None], -1)

    def _lane_neighbours_one(self) -> np.ndarray:
        """:meth:`_lane_neighbours` of a single environment on Python scalars (same result, fewer calls)."""
        sim = self.sim
        index = sim.index
        assert index is not None
        lane = sim.target_lane.item(0)
        found = {key: index.lane_members_one(0, lane + key[0], key[1], count)
                 for key, count in self._lane_searches.items()}
        x, y = sim.x, sim.y
        ex, ey, r2 = x.item(0), y.item(0), self.config.sensing_range_m ** 2
        out = []
        for offset, ahead, rank in LANE_SLOTS[: self.k]:
            members = found[(offset, ahead)]
            v = members[rank - 1] if len(members) >= rank else -1
            if v >= 0:
                dx, dy = x.item(v) - ex, y.item(v) - ey
                if dx * dx + dy * dy > r2:  # the operations of the batched test, in the same order
                    v = -1
            out.append(v)
        return np.array([out], dtype=np.int64)

    def _nearest_neighbours(self, ids: np.ndarray) -> np.ndarray:
        sim = self.sim
        n = sim.num_vehicles
        ego = (ids * n)[:, None]  # flat index of each ego into (E, N)
        flat = ego + _vehicle_range(n)
        x, y = sim.x.take(flat), sim.y.take(flat)
        d2 = (x - sim.x.take(ego)) ** 2 + (y - sim.y.take(ego)) ** 2
        d2[:, 0] = np.inf
        k = min(self.k, n - 1)
        order = _k_smallest(d2, k)
        near = d2.take(order + _vehicle_range(len(ids))[:, None] * n) <= self.config.sensing_range_m ** 2
        out = np.full((len(ids), self.k), -1, dtype=np.int64)
        out[:, :k] = np.where(near, order, -1)
        return out

    def observe(self, ids: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Batched observation of environments ``ids`` (all by default), B = len(ids).

        Returns ``current`` (B, 1+K, 9) with columns :data:`CURRENT_FEATURES` in the ego frame (row 0 is
        the ego: its own velocity, heading to the road, lane and target lane; a tenth column, each
        vehicle's own acceleration, with ``observe_acceleration``), ``history`` (B, K, H, 3):
        the last H positions of the same K vehicles in the ego frame of the current step, oldest first,
        with a validity flag, and ``image`` (B, 3, S, S) uint8 when rendering is on.
        """
        sim = self.sim
        every = ids is None
        ids = _vehicle_range(self.num_envs) if every else np.asarray(ids, dtype=np.int64)
        nb = self.neighbours(ids)
        rows = np.concatenate([np.zeros((len(ids), 1), dtype=np.int64), nb], axis=1)  # (B, 1+K)
        present = rows >= 0
        flat = np.maximum(rows, 0)
        flat += (ids * sim.num_vehicles)[:, None]  # flat indices into (E, N); column 0 is the ego
        px, py, yaw, speed = sim.x.take(flat), sim.y.take(flat), sim.yaw.take(flat), sim.speed.take(flat)
        ex, ey, eyaw, ev = px[:, :1], py[:, :1], yaw[:, :1], speed[:, :1]
        c, s = np.cos(eyaw), np.sin(eyaw)
        dx, dy = px - ex, py - ey
        rvx, rvy = speed * np.cos(yaw) - ev * c, speed * np.sin(yaw) - ev * s
        rvx[:, 0], rvy[:, 0] = ev[:, 0] * c[:, 0], ev[:, 0] * s[:, 0]  # the ego row holds its own velocity
        rel_yaw = yaw - eyaw
        rel_yaw[:, 0] = eyaw[:, 0]
        # Features first (np.array of the list: one copy, cheaper than np.stack), then moved last in the
        # float32 copy.
        cur = np.array([
            c * dx + s * dy, -s * dx + c * dy,
            c * rvx + s * rvy, -s * rvx + c * rvy,
            rel_yaw, speed,
            sim.lane.take(flat), sim.target_lane.take(flat),  # (small integers: exact in float64)
            np.ones(dx.shape),
        ] + ([sim.accel.take(flat)] if self.config.observe_acceleration else []), dtype=np.float64)
        cur *= present
        pos, valid = sim.history(nb, ids)  # (B, K, H, 2), (B, K, H)
        hdx, hdy = pos[..., 0] - ex[:, :, None], pos[..., 1] - ey[:, :, None]
        c3, s3 = c[:, :, None], s[:, :, None]
        hist = np.array([(c3 * hdx + s3 * hdy) * valid, (-s3 * hdx + c3 * hdy) * valid, valid], dtype=np.float64)
        obs = {"current": np.ascontiguousarray(cur.transpose(1, 2, 0), dtype=np.float32),
               "history": np.ascontiguousarray(hist.transpose(1, 2, 3, 0), dtype=np.float32)}
        if self.renderer is not None:
            if every:
                obs["image"] = self.renderer.render(sim.x, sim.y, sim.yaw, sim.length, sim.width)
            else:
                obs["image"] = self.renderer.render(sim.x[ids], sim.y[ids], sim.yaw[ids], sim.length[ids],
                                                    sim.width[ids])
        return obs
