"""The batched highway simulator: E environments x N vehicles advanced by one call.

State lives in ``(E, N)`` arrays (views of a few blocks, :mod:`lcsim.kernel`); vehicle 0 of every environment is
the ego. :meth:`HighwaySim.advance` runs any number of simulation steps of every environment in one compiled call:
neighbour search on each environment's sorted order, IDM for the traffic, Traffic-Manager-like lane changes at the check
period, the ego's PID controller on a kinematic bicycle model, then collision, lane-invasion and off-road sensors.
No per-vehicle Python objects and no Python per step; episodes are spawned (:meth:`HighwaySim.reset`) in Python.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from lcsim import kernel as K
from lcsim import rng
from lcsim.config import ScenarioConfig
from lcsim.control import PIDBank
from lcsim.neighbours import LaneIndex
from lcsim.road import StraightRoad
from lcsim.threads import check_threads, run_shards, shard_count
from lcsim.traffic import DriverParams

_LANE_CHANGE_STREAM = 1  # the random-number stream of the traffic's spontaneous lane changes
_REDRAW_STREAM = 2  # mixes the salt of rekey into the keys
_NOISE_STREAM = 3  # the knots of human-like drivers' acceleration noise and lateral wander
# The rows of the blocks that are the simulator's own attributes (the neighbour index and the drivers hold the rest).
_INDEX_ROWS = ("gap", "lead_speed", "order", "pos_of", "lo", "hi", "extra", "lead")
_DRIVER_ROWS = DriverParams.__slots__
_BLOCKS = (("vf", K.VF_NAMES), ("vi", K.VI_NAMES), ("vb", K.VB_NAMES), ("ef", K.EF_NAMES), ("ei", K.EI_NAMES),
           ("eb", K.EB_NAMES), ("keys", K.KEY_NAMES))
_OWN_ROWS = tuple((block, row, name) for block, names in _BLOCKS for row, name in enumerate(names)
                  if name not in _INDEX_ROWS and name not in _DRIVER_ROWS)
_VEHICLE_BLOCKS = ("vf", "vi", "vb")

SubstepHook = Callable[["HighwaySim"], None]
StepLogHook = Callable[["HighwaySim", np.ndarray, np.ndarray], None]

LOG_STEPS = 64
"""Most simulation steps one compiled call logs (:attr:`HighwaySim.log_hooks`); a longer advance is split."""
_NO_LOG = np.zeros((0, 0, 0))
_NO_LOG.flags.writeable = False


def _state_property(name: str) -> property:
    """A named row of a state block: reads give the view; assignment writes into it (the block stays the state)."""
    attr = "_" + name

    def fset(self: HighwaySim, value: Any) -> None:
        getattr(self, attr)[...] = value

    return property(operator.attrgetter(attr), fset, doc=f"``{name}``: a view of its state block.")


class HighwaySim:
    """E independent highway environments stepped in lockstep.

    Args:
        config: the scenario.
        num_envs: E.
        autopilot_ego: drive the ego with the traffic's autopilot instead of the PID controller
            (the corpus scenario records 20 autopilot vehicles).
        threads: the threads that advance the batch, each a contiguous shard of environments (the same bits
            however many); None: the process's default (:mod:`lcsim.threads`), 1: the calling thread only.

    The state arrays (``x``, ``y``, ``yaw``, ``speed``, ``accel``, ``lane``, ``target_lane``, ``lc_active``, ...;
    :data:`lcsim.kernel.VF_NAMES` and the other name lists) are views of a few blocks; assigning to one writes into
    it. ``frozen`` environments keep their state through :meth:`substep` and :meth:`advance`.
    """

    def __init__(self, config: ScenarioConfig, num_envs: int, *, autopilot_ego: bool = False,
                 threads: int | None = None) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.config = config
        self.threads = check_threads(threads)
        self.road = StraightRoad(config.road)
        self.autopilot_ego = autopilot_ego
        self.num_envs = e = num_envs
        self.num_vehicles = n = 1 + config.traffic.num_vehicles
        self.dt = config.dt_s
        tc, ec = config.traffic, config.ego
        self.ids = np.arange(n, dtype=np.int64)
        self.human = tc.human_like
        self.params, self.iparams = K.kernel_params(config, autopilot_ego)
        self.vf = np.zeros((len(K.VF_NAMES), e, n))
        self.vi = np.zeros((len(K.VI_NAMES), e, n), dtype=np.int64)
        self.vb = np.zeros((len(K.VB_NAMES), e, n), dtype=bool)
        self.ef = np.zeros((len(K.EF_NAMES), e))
        self.ei = np.zeros((len(K.EI_NAMES), e), dtype=np.int64)
        self.eb = np.zeros((len(K.EB_NAMES), e), dtype=bool)
        self.keys = np.zeros((len(K.KEY_NAMES), e), dtype=np.uint64)
        self._bind()
        self.length[:], self.width[:] = tc.length_m, tc.width_m
        self.length[:, 0], self.width[:, 0] = ec.length_m, ec.width_m
        self.is_traffic[:] = True
        self.is_traffic[:, 0] = autopilot_ego
        nominal = DriverParams.nominal(tc, (1,), self.dt)  # (human-like drivers get their own at reset)
        for name in _DRIVER_ROWS:
            getattr(self.drivers, name)[...] = getattr(nominal, name)[0]
        self.index.order[:] = self.ids
        # Spawning: the traffic's lanes before the shuffle, and the constants of kernel.spawn_env.
        self._lane_cycle = np.arange(n - 1) % config.road.num_lanes
        spacing = tc.length_m + tc.min_spawn_gap_m
        spawn = {"spacing": spacing, "half_spacing": 0.5 * spacing, "lo_w": -tc.spawn_behind_m,
                 "zone_lo": -0.5 * tc.ego_clearance_m - 0.5 * (ec.length_m + tc.length_m),
                 "zone": 1.5 * tc.ego_clearance_m + ec.length_m + tc.length_m, "speed_kmh": tc.speed_kmh,
                 "speed_spread_kmh": tc.speed_spread_kmh, "ego_target_speed": ec.target_speed_kmh / 3.6,
                 "ego_initial_speed": ec.initial_speed_kmh / 3.6, "lane_width": config.road.lane_width_m}
        self._spawn_params = np.array([spawn[k] for k in K.SPAWN_NAMES], dtype=np.float64)
        self.pid = PIDBank(e, 2, ec.pid_window)  # longitudinal, lateral
        self.collision_with[:] = self.lane_invasion[:] = -1
        # Position history ring buffer (E, H, N, 2) with a global write pointer.
        self.history_len = config.history_steps
        self.hist = np.zeros((e, self.history_len, n, 2))
        self.hist_ptr = 0
        # Called after every substep. The state arrays are updated in place: a hook that keeps values copies them.
        self.hooks: list[SubstepHook] = []
        # Called with the step log after every compiled call that ran steps (see advance).
        self.log_hooks: list[StepLogHook] = []
        self._log = self._log_spare = _NO_LOG
        self._log_count = np.zeros(e, dtype=np.int64)

    def _bind(self) -> None:
        """Bind the named views of the blocks (after they were made, copied or replaced)."""
        for block, row, name in _OWN_ROWS:
            setattr(self, "_" + name, getattr(self, block)[row])
        self.drivers = DriverParams(*(self.vf[K.VF_NAMES.index(name)] for name in _DRIVER_ROWS))
        self.index = LaneIndex(self.vf, self.vi, self.config.road.num_lanes)

    def __getstate__(self) -> dict[str, Any]:
        # (copies of a simulator, e.g. a planner's deepcopy, copy the blocks and bind their views anew)
        state = self.__dict__.copy()
        for _block, _row, name in _OWN_ROWS:
            del state["_" + name]
        del state["drivers"], state["index"]
        state["_log"] = state["_log_spare"] = _NO_LOG  # (the step logs are scratch: a copy makes its own)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._bind()

    # ------------------------------------------------------------------ reset
    def reset(self, env_ids: Sequence[int] | np.ndarray, seeds: Sequence[int]) -> None:
        """Spawn new episodes in environments ``env_ids``, each fully determined by its seed."""
        env_ids = np.asarray(env_ids, dtype=np.int64)
        for e, seed in zip(env_ids, seeds, strict=True):
            self._spawn(int(e), np.random.default_rng(int(seed)))
        K.finish_spawn(env_ids, self.params, self.iparams, self.vf, self.vi, self.vb, self.ei, self.eb, self.hist,
                       self.pid.errors, self.pid.count)
        self._derive_stream_bases()

    def _derive_stream_bases(self) -> None:
        """The per-environment bases of the random streams drawn every step, from the current keys."""
        self.lane_change_base = rng.stream_base(self.key, _LANE_CHANGE_STREAM)
        self.noise_base = rng.stream_base(self.key, _NOISE_STREAM)

    def rekey(self, salt: int | np.ndarray) -> None:
        """Mix ``salt`` (one for all, or ``(E,)``, one per environment) into every environment's key of the
        counter-based random streams: from now on the traffic draws other random numbers
        (:func:`lcsim.planning.redraw_future` is the planner's use)."""
        salts = np.broadcast_to(np.asarray(salt, dtype=np.uint64), (self.num_envs,))
        self.key = self.key ^ rng.stream_base(salts, _REDRAW_STREAM)
        self._derive_stream_bases()

    def replicate(self, rows: np.ndarray) -> HighwaySim:
        """A new simulator whose environments are copies of environments ``rows`` (repeats allowed), in that
        order, with everything they carry (state, history, controllers, random keys) and no hooks: futures of
        the same states imagined side by side in one batch."""
        rows = np.asarray(rows, dtype=np.int64)
        new = object.__new__(HighwaySim)
        state = self.__getstate__()
        for name in ("vf", "vi", "vb", "ef", "ei", "eb", "keys"):
            state[name] = np.ascontiguousarray(state[name][:, rows])
        state["hist"] = self.hist[rows]
        state["num_envs"], state["hooks"], state["log_hooks"] = len(rows), [], []
        state["_log_count"] = np.zeros(len(rows), dtype=np.int64)
        pid = object.__new__(PIDBank)
        pid.__dict__.update(self.pid.__dict__)
        pid.errors, pid.count = self.pid.errors[rows], self.pid.count[rows]
        state["pid"] = pid
        new.__setstate__(state)
        return new

    def _spawn(self, e: int, gen: np.random.Generator) -> None:
        """A new episode in environment ``e``: the random draws here, in their order; the state from them in one
        compiled call (:func:`lcsim.kernel.spawn_env`)."""
        tc, ec = self.config.traffic, self.config.ego
        lanes = self.road.num_lanes
        ego_lane = ec.start_lane if ec.start_lane >= 0 else int(gen.integers(lanes))
        lane_of = gen.permutation(self._lane_cycle)
        counts = np.bincount(lane_of, minlength=lanes)
        sp = self._spawn_params
        spacing, span, zone = sp[0], tc.spawn_ahead_m - sp[2], sp[4]
        draws = []
        for lane in range(lanes):
            k = int(counts[lane])
            if k == 0:
                continue
            free = span - (zone if lane == ego_lane else 0.0) - k * spacing
            if free < 0:
                raise ValueError(f"TrafficConfig: {k} vehicles do not fit in lane {lane}; lower num_vehicles")
            draws.append(gen.uniform(0.0, free, k))
        spread_z = gen.standard_normal(self.num_vehicles)
        key = np.uint64(gen.integers(0, 2**63 - 1))
        K.spawn_env(e, ego_lane, lane_of, counts, np.concatenate(draws) if draws else np.empty(0), spread_z, key, sp,
                    self.autopilot_ego, self.vf, self.vi, self.vb, self.ef, self.ei, self.eb, self.keys)
        if self.human:  # (drawn after everything else: the rest of the episode is as without them)
            self._spawn_drivers(e, gen)

    def _spawn_drivers(self, e: int, gen: np.random.Generator) -> None:
        """Human-like drivers for environment ``e``: their parameters, and their random processes started
        from their stationary distributions (the ego, unless on autopilot, neither wanders nor has noise)."""
        tc, n = self.config.traffic, self.num_vehicles
        self.drivers.draw(e, gen, tc, self.dt, n)
        noise_z = gen.standard_normal(n)
        K.spawn_noise(e, noise_z, gen.standard_normal(n), tc.accel_noise_mps2, tc.lane_wander_m, self.vf, self.vb)

    # --------------------------------------------------------------- decisions
    def start_lane_change(self, env_mask: np.ndarray, direction: np.ndarray) -> None:
        """Plan a BasicAgent-style lane change for the ego where ``env_mask`` (E,) is set.

        ``direction`` (E,) is +1 (left) or -1 (right). The path keeps the current lane for
        ``same_lane_time_s * speed``, moves laterally over ``lane_change_time_s * speed`` metres, then
        follows the target lane. A target beyond the edge lanes leads off the road, as in CARLA.
        """
        K.start_lane_changes(np.asarray(env_mask, dtype=bool), np.asarray(direction, dtype=np.int64), self.params,
                             self.vf, self.vi, self.ef, self.eb)

    # ----------------------------------------------------------------- physics
    def substep(self) -> None:
        """Advance every environment by one simulation step (frozen environments stay as they are), then call the
        log hooks and the hooks."""
        self._advance(1, False, bool(self.log_hooks))
        if self.log_hooks:
            self._call_log_hooks()
        for hook in self.hooks:
            hook(self)

    def advance(self, steps: int, *, stop_on_event: bool = False,
                then: Callable[[int, int], None] | None = None) -> None:
        """Advance every environment not frozen by ``steps`` simulation steps in one compiled call.

        With ``stop_on_event``, an environment whose ego touches a vehicle, leaves the road or passes the route's
        end is frozen from there (``frozen`` is set) for the rest of the steps. With hooks attached, the steps run
        one by one, each followed by the hooks (and the events are checked the same way).

        Log hooks (:attr:`log_hooks`, ``hook(sim, log, counts)``) see the steps without a Python call per step: the
        compiled call (at most :data:`LOG_STEPS` steps) writes a row per environment and step it ran into ``log``
        ``(E, S, kernel.log_width(N))`` float64 (:func:`lcsim.kernel.log_state`), environment e's in
        ``log[e, :counts[e]]``. Two logs take turns: the rows stay as they are until the hooks of the next call
        return (a hook may hold on to them until then); ``counts`` is the next call's.

        ``then(e0, e1)``, a reader of environments ``e0 .. e1 - 1`` (the observation), is called for every shard of
        environments once all the steps are done: without hooks, by the thread that advanced the shard, as soon as
        it has (with the ring pointers already moved on); with hooks, after the last hooks.
        """
        if not self.hooks and not self.log_hooks:
            self._advance(steps, stop_on_event, then=then)
            return
        if not self.hooks:
            for start in range(0, steps, LOG_STEPS):
                self._advance(min(steps - start, LOG_STEPS), stop_on_event, True)
                self._call_log_hooks()
        else:
            for _ in range(steps):  # (the hooks see the event's step before it freezes the environment)
                self.substep()
                if stop_on_event:
                    self.frozen |= ((self.collision_with >= 0) | self.off_road
                                    | (self.x[:, 0] >= self.config.route_length_m))
        if then is not None:
            run_shards(then, self.num_envs, self.shards)

    def _advance(self, steps: int, stop_on_event: bool, logged: bool = False,
                 then: Callable[[int, int], None] | None = None) -> None:
        pid = self.pid
        hist_ptr, pid_ptr = self.hist_ptr, pid.ptr
        log = _NO_LOG
        if logged:  # two logs in turn: a hook may hold on to the rows of a call until the next call's hooks run
            self._log, log = self._log_spare, self._log
            if log.shape[0] != self.num_envs or log.shape[1] < steps:  # (as many steps as the longest call so far)
                log = np.zeros((self.num_envs, steps, K.log_width(self.num_vehicles)))
            self._log_spare = log

        def shard(e0: int, e1: int) -> None:
            if logged:
                K.advance_logged(steps, stop_on_event, self.params, self.iparams, self.vf, self.vi, self.vb, self.ef,
                                 self.ei, self.eb, self.keys, self.hist, hist_ptr, pid.errors, pid.count, pid_ptr,
                                 log, self._log_count, e0, e1)  # fmt: skip
            else:
                K.advance(steps, stop_on_event, self.params, self.iparams, self.vf, self.vi, self.vb, self.ef, self.ei,
                          self.eb, self.keys, self.hist, hist_ptr, pid.errors, pid.count, pid_ptr, e0, e1)
            if then is not None:
                then(e0, e1)

        self.hist_ptr = (hist_ptr + steps) % self.history_len
        if not self.autopilot_ego:
            pid.ptr = (pid_ptr + steps) % pid.window
        try:
            run_shards(shard, self.num_envs, self.shards)
        except BaseException:
            self.hist_ptr, pid.ptr = hist_ptr, pid_ptr
            raise

    def _call_log_hooks(self) -> None:
        log, counts = self._log_spare, self._log_count
        for hook in tuple(self.log_hooks):
            hook(self, log, counts)

    def log_row(self, env: int) -> np.ndarray:
        """Environment ``env``'s present state as a step log row (what :attr:`log_hooks` get for each step), e.g. the
        state after a reset."""
        row = np.zeros(K.log_width(self.num_vehicles))
        K.log_state(env, self.iparams, self.vf, self.vi, self.vb, self.ef, self.ei, self.eb, row)
        return row

    @property
    def shards(self) -> int:
        """How many threads step this batch now (:func:`lcsim.threads.shard_count` of ``threads``)."""
        return shard_count(self.num_envs, self.threads)

    def rebuild_index(self) -> None:
        """Rebuild the neighbour index: call it after editing the state arrays by hand (the simulator itself keeps
        the index up to date)."""
        K.build_index(np.arange(self.num_envs), self.params, self.iparams, self.vf, self.vi, self.vb, False)

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



for _block, _row, _name in _OWN_ROWS:
    setattr(HighwaySim, _name, _state_property(_name))
del _block, _row, _name
