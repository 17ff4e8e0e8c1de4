"""Frozen, validated, JSON-serialisable configuration of the simulator and its environments.

Every config is a ``@dataclass(frozen=True, slots=True, kw_only=True)``; a bad value raises
``ValueError`` naming the field. Variants are made with :func:`dataclasses.replace`; the full config
goes into every recording and checkpoint as JSON (:meth:`ScenarioConfig.to_json`).

Units are in the field names (``_m``, ``_s``, ``_kmh``, ``_mps``, ``_mps2``, ``_deg``).
Defaults follow the paper (Hybrid-PPO, CARLA Town06) where it says something, and CARLA's own
code where it does not; ``docs/simulator.md`` lists the choices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

from lckit.config import JsonConfig, check_field, check_limits, require_non_negative, require_positive

WANDER_CLIP_SIGMAS = 2.5
"""A human-like driver's lateral offset from the lane centre is clipped at this many standard deviations."""


@dataclass(frozen=True, slots=True, kw_only=True)
class RoadConfig(JsonConfig):
    """A straight, Town06-like carriageway along +x. Lane 0 is the rightmost lane."""

    num_lanes: int = 4
    lane_width_m: float = 3.5
    shoulder_width_m: float = 2.5
    marking_width_m: float = 0.15
    dash_length_m: float = 3.0
    dash_gap_m: float = 6.0

    LIMITS: ClassVar[dict[str, float]] = {"lane_width_m": 10.0, "shoulder_width_m": 20.0, "marking_width_m": 1.0,
                                          "dash_length_m": 100.0, "dash_gap_m": 100.0}

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(isinstance(self.num_lanes, int) and 2 <= self.num_lanes <= 6, self, "num_lanes",
               "must be an integer in [2, 6]", self.num_lanes)
        require_positive(self, "lane_width_m", "marking_width_m", "dash_length_m", "dash_gap_m")
        require_non_negative(self, "shoulder_width_m")
        check_field(self.lane_width_m >= 2.5, self, "lane_width_m", "must be >= 2.5 m", self.lane_width_m)

    @property
    def width_m(self) -> float:
        """Width of the carriageway between the two solid edge lines."""
        return self.num_lanes * self.lane_width_m


@dataclass(frozen=True, slots=True, kw_only=True)
class TrafficConfig(JsonConfig):
    """Autopilot traffic: IDM car following with a Traffic-Manager-like gap and lane changes."""

    num_vehicles: int = 100
    speed_kmh: float = 24.0
    speed_spread_kmh: float = 2.0
    """Standard deviation of the per-vehicle desired speed (clipped at 2.5 sigma)."""
    length_m: float = 5.37  # Ford Crown
    width_m: float = 1.80
    spawn_behind_m: float = 300.0
    """Traffic is spawned from this far behind the ego's start ..."""
    spawn_ahead_m: float = 1300.0
    """... to this far ahead of it. The ego gains only ~1.7 m/s on the traffic, so ~200 m ahead already
    keeps traffic around it for the whole 600 m route; the window sets the density (100 vehicles on
    4 lanes over 1.6 km: about 64 m between vehicles; a saturated lane at 24 km/h has ~21 m)."""
    min_spawn_gap_m: float = 6.0
    ego_clearance_m: float = 20.0
    """Free space kept ahead of (and half of it behind) the ego in its lane at spawn."""
    idm_time_headway_s: float = 2.0
    idm_min_gap_m: float = 2.0
    idm_max_accel_mps2: float = 1.5
    idm_comfort_decel_mps2: float = 2.0
    idm_delta: float = 4.0
    max_decel_mps2: float = 8.0
    lane_changes: bool = True
    lane_change_duration_s: float = 5.0
    """Duration of a traffic lane change (the median across drivers when ``human_like``): naturalistic
    highway lane changes take 5 to 6 s on average (docs/simulator.md)."""
    lane_change_check_period_s: float = 0.5
    blocked_gap_min_m: float = 0.0
    blocked_gap_max_m: float = 50.0
    """A leader whose gap is in [min, max] and who is slower than the desired speed blocks."""
    blocked_speed_margin_kmh: float = 1.5
    lane_change_front_gap_m: float = 12.0
    lane_change_rear_gap_m: float = 8.0
    lane_change_rear_headway_s: float = 1.0
    random_lane_change_rate_per_min: float = 0.3
    """Rate of spontaneous lane changes (when the side lane is free), for variety in the corpus."""
    human_like: bool = True
    """Human-like drivers, as the fields below describe (docs/simulator.md gives their sources and the
    statistics they produce). False: every vehicle follows IDM exactly with the parameters above, no
    noise and no delay, and changes lanes in exactly ``lane_change_duration_s`` (with a duration of 3 s, the
    traffic of earlier versions, which configs stored before this field existed keep)."""
    driver_spread: float = 0.25
    """Per-driver spread of the car-following parameters: each driver's desired time gap, maximum
    acceleration and comfortable deceleration are lognormal with the medians above and this log-sd."""
    accel_noise_mps2: float = 0.2
    """Standard deviation of the stochastic acceleration each driver adds to IDM's (an Ornstein-Uhlenbeck
    process sampled every lane-change check and interpolated linearly in between)."""
    accel_noise_time_s: float = 2.0
    """Correlation time of that acceleration noise."""
    reaction_time_s: float = 0.5
    """Median per-driver reaction time: the applied acceleration follows the commanded one with this first
    order lag (lognormal across drivers with log-sd ``driver_spread``)."""
    lane_wander_m: float = 0.15
    """Standard deviation of each driver's lateral offset from the lane centre (an Ornstein-Uhlenbeck
    process like the acceleration noise, clipped at 2.5 standard deviations)."""
    lane_wander_time_s: float = 4.0
    """Correlation time of the lateral offset."""
    lane_change_spread: float = 0.25
    """Per-driver log-sd of the lane-change duration (lognormal, median ``lane_change_duration_s``)."""
    lane_change_eagerness_min: float = 0.3
    """Per-driver probability of acting on a blocked leader at a check, uniform in [this, 1] (1: always)."""

    LEGACY_DEFAULTS: ClassVar[dict[str, Any]] = {"human_like": False}
    LIMITS: ClassVar[dict[str, float]] = {
        "num_vehicles": 1_000_000, "speed_kmh": 300.0, "speed_spread_kmh": 100.0, "length_m": 30.0, "width_m": 5.0,
        "spawn_behind_m": 100_000.0, "spawn_ahead_m": 100_000.0, "min_spawn_gap_m": 1_000.0,
        "ego_clearance_m": 1_000.0, "idm_time_headway_s": 60.0, "idm_min_gap_m": 1_000.0, "idm_max_accel_mps2": 50.0,
        "idm_comfort_decel_mps2": 50.0, "idm_delta": 100.0, "max_decel_mps2": 100.0, "lane_change_duration_s": 60.0,
        "lane_change_check_period_s": 60.0, "blocked_gap_min_m": 10_000.0, "blocked_gap_max_m": 10_000.0,
        "blocked_speed_margin_kmh": 300.0, "lane_change_front_gap_m": 1_000.0, "lane_change_rear_gap_m": 1_000.0,
        "lane_change_rear_headway_s": 60.0, "random_lane_change_rate_per_min": 60.0, "driver_spread": 5.0,
        "accel_noise_mps2": 20.0, "accel_noise_time_s": 3_600.0, "reaction_time_s": 10.0, "lane_wander_m": 10.0,
        "lane_wander_time_s": 3_600.0, "lane_change_spread": 5.0, "lane_change_eagerness_min": 1.0,
    }  # fmt: skip
    """Plausible upper bounds (a highway's speeds, a car's size and accelerations, a human's times)."""

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(isinstance(self.num_vehicles, int) and self.num_vehicles >= 0, self, "num_vehicles",
               "must be an integer >= 0", self.num_vehicles)
        check_field(isinstance(self.human_like, bool), self, "human_like", "must be true or false", self.human_like)
        require_positive(self, "accel_noise_time_s", "lane_wander_time_s")
        require_non_negative(self, "driver_spread", "accel_noise_mps2", "reaction_time_s", "lane_wander_m",
                             "lane_change_spread")
        check_field(0.0 <= self.lane_change_eagerness_min <= 1.0, self, "lane_change_eagerness_min",
                    "must be in [0, 1]", self.lane_change_eagerness_min)
        require_positive(self, "speed_kmh", "length_m", "width_m", "idm_time_headway_s", "idm_max_accel_mps2",
                  "idm_comfort_decel_mps2", "idm_delta", "max_decel_mps2", "lane_change_duration_s",
                  "lane_change_check_period_s")
        require_non_negative(self, "speed_spread_kmh", "spawn_behind_m", "spawn_ahead_m", "min_spawn_gap_m",
                      "ego_clearance_m", "idm_min_gap_m", "blocked_gap_min_m", "blocked_gap_max_m",
                      "blocked_speed_margin_kmh", "lane_change_front_gap_m", "lane_change_rear_gap_m",
                      "lane_change_rear_headway_s", "random_lane_change_rate_per_min")
        check_field(self.blocked_gap_max_m >= self.blocked_gap_min_m, self, "blocked_gap_max_m",
               "must be >= blocked_gap_min_m", self.blocked_gap_max_m)


@dataclass(frozen=True, slots=True, kw_only=True)
class PIDGains(JsonConfig):
    """Gains of one CARLA ``PID*Controller``; ``dt_s`` is the controller's own dt parameter."""

    kp: float
    ki: float
    kd: float
    dt_s: float = 0.1

    LIMITS: ClassVar[dict[str, float]] = {"kp": 1_000.0, "ki": 1_000.0, "kd": 1_000.0, "dt_s": 10.0}

    def __post_init__(self) -> None:
        check_limits(self)
        require_non_negative(self, "kp", "ki", "kd")
        require_positive(self, "dt_s")


NEIGHBOUR_SELECTIONS = ("lanes", "nearest")
# The observation's vehicle slots with neighbour_selection="lanes", in order: (lane offset from the ego's
# target lane, -1 right / +1 left; ahead (True) or behind; rank in that lane, 1 = the nearest).
LANE_SLOTS: tuple[tuple[int, bool, int], ...] = (
    (0, True, 1), (0, False, 1),      # leader and follower in the ego's lane
    (-1, True, 1), (-1, False, 1),    # ... in the lane to its right
    (1, True, 1), (1, False, 1),      # ... in the lane to its left
    (-1, True, 2), (1, True, 2),      # the second leaders right and left: how long the gap there is
    # Wider views (num_neighbours up to 16): what the next 10-20 s bring, beyond the gaps beside the ego.
    (0, True, 2),                     # the leader's leader: a queue closing up ahead
    (-1, False, 2), (1, False, 2),    # the second followers right and left
    (-2, True, 1), (-2, False, 1),    # leader and follower two lanes right: who may move in beside the ego
    (2, True, 1), (2, False, 1),      # ... two lanes left
    (0, True, 3),                     # the third leader in the ego's lane
)

# The paper's gains. Its Ki/Kd labels may be swapped relative to CARLA's BasicAgent code
# (lateral K_I 0.05 / K_D 0.2 there), so the swapped reading is kept as a named variant.
PAPER_LATERAL = PIDGains(kp=1.95, ki=0.2, kd=0.07)
PAPER_LONGITUDINAL = PIDGains(kp=1.0, ki=0.0, kd=0.75)
SWAPPED_LATERAL = PIDGains(kp=1.95, ki=0.07, kd=0.2)
SWAPPED_LONGITUDINAL = PIDGains(kp=1.0, ki=0.75, kd=0.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class EgoConfig(JsonConfig):
    """The ego (Audi TT): kinematic bicycle model tracked by CARLA's ``VehiclePIDController``."""

    length_m: float = 4.18
    width_m: float = 1.99
    wheelbase_m: float = 2.65
    target_speed_kmh: float = 30.0
    initial_speed_kmh: float = 30.0
    start_lane: int = -1
    """Lane the ego starts in; -1 draws it from the episode seed."""
    max_steer_angle_deg: float = 70.0
    max_accel_mps2: float = 4.5
    """Acceleration at full throttle (Audi TT: 0-100 km/h in about 6 s)."""
    max_brake_decel_mps2: float = 8.0
    powertrain_lag_s: float = 0.3
    """First-order lag from pedal command to acceleration. It stands in for the engine and
    transmission dynamics of CARLA's PhysX vehicle; without it the paper's longitudinal gains
    (Kd 0.75 at dt 0.1) limit-cycle between full throttle and full brake."""
    rolling_resistance_mps2: float = 0.15
    drag_per_speed2: float = 4.0e-4
    lateral_pid: PIDGains = field(default_factory=lambda: PAPER_LATERAL)
    longitudinal_pid: PIDGains = field(default_factory=lambda: PAPER_LONGITUDINAL)
    max_throttle: float = 0.75
    max_brake: float = 0.3
    max_steer: float = 0.8
    max_steer_change: float = 0.1
    """Largest change of the steering command per control (simulation) step."""
    pid_window: int = 10
    """Errors kept for the integral and derivative terms, as CARLA's ``deque(maxlen=10)``."""
    lane_change_time_s: float = 2.0
    same_lane_time_s: float = 0.0
    waypoint_spacing_m: float = 2.0
    base_min_distance_m: float = 3.0
    distance_ratio: float = 0.5
    """Look-ahead of the local planner: base_min_distance_m + distance_ratio * speed (m/s)."""
    lane_change_tolerance_m: float = 0.3
    adaptive_cruise: bool = False
    """Off by default: the ego does not brake for a slower leader; the decision must avoid it."""
    acc_time_headway_s: float = 1.5
    acc_min_gap_m: float = 4.0

    NESTED: ClassVar[dict[str, type[JsonConfig]]] = {"lateral_pid": PIDGains, "longitudinal_pid": PIDGains}
    LIMITS: ClassVar[dict[str, float]] = {
        "length_m": 30.0, "width_m": 5.0, "wheelbase_m": 30.0, "target_speed_kmh": 300.0, "initial_speed_kmh": 300.0,
        "start_lane": 5, "max_accel_mps2": 50.0, "max_brake_decel_mps2": 100.0, "powertrain_lag_s": 10.0,
        "rolling_resistance_mps2": 10.0, "drag_per_speed2": 1.0, "max_steer_change": 2.0, "pid_window": 10_000,
        "lane_change_time_s": 60.0, "same_lane_time_s": 3_600.0, "waypoint_spacing_m": 100.0,
        "base_min_distance_m": 1_000.0, "distance_ratio": 100.0, "lane_change_tolerance_m": 10.0,
        "acc_time_headway_s": 60.0, "acc_min_gap_m": 1_000.0,
    }  # fmt: skip

    def __post_init__(self) -> None:
        check_limits(self)
        require_positive(self, "length_m", "width_m", "wheelbase_m", "target_speed_kmh", "max_steer_angle_deg",
                  "max_accel_mps2", "max_brake_decel_mps2", "max_throttle", "max_brake", "max_steer",
                  "max_steer_change", "lane_change_time_s", "waypoint_spacing_m",
                  "lane_change_tolerance_m", "acc_time_headway_s")
        require_non_negative(self, "initial_speed_kmh", "powertrain_lag_s", "rolling_resistance_mps2", "drag_per_speed2",
                      "same_lane_time_s", "base_min_distance_m", "distance_ratio", "acc_min_gap_m")
        check_field(self.wheelbase_m < self.length_m, self, "wheelbase_m", "must be shorter than length_m",
               self.wheelbase_m)
        for name in ("max_throttle", "max_brake", "max_steer"):
            check_field(getattr(self, name) <= 1.0, self, name, "must be <= 1", getattr(self, name))
        check_field(self.max_steer_angle_deg < 90, self, "max_steer_angle_deg", "must be < 90", self.max_steer_angle_deg)
        check_field(isinstance(self.pid_window, int) and self.pid_window >= 2, self, "pid_window",
               "must be an integer >= 2", self.pid_window)
        check_field(isinstance(self.start_lane, int) and self.start_lane >= -1, self, "start_lane",
               "must be -1 (random) or a lane index", self.start_lane)
        for name in ("lateral_pid", "longitudinal_pid"):
            check_field(isinstance(getattr(self, name), PIDGains), self, name, "must be a PIDGains", getattr(self, name))


@dataclass(frozen=True, slots=True, kw_only=True)
class RewardConfig(JsonConfig):
    """The paper's reward: collision, out of road, go-forward (metres) and success milestones."""

    collision: float = -500.0
    off_road: float = -10.0
    forward_per_m: float = 1.0
    milestones: tuple[float, ...] = (0.25, 0.5, 0.75, 1.0)
    """Fractions of the route at which a success reward is paid; reaching 1.0 ends the episode."""
    milestone_rewards: tuple[float, ...] = (100.0, 150.0, 200.0, 1000.0)

    MAX_MILESTONES: ClassVar[int] = 100

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(len(self.milestones) <= self.MAX_MILESTONES, self, "milestones",
                    f"must be at most {self.MAX_MILESTONES} fractions", len(self.milestones))
        check_field(len(self.milestones) == len(self.milestone_rewards) and len(self.milestones) > 0, self,
               "milestone_rewards", "must have one reward per milestone", self.milestone_rewards)
        ms = list(self.milestones)
        check_field(all(0 < m <= 1 for m in ms) and ms == sorted(ms) and ms[-1] == 1.0, self, "milestones",
               "must be increasing fractions in (0, 1] ending with 1.0", self.milestones)


@dataclass(frozen=True, slots=True, kw_only=True)
class RenderConfig(JsonConfig):
    """Ego-centred, heading-up bird's-eye semantic image."""

    image_size_px: int = 120
    resolution_m_per_px: float = 0.5
    max_vehicles_drawn: int = 32

    LIMITS: ClassVar[dict[str, float]] = {"image_size_px": 1024, "resolution_m_per_px": 100.0,
                                          "max_vehicles_drawn": 10_000}

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(isinstance(self.image_size_px, int) and 16 <= self.image_size_px <= 1024, self,
               "image_size_px", "must be an integer in [16, 1024]", self.image_size_px)
        require_positive(self, "resolution_m_per_px")
        check_field(isinstance(self.max_vehicles_drawn, int) and self.max_vehicles_drawn >= 1, self,
               "max_vehicles_drawn", "must be an integer >= 1", self.max_vehicles_drawn)


@dataclass(frozen=True, slots=True, kw_only=True)
class ScenarioConfig(JsonConfig):
    """Everything that defines an episode, given its seed."""

    NESTED: ClassVar[dict[str, type[JsonConfig]]] = {"road": RoadConfig, "traffic": TrafficConfig, "ego": EgoConfig,
                                                      "reward": RewardConfig, "render": RenderConfig}
    LEGACY_DEFAULTS: ClassVar[dict[str, Any]] = {"neighbour_selection": "nearest"}

    road: RoadConfig = field(default_factory=RoadConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    ego: EgoConfig = field(default_factory=EgoConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    dt_s: float = 0.05
    """Simulation step (20 Hz)."""
    decision_period_s: float = 0.5
    route_length_m: float = 600.0
    time_limit_s: float = 75.0
    """Episode time limit (truncation): the route takes 72 s at 30 km/h, so a lane keeper with
    adaptive cruise, held up by slower traffic, almost never makes it (docs/simulator.md)."""
    history_steps: int = 10
    num_neighbours: int = 8
    neighbour_selection: str = "lanes"
    """Which K vehicles the observation shows (within ``sensing_range_m``): ``lanes`` (fixed slots: the
    leader and follower in the ego's lane and in the lanes right and left of it, then the second leaders
    right and left; :data:`LANE_SLOTS`; K <= 16, the slots after the eighth a wider view) or ``nearest``
    (the K nearest by distance, nearest first). PPO on ``pure`` observations wins far more of the held-out
    episodes with ``lanes`` (docs/simulator.md). Configs stored before this field existed read as ``nearest``."""
    sensing_range_m: float = 80.0
    observe_acceleration: bool = False
    """``current`` gets a tenth column, ``accel_mps2``: each vehicle's acceleration along its heading over
    the last step (what a radar track or CARLA's ``get_acceleration`` shows). The traffic's acceleration
    tells its intent (an IDM follower closing on its desired speed, a leader braking), which speeds alone do
    not; off by default, so stored observations keep their nine columns. Shown to PPO (``pure`` and
    ``hybrid``), it made no difference beyond the spread of training seeds (docs/results/accel)."""
    render_image: bool = True
    invalid_lane_change: str = "refuse"
    """A change towards a lane that does not exist: ``refuse`` (not carried out, rewarded ``reward.off_road``,
    the episode goes on: CARLA's agent finds no waypoint there, and the paper's outcomes have no off-road)
    or ``leave_road`` (carried out; the ego leaves the road and the episode ends ``off_road``)."""

    LIMITS: ClassVar[dict[str, float]] = {"dt_s": 1.0, "decision_period_s": 60.0, "route_length_m": 100_000.0,
                                          "time_limit_s": 86_400.0, "history_steps": 1_000, "num_neighbours": 64,
                                          "sensing_range_m": 10_000.0}
    """Plausible upper bounds: a day-long episode, a 100 km route, 1000 steps of history, 64 vehicles shown."""
    MIN_DT_S: ClassVar[float] = 1e-3
    MAX_STEPS: ClassVar[int] = 1_000_000
    """The most simulation steps an episode may have (``time_limit_s / dt_s``): 14 hours at 20 Hz."""

    def __post_init__(self) -> None:
        check_limits(self)
        for name, want in self.NESTED.items():
            check_field(isinstance(getattr(self, name), want), self, name, f"must be a {want.__name__}",
                        getattr(self, name))
        require_positive(self, "dt_s", "decision_period_s", "route_length_m", "time_limit_s", "sensing_range_m")
        check_field(self.dt_s >= self.MIN_DT_S, self, "dt_s", f"must be >= {self.MIN_DT_S}", self.dt_s)
        check_field(self.time_limit_s / self.dt_s <= self.MAX_STEPS, self, "time_limit_s",
                    f"must be at most {self.MAX_STEPS} steps of dt_s ({self.MAX_STEPS * self.dt_s:g} s)",
                    self.time_limit_s)
        tc = self.traffic
        if tc.human_like:  # the wander (clipped) must keep a car (the ego too, on autopilot) and the neighbour
            # index's margin strictly inside its lane
            width = max(tc.width_m, self.ego.width_m)
            check_field(2 * WANDER_CLIP_SIGMAS * tc.lane_wander_m + width + 0.2 < self.road.lane_width_m - 1e-6, tc,
                        "lane_wander_m",
                        f"lets a {width} m wide vehicle leave its {self.road.lane_width_m} m lane; lower it",
                        tc.lane_wander_m)
        ratio = self.decision_period_s / self.dt_s
        check_field(abs(ratio - round(ratio)) < 1e-9, self, "decision_period_s", "must be a multiple of dt_s",
               self.decision_period_s)
        check_field(self.invalid_lane_change in ("refuse", "leave_road"), self, "invalid_lane_change",
               "must be 'refuse' or 'leave_road'", self.invalid_lane_change)
        check_field(isinstance(self.history_steps, int) and self.history_steps >= 1, self, "history_steps",
               "must be an integer >= 1", self.history_steps)
        check_field(isinstance(self.num_neighbours, int) and self.num_neighbours >= 1, self, "num_neighbours",
               "must be an integer >= 1", self.num_neighbours)
        check_field(self.neighbour_selection in NEIGHBOUR_SELECTIONS, self, "neighbour_selection",
               f"must be one of {', '.join(NEIGHBOUR_SELECTIONS)}", self.neighbour_selection)
        check_field(self.neighbour_selection != "lanes" or self.num_neighbours <= len(LANE_SLOTS), self,
               "num_neighbours", f"must be <= {len(LANE_SLOTS)} with neighbour_selection='lanes'",
               self.num_neighbours)
        check_field(self.time_limit_s >= self.decision_period_s, self, "time_limit_s",
               "must be >= decision_period_s", self.time_limit_s)
        if self.ego.start_lane >= self.road.num_lanes:
            raise ValueError(f"EgoConfig.start_lane must be < road.num_lanes ({self.road.num_lanes}), "
                             f"got {self.ego.start_lane}")
        # Spawn feasibility: every lane must hold its share of vehicles at the minimum spacing.
        t = self.traffic
        window = t.spawn_behind_m + t.spawn_ahead_m - t.ego_clearance_m * 1.5
        per_lane = math.ceil(t.num_vehicles / self.road.num_lanes)
        need = per_lane * (t.length_m + t.min_spawn_gap_m)
        if t.num_vehicles and need > window:
            raise ValueError(
                f"TrafficConfig.num_vehicles={t.num_vehicles} does not fit: {per_lane} vehicles per lane "
                f"need {need:.0f} m but the spawn window is {window:.0f} m (raise spawn_ahead_m/"
                f"spawn_behind_m or lower min_spawn_gap_m)")

    @property
    def steps_per_decision(self) -> int:
        return round(self.decision_period_s / self.dt_s)

    @property
    def max_steps(self) -> int:
        """Simulation steps in the time limit."""
        return round(self.time_limit_s / self.dt_s)


def paper_scenario(**overrides: Any) -> ScenarioConfig:
    """The paper's lane-change scenario (100 vehicles at ~24 km/h, ego targeting 30 km/h)."""
    return ScenarioConfig(**overrides)


def corpus_scenario(**overrides: Any) -> ScenarioConfig:
    """The paper's trajectory corpus: 20 autopilot vehicles, 20 Hz, 2000 steps (100 s).

    The ego is driven by the autopilot too when recording it (``lc-record --driver autopilot``).
    """
    traffic = TrafficConfig(num_vehicles=20, spawn_behind_m=80.0, spawn_ahead_m=220.0)
    kwargs: dict[str, Any] = dict(traffic=traffic, route_length_m=5000.0, time_limit_s=100.0,
                                  render_image=False)
    kwargs.update(overrides)
    return ScenarioConfig(**kwargs)


def light_scenario(**overrides: Any) -> ScenarioConfig:
    """A smaller version of the paper's task (30 vehicles, 300 m route) for quick experiments."""
    kwargs: dict[str, Any] = dict(traffic=TrafficConfig(num_vehicles=30, spawn_behind_m=80.0, spawn_ahead_m=200.0),
                                  route_length_m=300.0, time_limit_s=40.0)
    kwargs.update(overrides)
    return ScenarioConfig(**kwargs)


def tiny_scenario(**overrides: Any) -> ScenarioConfig:
    """8 vehicles on a 150 m route (25 s): for tests and smoke runs, not for results."""
    kwargs: dict[str, Any] = dict(traffic=TrafficConfig(num_vehicles=8, spawn_behind_m=40.0, spawn_ahead_m=100.0),
                                  route_length_m=150.0, time_limit_s=25.0)
    kwargs.update(overrides)
    return ScenarioConfig(**kwargs)
