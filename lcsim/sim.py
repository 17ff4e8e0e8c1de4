"""The batched highway simulator: E environments x N vehicles advanced by one call.

State lives in ``(E, N)`` arrays; vehicle 0 of every environment is the ego. One :meth:`HighwaySim.substep`
advances every environment by ``dt_s``: neighbour search on the per-lane sorted order, IDM for the
traffic, Traffic-Manager-like lane changes at the check period, the ego's PID controller on a kinematic
bicycle model, then collision, lane-invasion and off-road sensors. No per-vehicle Python objects, no
per-environment loops in the hot path.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from lcsim import rng
from lcsim.collision import obb_overlap
from lcsim.config import ScenarioConfig
from lcsim.control import (
    ArrayOps,
    FloatOps,
    PIDBank,
    ego_step,
)
from lcsim.neighbours import LaneIndex
from lcsim.road import StraightRoad
from lcsim.traffic import WANDER_CLIP_SIGMAS, DriverParams, idm_accel, smoothstep5

# Per-vehicle state arrays (E, N) and per-environment arrays (E,) frozen together when an episode ends.
_VEHICLE_STATE = ("x", "y", "yaw", "speed", "accel", "lane", "target_lane", "lc_active", "lc_t0", "lc_y0",
                  "lc_y1")
_ENV_STATE = ("step", "t_s", "ego_accel", "path_x0", "path_len", "path_y0", "path_y1", "ego_lc_active", "steer",
              "throttle", "brake", "collision_with", "lane_invasion", "off_road")
_SENSOR_STATE = ("collision_with", "lane_invasion", "off_road")
# The state of human-like traffic (TrafficConfig.human_like), frozen with the rest: each driver's acceleration
# noise (held between two lane-change checks) and lateral wander (its value at the last check, at the next,
# and the change per step between them).
_HUMAN_STATE = ("noise", "wander_base", "wander_next", "wander_step")
# Up to this many vehicles changing lanes, their lateral update runs on Python floats (fewer calls).
_SCALAR_LANE_CHANGES = 12
# Up to this many environments the neighbour index is updated rather than rebuilt when nothing but the
# gaps changed (all environments must qualify, which becomes rare on large batches).
_INCREMENTAL_INDEX_MAX_ENVS = 8
_NONE = np.zeros(0, dtype=np.int64)  # no environment, no vehicle
_LANE_CHANGE_STREAM = 1  # the random-number stream of the traffic's spontaneous lane changes
_REDRAW_STREAM = 2  # mixes the salt of rekey into the keys
_NOISE_STREAM = 3  # the knots of human-like drivers' acceleration noise and lateral wander
_ALL_ONE_ENV = np.ones(1, dtype=bool)

SubstepHook = Callable[["HighwaySim"], None]


class HighwaySim:
    """E independent highway environments stepped in lockstep.

    Args:
        config: the scenario.
        num_envs: E.
        autopilot_ego: drive the ego with the traffic's autopilot instead of the PID controller
            (the corpus scenario records 20 autopilot vehicles).
    """

    def __init__(self, config: ScenarioConfig, num_envs: int, *, autopilot_ego: bool = False) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.config = config
        self.road = StraightRoad(config.road)
        self.autopilot_ego = autopilot_ego
        self.num_envs = e = num_envs
        self.num_vehicles = n = 1 + config.traffic.num_vehicles
        self.dt = config.dt_s
        tc, ec = config.traffic, config.ego
        self.ids = np.arange(n, dtype=np.int64)
        self.length = np.full((e, n), tc.length_m)
        self.width = np.full((e, n), tc.width_m)
        self.length[:, 0], self.width[:, 0] = ec.length_m, ec.width_m
        self.half_width = 0.5 * self.width
        self.radius = 0.5 * np.hypot(self.length, self.width)
        self.is_traffic = np.ones((e, n), dtype=bool)
        self.is_traffic[:, 0] = autopilot_ego
        self.check_every = max(1, round(tc.lane_change_check_period_s / self.dt))
        self.p_spontaneous = tc.random_lane_change_rate_per_min * tc.lane_change_check_period_s / 60.0
        self.human = tc.human_like

        f64 = lambda shape: np.zeros(shape)  # noqa: E731
        self.x, self.y, self.yaw, self.speed, self.accel = (f64((e, n)) for _ in range(5))
        self.lane = np.zeros((e, n), dtype=np.int64)
        self.target_lane = np.zeros((e, n), dtype=np.int64)
        self.v0 = f64((e, n))
        self.lc_active = np.zeros((e, n), dtype=bool)
        self.lc_t0, self.lc_y0, self.lc_y1 = f64((e, n)), f64((e, n)), f64((e, n))
        # Human-like drivers: per-driver parameters (set at reset) and the state of their random processes.
        self.drivers = DriverParams.nominal(tc, (e, n), self.dt)
        if self.human:
            for name in _HUMAN_STATE:
                setattr(self, name, f64((e, n)))
            period = self.check_every * self.dt
            self._noise_rho = math.exp(-period / tc.accel_noise_time_s)
            self._wander_rho = math.exp(-period / tc.lane_wander_time_s)
        # Ego planner (BasicAgent-style lane-change path) and controller state, per environment.
        self.path_x0, self.path_len, self.path_y0, self.path_y1 = (f64(e) for _ in range(4))
        self.ego_lc_active = np.zeros(e, dtype=bool)
        self.pid = PIDBank(e, [ec.longitudinal_pid, ec.lateral_pid], ec.pid_window)
        self.steer, self.throttle, self.brake, self.ego_accel = f64(e), f64(e), f64(e), f64(e)
        self.lag_alpha = min(1.0, self.dt / ec.powertrain_lag_s) if ec.powertrain_lag_s > 0 else 1.0
        # Clock, sensors, seeds.
        self.step = np.zeros(e, dtype=np.int64)
        self.t_s = f64(e)
        self.key = np.zeros(e, dtype=np.uint64)
        self._derive_stream_bases()  # (kept with key by reset and rekey)
        self.collision_with = np.full(e, -1, dtype=np.int64)
        self.lane_invasion = np.full(e, -1, dtype=np.int64)
        self.off_road = np.zeros(e, dtype=bool)
        self.traffic_collisions = np.zeros(e, dtype=np.int64)
        # Position history ring buffer (E, H, N, 2) with a global write pointer.
        self.history_len = config.history_steps
        self.hist = np.zeros((e, self.history_len, n, 2))
        self.hist_ptr = 0
        self.hist_count = np.zeros(e, dtype=np.int64)
        self.frozen = np.zeros(e, dtype=bool)
        self.rows = np.arange(e)[:, None]
        self.target_speed = ec.target_speed_kmh / 3.6
        self.index: LaneIndex | None = None
        self._ego_flat = np.arange(e, dtype=np.int64) * n  # flat index of each environment's vehicle 0
        # Called after every substep. Contract (tested in tests/test_record.py): each substep binds new
        # x, y, yaw, speed, accel, lane and target_lane arrays and nothing writes into earlier ones (only
        # reset writes, into the rows it resets; a lane change copies target_lane before it sets the
        # target), so a hook may keep references to them.
        self.hooks: list[SubstepHook] = []

    # ------------------------------------------------------------------ reset
    def reset(self, env_ids: Sequence[int] | np.ndarray, seeds: Sequence[int]) -> None:
        """Spawn new episodes in environments ``env_ids``, each fully determined by its seed."""
        env_ids = np.asarray(env_ids, dtype=np.int64)
        for e, seed in zip(env_ids, seeds, strict=True):
            self._spawn(int(e), np.random.default_rng(int(seed)))
        self.frozen[env_ids] = False
        self.pid.reset(env_ids)
        self.index = self._build_index()
        self.hist[env_ids] = np.stack([self.x[env_ids], self.y[env_ids]], axis=-1)[:, None]
        self.hist_count[env_ids] = 1
        self._derive_stream_bases()

    def _derive_stream_bases(self) -> None:
        """The per-environment bases of the random streams drawn every step, from the current keys."""
        self.lane_change_base = rng.stream_base(self.key, _LANE_CHANGE_STREAM)
        self.noise_base = rng.stream_base(self.key, _NOISE_STREAM)

    def rekey(self, salt: int) -> None:
        """Mix ``salt`` into every environment's key of the counter-based random streams: from now on the
        traffic draws other random numbers (:func:`lcsim.planning.redraw_future` is the planner's use)."""
        self.key = self.key ^ rng.stream_base(np.array([salt], dtype=np.uint64), _REDRAW_STREAM)[0]
        self._derive_stream_bases()

    def _spawn(self, e: int, gen: np.random.Generator) -> None:
        _cfg, tc, ec, road = self.config, self.config.traffic, self.config.ego, self.road
        lanes = road.num_lanes
        ego_lane = ec.start_lane if ec.start_lane >= 0 else int(gen.integers(lanes))
        n_traffic = self.num_vehicles - 1
        lane_of = gen.permutation(np.arange(n_traffic) % lanes)
        xs = np.empty(n_traffic)
        spacing = tc.length_m + tc.min_spawn_gap_m
        lo_w, hi_w = -tc.spawn_behind_m, tc.spawn_ahead_m
        for lane in range(lanes):
            sel = np.flatnonzero(lane_of == lane)
            k = sel.size
            if k == 0:
                continue
            zone = 0.0
            if lane == ego_lane:  # keep the ego's spot free: half the clearance behind, all of it ahead
                zone_lo = -0.5 * tc.ego_clearance_m - 0.5 * (ec.length_m + tc.length_m)
                zone = 1.5 * tc.ego_clearance_m + ec.length_m + tc.length_m
            free = (hi_w - lo_w) - zone - k * spacing
            if free < 0:
                raise ValueError(f"TrafficConfig: {k} vehicles do not fit in lane {lane}; lower num_vehicles")
            pos = lo_w + np.sort(gen.uniform(0.0, free, k)) + np.arange(k) * spacing + 0.5 * spacing
            if zone:
                pos = np.where(pos >= zone_lo, pos + zone, pos)
            xs[sel] = pos
        spread = np.clip(gen.standard_normal(self.num_vehicles), -2.5, 2.5) * tc.speed_spread_kmh
        v0 = (tc.speed_kmh + spread) / 3.6
        v0 = np.maximum(v0, 1.0)
        if not self.autopilot_ego:
            v0[0] = ec.target_speed_kmh / 3.6
        self.x[e, 0], self.x[e, 1:] = 0.0, xs
        all_lanes = np.concatenate([[ego_lane], lane_of]).astype(np.int64)
        self.lane[e] = self.target_lane[e] = all_lanes
        self.y[e] = road.lane_center(all_lanes)
        self.yaw[e] = 0.0
        self.v0[e] = v0
        self.speed[e] = v0
        if not self.autopilot_ego:
            self.speed[e, 0] = ec.initial_speed_kmh / 3.6
        self.accel[e] = 0.0
        self.lc_active[e] = False
        self.lc_t0[e] = 0.0
        self.lc_y0[e] = self.lc_y1[e] = self.y[e]
        y_c = float(road.lane_center(ego_lane))
        self.path_x0[e], self.path_len[e], self.path_y0[e], self.path_y1[e] = 0.0, 1.0, y_c, y_c
        self.ego_lc_active[e] = False
        self.steer[e] = self.throttle[e] = self.brake[e] = self.ego_accel[e] = 0.0
        self.step[e], self.t_s[e] = 0, 0.0
        self.key[e] = np.uint64(gen.integers(0, 2**63 - 1))
        self.collision_with[e], self.lane_invasion[e], self.off_road[e] = -1, -1, False
        self.traffic_collisions[e] = 0
        if self.human:  # (drawn after everything else: the rest of the episode is as without them)
            self._spawn_drivers(e, gen)

    def _spawn_drivers(self, e: int, gen: np.random.Generator) -> None:
        """Human-like drivers for environment ``e``: their parameters, and their random processes started
        from their stationary distributions (the ego, unless on autopilot, neither wanders nor has noise)."""
        tc, n = self.config.traffic, self.num_vehicles
        self.drivers.draw(e, gen, tc, self.dt, n)
        traffic = self.is_traffic[e]
        self.noise[e] = tc.accel_noise_mps2 * gen.standard_normal(n) * traffic
        self.wander_base[e] = self.wander_next[e] = np.clip(gen.standard_normal(n), -WANDER_CLIP_SIGMAS,
                                                           WANDER_CLIP_SIGMAS) * tc.lane_wander_m * traffic
        self.wander_step[e] = 0.0
        self.y[e] = self.y[e] + self.wander_base[e]

    # --------------------------------------------------------------- decisions
    def start_lane_change(self, env_mask: np.ndarray, direction: np.ndarray) -> None:
        """Plan a BasicAgent-style lane change for the ego where ``env_mask`` (E,) is set.

        ``direction`` (E,) is +1 (left) or -1 (right). The path keeps the current lane for
        ``same_lane_time_s * speed``, moves laterally over ``lane_change_time_s * speed`` metres, then
        follows the target lane. A target beyond the edge lanes leads off the road, as in CARLA.
        """
        ec = self.config.ego
        start = env_mask & ~self.ego_lc_active
        if not start.any():
            return
        idx = np.flatnonzero(start)
        v = self.speed[idx, 0]
        cur = self.target_lane[idx, 0]
        new = cur + direction[idx].astype(np.int64)
        self.path_x0[idx] = self.x[idx, 0] + ec.same_lane_time_s * v
        self.path_len[idx] = np.maximum(ec.lane_change_time_s * v, ec.waypoint_spacing_m)
        self.path_y0[idx] = self.road.lane_center(cur)
        self.path_y1[idx] = self.road.lane_center(new)
        self.target_lane = self.target_lane.copy()  # the previous step's array may be held by a hook
        self.target_lane[idx, 0] = new
        self.ego_lc_active[idx] = True

    # ----------------------------------------------------------------- physics
    def substep(self) -> None:
        """Advance every environment by one simulation step (frozen environments stay as they are)."""
        single = self.num_envs == 1  # (single-environment paths on Python scalars: the same results)
        frozen = _NONE if single and not self.frozen.item(0) else self.frozen.nonzero()[0]
        saved = self._save(frozen) if frozen.size else None
        tc, dt = self.config.traffic, self.dt
        index = self.index if self.index is not None else self._build_index()
        speed = self.speed
        human = self.human
        check_now = self.step.item(0) % self.check_every == 0 if single else None  # (one env: known once)
        if human:
            if check_now or not single:
                self._next_knots(single)
            acc = idm_accel(speed, self.v0, index.gap, speed - index.lead_speed, tc, self.drivers)
            # The driver's own noise on top, then the reaction lag: the applied acceleration closes a share
            # of its distance to the commanded one each step.
            acc += self.noise
            acc -= self.accel
            acc *= self.drivers.lag
            acc += self.accel
        else:
            acc = idm_accel(speed, self.v0, index.gap, speed - index.lead_speed, tc)
        if tc.lane_changes:
            if single:
                if check_now:
                    self._traffic_lane_changes(index, _ALL_ONE_ENV)
            else:
                due = (self.step % self.check_every) == 0
                if due.any():
                    self._traffic_lane_changes(index, due)

        # Traffic: ballistic longitudinal update, minimum-jerk lateral profile while changing lanes
        # (computed for the few vehicles changing lanes only).
        new_speed = acc * dt
        new_speed += speed
        np.maximum(new_speed, 0.0, out=new_speed)
        new_x = speed + new_speed
        new_x *= 0.5 * dt  # (= 0.5 * (v + v') * dt bit for bit: halving is exact)
        new_x += self.x
        # Lane keepers move sideways by their wander only (one step of it; zero without human-like drivers).
        new_y, new_yaw = (self.y + self.wander_step) if human else self.y.copy(), np.zeros(self.yaw.shape)
        changing = self.lc_active.ravel().nonzero()[0]
        if 0 < changing.size <= _SCALAR_LANE_CHANGES:
            self._lateral_few(changing.tolist(), new_speed, new_y, new_yaw)
        elif changing.size:
            inv_dur = self.drivers.lc_inv_duration.take(changing) if human else 1.0 / tc.lane_change_duration_s
            tau = (self.t_s.take(changing // self.num_vehicles) + (dt - self.lc_t0.take(changing))) * inv_dur
            prof, dprof = smoothstep5(tau)
            y0 = self.lc_y0.take(changing)
            dy = self.lc_y1.take(changing) - y0
            new_y.put(changing, y0 + dy * prof)
            new_yaw.put(changing, np.arctan2(dy * dprof * inv_dur, np.maximum(new_speed.take(changing), 1e-3)))
            self.lc_active.put(changing, tau < 1.0)

        if human and changing.size > _SCALAR_LANE_CHANGES:  # lane changers: their path plus their wander
            new_y.put(changing, new_y.take(changing) + self._wander_at(changing, 1))  # (_lateral_few adds it too)
        ego_y_prev = self.y[:, 0].copy()
        ego_target = self.target_lane.item(0) if single else self.target_lane[:, 0].copy()
        if not self.autopilot_ego:
            self._ego_step(index.gap[:, 0], new_x, new_y, new_yaw, new_speed, acc)
        self.x, self.y, self.yaw, self.speed, self.accel = new_x, new_y, new_yaw, new_speed, acc
        if single:
            self._relane_one(changing, ego_target)
            self.step[0] = self.step.item(0) + 1
            self.t_s[0] = self.t_s.item(0) + dt
            self.hist_count[0] = self.hist_count.item(0) + 1
        else:
            lane = np.floor(new_y / self.road.lane_width)  # as road.lane_of, inlined
            self.lane = np.minimum(np.maximum(lane, 0), self.road.num_lanes - 1).astype(np.int64)
            self.target_lane = np.where(self.lc_active, self.target_lane, self.lane)
            if not self.autopilot_ego:
                self.target_lane[:, 0] = np.where(self.ego_lc_active, ego_target, self.lane[:, 0])
            self.step += 1
            self.t_s += dt
            self.hist_count += 1  # (restoring frozen environments leaves it: their history is written too)

        if saved is not None:  # frozen environments get their state back before the index is built
            self._restore(frozen, saved)
            self.index = self._build_index()
        else:  # only the lane changers and the egos can have changed lanes (a lane keeper's wander is bounded
            # inside its lane: ScenarioConfig checks it)
            self.index = self._build_index(changing)
        self._sensors(ego_y_prev, frozen if saved is not None else None)
        if saved is not None:
            for name in _SENSOR_STATE:
                getattr(self, name)[frozen] = saved[name]
        self.hist_ptr = (self.hist_ptr + 1) % self.history_len
        self.hist[:, self.hist_ptr, :, 0] = self.x
        self.hist[:, self.hist_ptr, :, 1] = self.y
        for hook in self.hooks:
            hook(self)

    def _next_knots(self, single: bool) -> None:
        """Human-like drivers, at each lane-change check: every driver's acceleration noise for the coming
        period and the next knot of its lateral wander (Ornstein-Uhlenbeck steps over one period, from
        counter-based uniform draws), towards which the wander moves in equal steps; the wander (a lateral offset
        of the position; its heading, under half a degree, is left out) is clipped within the lane."""
        c = self.check_every
        if single:  # (called at the checks only)
            rows = slice(None)
        else:
            rows = ((self.step % c) == 0).nonzero()[0]
            if not rows.size:
                return
        tc, n = self.config.traffic, self.num_vehicles
        # Innovations: uniform draws of unit variance (the processes, sums of many, are nearly normal; no
        # transcendental function per draw)
        u = rng.uniform(self.key[rows], self.step[rows], 2 * n, stream=_NOISE_STREAM, base=self.noise_base[rows])
        u -= 0.5
        u *= math.sqrt(12.0)
        z_noise, z_wander = u[:, :n], u[:, n:]
        traffic = self.is_traffic[rows]
        rho, rho_w = self._noise_rho, self._wander_rho
        noise = self.noise[rows] * rho + (tc.accel_noise_mps2 * math.sqrt(1.0 - rho * rho)) * z_noise
        base = self.wander_next[rows].copy()  # (a view when rows is a slice)
        nxt = base * rho_w + (tc.lane_wander_m * math.sqrt(1.0 - rho_w * rho_w)) * z_wander
        limit = WANDER_CLIP_SIGMAS * tc.lane_wander_m
        nxt = np.minimum(np.maximum(nxt, -limit), limit) * traffic
        # (in place: these arrays are the simulator's own; an imagined copy has copies of them)
        self.noise[rows] = noise * traffic
        self.wander_base[rows] = base
        self.wander_next[rows] = nxt
        self.wander_step[rows] = (nxt - base) * (1.0 / c)

    def _wander_at(self, flat: np.ndarray, ahead: int) -> np.ndarray:
        """The lateral wander of vehicles ``flat`` (flat indices into E x N) ``ahead`` steps after the current
        one (0: now), within the current check period."""
        phase = self.step.take(flat // self.num_vehicles) % self.check_every + ahead
        return self.wander_base.take(flat) + self.wander_step.take(flat) * phase

    def _relane_one(self, changing: np.ndarray, ego_target: int) -> None:
        """``lane`` and ``target_lane`` after a substep of a single environment, for the vehicles that can
        have moved sideways only: the lane changers (``changing``, whose ``lc_active`` may also have
        flipped) and the ego. Every other vehicle kept its ``y``, has no change in progress and so keeps
        ``target_lane == lane`` (as the full update in :meth:`substep` would set it): the same arrays, in
        a few scalar operations instead of six passes over every vehicle. An array that changes is a new
        one, as the full update makes (a hook may hold the previous one); one that does not (most substeps)
        is kept."""
        lane, target = self.lane, self.target_lane
        y, active, lw, top = self.y, self.lc_active, self.road.lane_width, self.road.num_lanes - 1
        movers = changing.tolist()
        if not self.autopilot_ego:
            movers.append(0)  # (the ego's lc_active is never set: its own change is ego_lc_active)
        new_lane, new_target = [], []  # (vehicle, value) where the value changes
        for v in movers:
            k = min(max(math.floor(y.item(v) / lw), 0), top)  # as road.lane_of, on a float
            if lane.item(v) != k:
                new_lane.append((v, k))
            if not active.item(v) and target.item(v) != k:
                new_target.append((v, k))
        if not self.autopilot_ego and self.ego_lc_active.item(0):
            new_target = [(v, k) for v, k in new_target if v != 0]
            if target.item(0) != ego_target:
                new_target.append((0, ego_target))
        if new_lane:
            self.lane = lane = lane.copy()
            for v, k in new_lane:
                lane[0, v] = k
        if new_target:
            self.target_lane = target = target.copy()
            for v, k in new_target:
                target[0, v] = k

    def _lateral_few(self, changing: list[int], new_speed: np.ndarray, new_y: np.ndarray, new_yaw: np.ndarray) -> None:
        """The minimum-jerk lateral update of :meth:`substep` for a few vehicles, on Python floats (with
        human-like drivers, plus their wander).

        The same operations in the same order as the array version (traffic.smoothstep5), so the result
        does not depend on which of the two ran; arctan2 still comes from numpy.
        """
        tc, dt, n = self.config.traffic, self.dt, self.num_vehicles
        inv_dur = 1.0 / tc.lane_change_duration_s
        inv_durs = self.drivers.lc_inv_duration if self.human else None
        if inv_durs is not None:
            w_base, w_step, steps, c = self.wander_base, self.wander_step, self.step, self.check_every
        t_s, t0, y0s, y1s, active = self.t_s, self.lc_t0, self.lc_y0, self.lc_y1, self.lc_active
        rates, speeds = [], []
        for i in changing:
            e, v = divmod(i, n)
            if inv_durs is not None:
                inv_dur = inv_durs.item(i)
                wander = w_base.item(i) + w_step.item(i) * float(steps.item(e) % c + 1)  # (as _wander_at, on floats)
            tau = (t_s.item(e) + (dt - t0.item(i))) * inv_dur
            t = min(max(tau, 0.0), 1.0)
            t2 = t * t
            u = 1.0 - t
            prof = t2 * t * (10.0 - 15.0 * t + 6.0 * t2)
            dprof = 30.0 * t2 * (u * u)
            y0 = y0s.item(i)
            dy = y1s.item(i) - y0
            new_y[e, v] = y0 + dy * prof if inv_durs is None else (y0 + dy * prof) + wander
            rates.append(dy * dprof * inv_dur)
            speeds.append(max(new_speed.item(i), 1e-3))
            active[e, v] = tau < 1.0
        new_yaw.put(changing, np.arctan2(rates, speeds))  # one call (elementwise: the same as one per vehicle)

    def _pid_floats(self, e_speed: float, e_head: float) -> list[float]:
        """The ego's PID commands (longitudinal, lateral) of one environment's errors, on floats."""
        return self.pid.step_one((e_speed, e_head))

    def _pid_arrays(self, e_speed: np.ndarray, e_head: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The same for ``(E,)`` arrays of errors."""
        u = self.pid.step(np.stack((e_speed, e_head), axis=1))
        return u[:, 0], u[:, 1]

    def _ego_step(self, lead_gap: np.ndarray, x_out: np.ndarray, y_out: np.ndarray, yaw_out: np.ndarray,
                  v_out: np.ndarray, a_out: np.ndarray) -> None:
        """PID control on the planned path and a bicycle-model step (:func:`lcsim.control.ego_step`, on arrays,
        or on floats for one environment); writes column 0 of the outputs."""
        ec = self.config.ego
        if self.num_envs == 1:
            r = ego_step(FloatOps, ec, x=self.x.item(0), y=self.y.item(0), yaw=self.yaw.item(0),
                         speed=self.speed.item(0), target_speed=self.target_speed, lead_gap=lead_gap.item(0),
                         path=(self.path_x0.item(0), self.path_len.item(0), self.path_y0.item(0),
                               self.path_y1.item(0)),
                         steer_past=self.steer.item(0), accel_past=self.ego_accel.item(0), lag_alpha=self.lag_alpha,
                         dt=self.dt, pid=self._pid_floats)  # fmt: skip
            self.ego_accel[0], self.steer[0], self.throttle[0], self.brake[0] = r.accel, r.steer, r.throttle, r.brake
            if (self.ego_lc_active.item(0) and r.x >= self.path_x0.item(0) + self.path_len.item(0)
                    and abs(r.y - self.path_y1.item(0)) < ec.lane_change_tolerance_m):
                self.ego_lc_active[0] = False
            x_out[0, 0], y_out[0, 0], yaw_out[0, 0], v_out[0, 0], a_out[0, 0] = r.x, r.y, r.yaw, r.speed, r.accel
            return

        r = ego_step(ArrayOps, ec, x=self.x[:, 0], y=self.y[:, 0], yaw=self.yaw[:, 0], speed=self.speed[:, 0],
                     target_speed=self.target_speed, lead_gap=lead_gap,
                     path=(self.path_x0, self.path_len, self.path_y0, self.path_y1), steer_past=self.steer,
                     accel_past=self.ego_accel, lag_alpha=self.lag_alpha, dt=self.dt, pid=self._pid_arrays)  # fmt: skip
        self.ego_accel, self.steer, self.throttle, self.brake = r.accel, r.steer, r.throttle, r.brake
        if self.ego_lc_active.any():
            done = self.ego_lc_active & (r.x >= self.path_x0 + self.path_len) & (
                np.abs(r.y - self.path_y1) < ec.lane_change_tolerance_m)
            self.ego_lc_active &= ~done
        x_out[:, 0], y_out[:, 0], yaw_out[:, 0], v_out[:, 0], a_out[:, 0] = r.x, r.y, r.yaw, r.speed, r.accel

    def _traffic_lane_changes(self, index: LaneIndex, due: np.ndarray) -> None:
        """Traffic-Manager-like lane changes: when blocked (or at random), into a free side lane."""
        tc, n = self.config.traffic, self.num_vehicles
        cand = self.is_traffic & ~self.lc_active & due[:, None]
        gap = index.gap
        # A leader exists exactly where the gap is finite.
        blocked = (gap < np.inf) & (gap >= tc.blocked_gap_min_m) & (gap <= tc.blocked_gap_max_m) & (
            index.lead_speed < self.v0 - tc.blocked_speed_margin_kmh / 3.6)
        u = rng.uniform(self.key, self.step, n, stream=_LANE_CHANGE_STREAM, base=self.lane_change_base)
        spontaneous = u < self.p_spontaneous
        if self.human:  # whether the driver acts on a blocked leader now (the same draw serves: a driver who
            # changes spontaneously would have acted on a blocked leader too, as p_spontaneous < eagerness)
            blocked &= u < self.drivers.eagerness
        want = (cand & (blocked | spontaneous)).ravel().nonzero()[0]  # flat (E * N) indices of the few that want to
        if not want.size:
            return
        # One side per check period (left on even periods) so that two vehicles never merge into one gap.
        env = want // n
        tl = self.lane.take(want) + np.where((self.step.take(env) // self.check_every) % 2 == 0, 1, -1)
        x, length = self.x.take(want), self.length.take(want)
        front = index.neighbour_flat(want, tl, ahead=True)
        rear = index.neighbour_flat(want, tl, ahead=False)
        no_front, no_rear = front < 0, rear < 0
        front_x = np.where(no_front, np.inf, self.x.take(front, mode="clip"))
        front_len = np.where(no_front, 0.0, self.length.take(front, mode="clip"))
        rear_x = np.where(no_rear, -np.inf, self.x.take(rear, mode="clip"))
        rear_len = np.where(no_rear, 0.0, self.length.take(rear, mode="clip"))
        rear_speed = np.where(no_rear, 0.0, self.speed.take(rear, mode="clip"))
        front_gap = front_x - x - 0.5 * (length + front_len)
        rear_gap = x - rear_x - 0.5 * (length + rear_len)
        rear_need = tc.lane_change_rear_gap_m + tc.lane_change_rear_headway_s * rear_speed
        ok = (tl >= 0) & (tl < self.road.num_lanes) & (front_gap >= tc.lane_change_front_gap_m) & (
            rear_gap >= rear_need) & ((front_gap > gap.take(want) + 5.0) | spontaneous.take(want))
        if not ok.any():
            return
        go, tl = want[ok], tl[ok]
        self.lc_active.put(go, True)
        self.lc_t0.put(go, self.t_s.take(env[ok]))
        y0 = self.y.take(go)
        self.lc_y0.put(go, y0 - self._wander_at(go, 0) if self.human else y0)  # from the lane-keeping position
        self.lc_y1.put(go, self.road.lane_center(tl))
        self.target_lane = self.target_lane.copy()  # the previous step's array may be held by a hook
        self.target_lane.put(go, tl)

    def rebuild_index(self) -> None:
        """Rebuild the neighbour index from scratch: call it after editing the state arrays by hand
        (the simulator itself keeps the index up to date)."""
        self.index = self._build_index()

    def _build_index(self, changing: np.ndarray | None = None) -> LaneIndex:
        """The neighbour index of the current state.

        ``changing``: flat indices (into E x N) of the traffic vehicles whose ``y``, ``yaw`` or lane-change
        state may have changed since ``self.index`` was built, besides the egos (None: any vehicle's). For a few
        environments the previous index is then updated in place of a full build when the sorted order is
        unchanged (most steps; see LaneIndex.after_move); the result is the same.
        """
        extra = np.where(self.lc_active, self.target_lane, -1)
        prev = self.index
        if changing is not None and prev is not None and self.num_envs <= _INCREMENTAL_INDEX_MAX_ENVS:
            moved = np.concatenate((changing, self._ego_flat)) if changing.size else self._ego_flat
            index = prev.after_move(self.x, self.y, self.yaw, self.speed, self.length, self.width, extra,
                                    self.road.lane_width, moved)
            if index is not None:
                return index
        previous = prev.order if prev is not None else None
        return LaneIndex(self.x, self.y, self.yaw, self.speed, self.length, self.width, extra,
                         self.road.lane_width, self.road.num_lanes, self.rows, previous_order=previous)

    def _sensors(self, ego_y_prev: np.ndarray, frozen: np.ndarray | None = None) -> None:
        """Collisions, lane invasion and off-road (the caller restores them in ``frozen`` environments).

        Collision candidates are the pairs (vehicle, leader) whose gap along x is under a metre: the
        leader is the nearest vehicle ahead in any lane the body overlaps, so any contact shows up as
        such a pair. Candidates are then decided exactly by the oriented-rectangle test.
        """
        index = self.index
        assert index is not None
        n = self.num_vehicles
        self.collision_with[:] = -1
        if self.num_envs == 1 and (frozen is not None or not np.count_nonzero(index.gap < 1.0)):
            va = _NONE  # (one environment: no candidate, known from one reduction)
        else:
            cand = index.gap < 1.0
            if frozen is not None:
                cand[frozen] = False
            va = cand.ravel().nonzero()[0]
        if va.size:
            vb = index.lead_flat.take(va)
            x, y, yaw, length, width = self.x, self.y, self.yaw, self.length, self.width
            hit = obb_overlap(x.take(va), y.take(va), yaw.take(va), length.take(va), width.take(va),
                              x.take(vb), y.take(vb), yaw.take(vb), length.take(vb), width.take(vb))
            if hit.any():
                va, vb = va[hit], vb[hit]
                ee, va, vb = va // n, va % n, vb % n
                ego_hit = (va == 0) | (vb == 0)
                other = np.where(va == 0, vb, va)
                self.collision_with[ee[ego_hit][::-1]] = other[ego_hit][::-1]
                np.add.at(self.traffic_collisions, ee[~ego_hit], 1)
        lw = self.road.lane_width
        if self.num_envs == 1:  # the same on floats (floor of a float is exact either way)
            y_prev, y_now = ego_y_prev.item(0), self.y.item(0)
            k_prev, k_new = math.floor(y_prev / lw), math.floor(y_now / lw)
            self.lane_invasion[0] = max(k_prev, k_new) if k_prev != k_new else -1  # (in place, as collision_with)
            self.off_road[0] = y_now < 0.0 or y_now > self.road.width
            return
        ego_y = self.y[:, 0]
        k_prev, k_new = np.floor(ego_y_prev / lw), np.floor(ego_y / lw)
        self.lane_invasion = np.where(k_prev != k_new, np.maximum(k_prev, k_new), -1).astype(np.int64)
        self.off_road = (ego_y < 0.0) | (ego_y > self.road.width)  # not road.on_road, inlined

    # ------------------------------------------------------------- freezing
    def _state_names(self) -> tuple[str, ...]:
        return _VEHICLE_STATE + _ENV_STATE + (_HUMAN_STATE if self.human else ())

    def _save(self, idx: np.ndarray) -> dict[str, np.ndarray]:
        out = {name: getattr(self, name)[idx].copy() for name in self._state_names()}
        out["pid"] = self.pid.errors[idx].copy()
        out["pid_count"] = self.pid.count[idx].copy()
        return out

    def _restore(self, idx: np.ndarray, saved: dict[str, np.ndarray] | None) -> None:
        assert saved is not None
        for name in self._state_names():
            getattr(self, name)[idx] = saved[name]
        self.pid.errors[idx] = saved["pid"]
        self.pid.count[idx] = saved["pid_count"]

    # ---------------------------------------------------------------- queries
    def history(self, env_vehicles: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions of chosen vehicles over the last H steps, oldest first.

        Args:
            env_vehicles: ``(B, K)`` vehicle indices (-1 for an empty slot) of environments ``ids`` (B,).

        Returns:
            ``(B, K, H, 2)`` world positions and ``(B, K, H)`` validity.
        """
        h = self.history_len
        slots = (self.hist_ptr - h + 1 + np.arange(h)) % h
        veh = np.maximum(env_vehicles, 0)[:, :, None]
        n = self.num_vehicles
        rows = (ids[:, None, None] * h + slots[None, None, :]) * n + veh  # rows of hist seen as (E * H * N, 2)
        pos = self.hist.reshape(-1, 2).take(rows, axis=0)  # (B, K, H, 2)
        valid_t = np.arange(h)[None, :] >= (h - np.minimum(self.hist_count[ids], h))[:, None]  # (B, H)
        valid = (env_vehicles >= 0)[:, :, None] & valid_t[:, None, :]
        return pos, valid

