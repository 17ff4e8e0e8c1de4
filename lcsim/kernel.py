"""The simulator's compiled core: every per-step computation of :class:`~lcsim.sim.HighwaySim`, compiled with numba.

One call advances any number of environments by any number of simulation steps; inside it, each environment
runs its steps one after the other on scalars (no temporary arrays, no Python per vehicle): IDM car following,
the human-like drivers' random processes, Traffic-Manager-like lane changes at the check period, the minimum-jerk
lateral profile, the ego's PID controller on a kinematic bicycle model (:func:`lcsim.control.ego_law`), the
neighbour index, collision, lane-invasion and off-road sensors, and the position history. An environment that
meets an event (contact, the road edge, the route's end) can be frozen there for the rest of the call.

The state lives in a few blocks that the simulator exposes as named views (``sim.x`` is ``sim.vf[VF_X]``):

- ``vf`` ``(len(VF_NAMES), E, N)`` float64, ``vi`` ``(len(VI_NAMES), E, N)`` int64, ``vb`` ``(len(VB_NAMES), E, N)``
  bool: per vehicle;
- ``ef`` float64, ``ei`` int64, ``eb`` bool ``(len(E*_NAMES), E)``: per environment; ``keys`` ``(3, E)`` uint64;
- ``hist`` ``(E, H, N, 2)``, the PID windows ``pid_err`` ``(E, W, 2)`` and ``pid_count`` ``(E, 1)``;
- ``p`` (float64) and ``ip`` (int64): the scenario's constants, laid out by :func:`kernel_params`.

Few arguments keep a call cheap (numba checks each one). The results depend on an environment's own state only,
so a batch and single environments with the same seeds agree bit for bit.

The neighbour index: the vehicles of an environment sorted by ``x`` (ties by index; an insertion sort from the
previous order, which a step rarely changes); a vehicle is a member of every lane its body overlaps (its lateral
extent accounts for its yaw) and, while a traffic vehicle changes lanes, of its target lane; its leader is the
nearest vehicle ahead that shares one of its lanes. Searches for the nearest member of a lane ahead or behind walk
the sorted order from the vehicle's position (a few places on a highway).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from lcsim.config import WANDER_CLIP_SIGMAS

# Per-vehicle blocks: names of their rows (the simulator's attributes of the same names are views of them).
VF_NAMES = ("x", "y", "yaw", "speed", "accel", "lc_t0", "lc_y0", "lc_y1", "v0", "length", "width",
            "noise", "wander_base", "wander_next", "wander_step",
            "time_headway", "max_accel", "inv_2sqrt_ab", "lag", "lc_inv_duration", "eagerness",
            "gap", "lead_speed")
VI_NAMES = ("lane", "target_lane", "order", "pos_of", "lo", "hi", "extra", "lead")
VB_NAMES = ("lc_active", "is_traffic")
# Per-environment blocks.
EF_NAMES = ("t_s", "path_x0", "path_len", "path_y0", "path_y1", "steer", "throttle", "brake", "ego_accel")
EI_NAMES = ("step", "collision_with", "lane_invasion", "hist_count", "traffic_collisions")
EB_NAMES = ("ego_lc_active", "off_road", "frozen")
KEY_NAMES = ("key", "lane_change_base", "noise_base")

(X, Y, YAW, SPEED, ACCEL, LC_T0, LC_Y0, LC_Y1, V0, LENGTH, WIDTH, NOISE, W_BASE, W_NEXT, W_STEP,
 HEADWAY, MAX_ACCEL, INV_2SQRT_AB, LAG, LC_INV_DUR, EAGERNESS, GAP, LEAD_SPEED) = range(len(VF_NAMES))
LANE, TARGET, ORDER, POS_OF, LO, HI, EXTRA, LEAD = range(len(VI_NAMES))
LC_ACTIVE, IS_TRAFFIC = range(len(VB_NAMES))
T_S, PATH_X0, PATH_LEN, PATH_Y0, PATH_Y1, STEER, THROTTLE, BRAKE, EGO_ACCEL = range(len(EF_NAMES))
STEP, COLLISION_WITH, LANE_INVASION, HIST_COUNT, TRAFFIC_COLLISIONS = range(len(EI_NAMES))
EGO_LC_ACTIVE, OFF_ROAD, FROZEN = range(len(EB_NAMES))
KEY, LANE_CHANGE_BASE, NOISE_BASE = range(len(KEY_NAMES))

# The scenario's constants: float parameters (p) and integer ones (ip).
P_NAMES = ("dt", "lane_width", "road_width", "margin",
           "idm_a", "idm_t", "idm_two_sqrt_ab", "idm_s0", "idm_delta", "max_decel",
           "lc_duration_inv", "blocked_min", "blocked_max", "blocked_margin_mps", "lc_front_gap", "lc_rear_gap",
           "lc_rear_headway", "p_spontaneous",
           "noise_rho", "noise_scale", "wander_rho", "wander_scale", "wander_limit",
           "target_speed", "lag_alpha", "acc_min_gap", "acc_headway", "waypoint_spacing", "base_min_distance",
           "distance_ratio", "max_throttle", "max_brake", "max_steer_change", "max_steer", "rolling_resistance",
           "drag", "max_accel", "max_brake_decel", "steer_angle_rad", "two_over_wheelbase", "lc_tolerance",
           "kp_long", "kp_lat", "kd_dt_long", "kd_dt_lat", "ki_dt_long", "ki_dt_lat", "route", "same_lane_time",
           "lane_change_time", "r_collision", "r_off_road", "r_forward", "time_limit")
IP_NAMES = ("num_lanes", "check_every", "human", "lane_changes", "autopilot_ego", "adaptive_cruise", "idm_delta_int")
(DT, LW, ROAD_W, MARGIN, IDM_A, IDM_T, IDM_2SQRT_AB, IDM_S0, IDM_DELTA, MAX_DECEL, LC_DUR_INV, BLK_MIN, BLK_MAX,
 BLK_MARGIN, LC_FRONT, LC_REAR, LC_REAR_HW, P_SPONT, NOISE_RHO, NOISE_SCALE, WANDER_RHO, WANDER_SCALE, WANDER_LIMIT,
 TARGET_SPEED, LAG_ALPHA, ACC_MIN_GAP, ACC_HEADWAY, WP_SPACING, BASE_MIN_DIST, DIST_RATIO, MAX_THROTTLE, MAX_BRAKE,
 MAX_STEER_CHANGE, MAX_STEER, ROLLING, DRAG, EGO_MAX_ACCEL, EGO_MAX_BRAKE_DECEL, STEER_ANGLE, TWO_OVER_WB,
 LC_TOLERANCE, KP_LONG, KP_LAT, KD_DT_LONG, KD_DT_LAT, KI_DT_LONG, KI_DT_LAT, ROUTE, SAME_LANE_TIME, LANE_CHANGE_TIME,
 R_COLLISION, R_OFF_ROAD, R_FORWARD, TIME_LIMIT) = range(len(P_NAMES))
(NUM_LANES, CHECK_EVERY, HUMAN, LANE_CHANGES, AUTOPILOT_EGO, ADAPTIVE_CRUISE, IDM_DELTA_INT) = range(len(IP_NAMES))

INDEX_MARGIN_M = 0.1  # lateral margin of lane membership (m)

# Counter-based random numbers (lcsim.rng, the same function of key, step and index).
_GOLDEN, _M1, _M2 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_S11, _S20, _S27, _S30, _S31 = np.uint64(11), np.uint64(20), np.uint64(27), np.uint64(30), np.uint64(31)
_INV_2_53 = 1.0 / (1 << 53)
_SQRT12 = math.sqrt(12.0)


def kernel_params(config, autopilot_ego: bool) -> tuple[np.ndarray, np.ndarray]:
    """The ``(p, ip)`` arrays of a scenario (:data:`P_NAMES`, :data:`IP_NAMES`)."""
    tc, ec, road, dt = config.traffic, config.ego, config.road, config.dt_s
    check_every = max(1, round(tc.lane_change_check_period_s / dt))
    period = check_every * dt
    noise_rho = math.exp(-period / tc.accel_noise_time_s) if tc.human_like else 0.0
    wander_rho = math.exp(-period / tc.lane_wander_time_s) if tc.human_like else 0.0
    lon, lat = ec.longitudinal_pid, ec.lateral_pid
    values = {
        "dt": dt, "lane_width": road.lane_width_m, "road_width": road.width_m, "margin": INDEX_MARGIN_M,
        "idm_a": tc.idm_max_accel_mps2, "idm_t": tc.idm_time_headway_s,
        "idm_two_sqrt_ab": 2.0 * math.sqrt(tc.idm_max_accel_mps2 * tc.idm_comfort_decel_mps2),
        "idm_s0": tc.idm_min_gap_m, "idm_delta": tc.idm_delta, "max_decel": tc.max_decel_mps2,
        "lc_duration_inv": 1.0 / tc.lane_change_duration_s, "blocked_min": tc.blocked_gap_min_m,
        "blocked_max": tc.blocked_gap_max_m, "blocked_margin_mps": tc.blocked_speed_margin_kmh / 3.6,
        "lc_front_gap": tc.lane_change_front_gap_m, "lc_rear_gap": tc.lane_change_rear_gap_m,
        "lc_rear_headway": tc.lane_change_rear_headway_s,
        "p_spontaneous": tc.random_lane_change_rate_per_min * tc.lane_change_check_period_s / 60.0,
        "noise_rho": noise_rho, "noise_scale": tc.accel_noise_mps2 * math.sqrt(1.0 - noise_rho * noise_rho),
        "wander_rho": wander_rho, "wander_scale": tc.lane_wander_m * math.sqrt(1.0 - wander_rho * wander_rho),
        "wander_limit": WANDER_CLIP_SIGMAS * tc.lane_wander_m,
        "target_speed": ec.target_speed_kmh / 3.6,
        "lag_alpha": min(1.0, dt / ec.powertrain_lag_s) if ec.powertrain_lag_s > 0 else 1.0,
        "acc_min_gap": ec.acc_min_gap_m, "acc_headway": ec.acc_time_headway_s,
        "waypoint_spacing": ec.waypoint_spacing_m, "base_min_distance": ec.base_min_distance_m,
        "distance_ratio": ec.distance_ratio, "max_throttle": ec.max_throttle, "max_brake": ec.max_brake,
        "max_steer_change": ec.max_steer_change, "max_steer": ec.max_steer,
        "rolling_resistance": ec.rolling_resistance_mps2, "drag": ec.drag_per_speed2,
        "max_accel": ec.max_accel_mps2, "max_brake_decel": ec.max_brake_decel_mps2,
        "steer_angle_rad": math.radians(ec.max_steer_angle_deg), "two_over_wheelbase": 2.0 / ec.wheelbase_m,
        "lc_tolerance": ec.lane_change_tolerance_m,
        "kp_long": lon.kp, "kp_lat": lat.kp, "kd_dt_long": lon.kd / lon.dt_s, "kd_dt_lat": lat.kd / lat.dt_s,
        "ki_dt_long": lon.ki * lon.dt_s, "ki_dt_lat": lat.ki * lat.dt_s, "route": config.route_length_m,
        "same_lane_time": ec.same_lane_time_s, "lane_change_time": ec.lane_change_time_s,
        "r_collision": config.reward.collision, "r_off_road": config.reward.off_road,
        "r_forward": config.reward.forward_per_m, "time_limit": config.time_limit_s,
    }
    delta = tc.idm_delta
    ints = {"num_lanes": road.num_lanes, "check_every": check_every, "human": int(tc.human_like),
            "lane_changes": int(tc.lane_changes), "autopilot_ego": int(autopilot_ego),
            "adaptive_cruise": int(ec.adaptive_cruise), "idm_delta_int": int(delta) if delta in (2, 4) else 0}
    return (np.array([values[k] for k in P_NAMES], dtype=np.float64),
            np.array([ints[k] for k in IP_NAMES], dtype=np.int64))


# ----------------------------------------------------------------------------------------------- random numbers
@njit(cache=True, inline="always")
def _mix(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True, inline="always")
def uniform_one(base, step, i):
    """The uniform draw in [0, 1) of :func:`lcsim.rng.uniform` for counter ``i`` at ``step``, from the stream base."""
    ctr = (np.uint64(step) << _S20) + np.uint64(i)
    z = _mix(ctr * _GOLDEN + base)
    return float(z >> _S11) * _INV_2_53


# ----------------------------------------------------------------------------------- car following and control
@njit(cache=True, inline="always")
def idm(v, v0, gap, dv, a, headway, sqrt_ab_term, per_driver, s0, delta_int, delta, max_decel):
    """Intelligent Driver Model acceleration (m/s^2), clipped to [-max_decel, a].

    ``s* = s0 + v T + v dv / (2 sqrt(a b))``; ``sqrt_ab_term`` is ``1 / (2 sqrt(a b))`` of the driver when
    ``per_driver``, else ``2 sqrt(a b)`` (divided by). ``gap`` is inf without a leader; ``delta_int`` is 2 or 4 for
    those powers by squaring, 0 for ``delta`` by pow.
    """
    s = v * dv
    s = s * sqrt_ab_term if per_driver else s / sqrt_ab_term
    s = max(s + v * headway, 0.0) + s0
    ratio = v / max(v0, 0.1)
    if delta_int == 4:
        free = ratio * ratio
        free = free * free
    elif delta_int == 2:
        free = ratio * ratio
    else:
        free = ratio ** delta
    inter = s / max(gap, 0.1)
    inter = inter * inter
    acc = ((1.0 - free) - inter) * a
    return min(max(acc, -max_decel), a)


@njit(cache=True)
def idm_array(v, v0, gap, dv, a, headway, sqrt_ab_term, per_driver, s0, delta_int, delta, max_decel):
    """:func:`idm` over 1-D arrays (``a``, ``headway``, ``sqrt_ab_term`` arrays of the same length)."""
    out = np.empty(v.shape[0])
    for i in range(v.shape[0]):
        out[i] = idm(v[i], v0[i], gap[i], dv[i], a[i], headway[i], sqrt_ab_term[i], per_driver, s0, delta_int, delta,
                     max_decel)
    return out


@njit(cache=True)
def ego_law(p, x, y, yaw, speed, lead_gap, px0, plen, py0, py1, steer_past, accel_past, adaptive_cruise, window,
            slot, count):
    """The ego's control law: CARLA's local planner and ``VehiclePIDController`` on the planned path, a first-order
    powertrain lag and the kinematic bicycle model, one step.

    The planned path is the lateral move from ``py0`` to ``py1`` over ``plen`` metres from ``px0``. The PID window
    ``window`` ``(W, 2)`` (longitudinal, lateral errors by ring slot) receives this step's errors at ``slot``; the
    previous ones are at the slot before; ``count`` errors have been pushed, this one included. As in CARLA: errors
    are kept over the last W steps, the integral is ``sum(window) * dt``, the derivative ``(e - e_prev) / dt``,
    both zero until two errors exist; the speed error is in km/h; the heading error is the signed angle from the
    heading to the target waypoint.

    Returns ``(x, y, yaw, speed, accel, steer, throttle, brake)`` after the step.
    """
    target_speed = p[TARGET_SPEED]
    if adaptive_cruise:
        target_speed = min(target_speed, max((lead_gap - p[ACC_MIN_GAP]) / p[ACC_HEADWAY], 0.0))
    # Local planner: the first waypoint (every waypoint_spacing_m along the path) beyond the look-ahead.
    sp = p[WP_SPACING]
    tx = px0 + math.ceil((x + (p[BASE_MIN_DIST] + p[DIST_RATIO] * speed) - px0) / sp) * sp
    frac = min(max((tx - px0) / plen, 0.0), 1.0)
    ty = py0 + (py1 - py0) * frac
    e_speed = (target_speed - speed) * 3.6
    e_head = (math.atan2(ty - y, tx - x) - yaw + math.pi) % (2 * math.pi) - math.pi
    # PID, both controllers.
    w = window.shape[0]
    prev = (slot - 1) % w
    prev_speed, prev_head = window[prev, 0], window[prev, 1]
    window[slot, 0] = e_speed
    window[slot, 1] = e_head
    if count >= 2:
        sum_speed, sum_head = window[0, 0], window[0, 1]
        for k in range(1, w):
            sum_speed += window[k, 0]
            sum_head += window[k, 1]
        u_long = p[KP_LONG] * e_speed + (e_speed - prev_speed) * p[KD_DT_LONG] + sum_speed * p[KI_DT_LONG]
        u_lat = p[KP_LAT] * e_head + (e_head - prev_head) * p[KD_DT_LAT] + sum_head * p[KI_DT_LAT]
    else:
        u_long = p[KP_LONG] * e_speed
        u_lat = p[KP_LAT] * e_head
    u_long = min(max(u_long, -1.0), 1.0)
    u_lat = min(max(u_lat, -1.0), 1.0)
    # VehiclePIDController.run_step: throttle and brake capped, steering rate-limited and clipped.
    throttle = min(max(u_long, 0.0), p[MAX_THROTTLE])
    brake = min(max(-u_long, 0.0), p[MAX_BRAKE])
    lo = max(steer_past - p[MAX_STEER_CHANGE], -p[MAX_STEER])
    hi = min(steer_past + p[MAX_STEER_CHANGE], p[MAX_STEER])
    steer = min(max(u_lat, lo), hi)
    # Pedals to acceleration (rolling resistance and drag, none at standstill), through the powertrain lag.
    resist = (p[ROLLING] + p[DRAG] * speed * speed) if speed > 0.0 else 0.0
    drive = throttle * p[EGO_MAX_ACCEL] - brake * p[EGO_MAX_BRAKE_DECEL] - resist
    accel = accel_past + (drive - accel_past) * p[LAG_ALPHA]
    # Kinematic bicycle about the centre of gravity (mid-wheelbase), one Euler step.
    beta = math.atan(0.5 * math.tan(steer * p[STEER_ANGLE]))
    heading = yaw + beta
    vdt = speed * p[DT]
    return (x + vdt * math.cos(heading), y + vdt * math.sin(heading), yaw + vdt * p[TWO_OVER_WB] * math.sin(beta),
            max(speed + accel * p[DT], 0.0), accel, steer, throttle, brake)


@njit(cache=True)
def stream_bases(keys, salt):
    """``(E,)`` the stream bases of keys ``keys`` for a stream's ``salt`` (:func:`lcsim.rng.stream_base`)."""
    out = np.empty_like(keys)
    for i in range(keys.shape[0]):
        out[i] = _mix(keys[i] ^ salt)
    return out


@njit(cache=True)
def uniform_draws(bases, steps, n):
    """``(E, n)``: the draws :func:`uniform_one` gives counters ``0 .. n-1`` of each environment at its step."""
    out = np.empty((bases.shape[0], n))
    for e in range(bases.shape[0]):
        for i in range(n):
            out[e, i] = uniform_one(bases[e], steps[e], i)
    return out


# ---------------------------------------------------------------------------------------------------------- spawn
SPAWN_NAMES = ("spacing", "half_spacing", "lo_w", "zone_lo", "zone", "speed_kmh", "speed_spread_kmh",
               "ego_target_speed", "ego_initial_speed", "lane_width")
"""The constants of :func:`spawn_env` (:meth:`lcsim.sim.HighwaySim._spawn` computes them once)."""


@njit(cache=True)
def spawn_env(e, ego_lane, lane_of, counts, draws, spread_z, key, sp, autopilot_ego, vf, vi, vb, ef, ei, eb, keys):
    """A new episode's state in environment ``e``, from its random draws (made in this order by the caller):
    traffic vehicle ``i`` in lane ``lane_of[i]`` (``counts`` per lane); ``draws``, lane after lane, a uniform draw
    in the lane's free length per vehicle in it; ``spread_z`` ``(N,)`` standard normal draws of the desired
    speeds; ``key`` the random streams' key. In a lane, the sorted draws plus one vehicle's spacing each give the
    vehicles' places in index order, those past the ego's spot moved beyond its clearance (the ego's lane). The
    same operations in the same order as the numpy code it replaced, so the same bits."""
    spacing, half_spacing, lo_w, zone_lo, zone = sp[0], sp[1], sp[2], sp[3], sp[4]
    speed_kmh, spread_kmh, lw = sp[5], sp[6], sp[9]
    n = vf.shape[2]
    x, y = vf[X, e], vf[Y, e]
    x[0] = 0.0
    start = 0
    for lane in range(counts.shape[0]):
        k = counts[lane]
        if k == 0:
            continue
        pos = np.sort(draws[start:start + k])
        start += k
        shift = zone if lane == ego_lane else 0.0
        j = 0
        for i in range(n - 1):
            if lane_of[i] == lane:
                p = ((lo_w + pos[j]) + float(j) * spacing) + half_spacing
                if shift != 0.0 and p >= zone_lo:
                    p = p + shift
                x[1 + i] = p
                j += 1
    for v in range(n):
        z = min(max(spread_z[v], -2.5), 2.5) * spread_kmh
        v0 = max((speed_kmh + z) / 3.6, 1.0)
        if v == 0 and not autopilot_ego:
            v0 = sp[7]
        ln = ego_lane if v == 0 else lane_of[v - 1]
        vi[LANE, e, v] = ln
        vi[TARGET, e, v] = ln
        yv = (ln + 0.5) * lw
        y[v] = yv
        vf[YAW, e, v] = 0.0
        vf[V0, e, v] = v0
        vf[SPEED, e, v] = v0
        vf[ACCEL, e, v] = 0.0
        vb[LC_ACTIVE, e, v] = False
        vf[LC_T0, e, v] = 0.0
        vf[LC_Y0, e, v] = yv
        vf[LC_Y1, e, v] = yv
    if not autopilot_ego:
        vf[SPEED, e, 0] = sp[8]
    y_c = (ego_lane + 0.5) * lw
    ef[PATH_X0, e], ef[PATH_LEN, e], ef[PATH_Y0, e], ef[PATH_Y1, e] = 0.0, 1.0, y_c, y_c
    eb[EGO_LC_ACTIVE, e] = False
    ef[STEER, e] = ef[THROTTLE, e] = ef[BRAKE, e] = ef[EGO_ACCEL, e] = 0.0
    ei[STEP, e] = 0
    ef[T_S, e] = 0.0
    keys[KEY, e] = key
    ei[COLLISION_WITH, e] = -1
    ei[LANE_INVASION, e] = -1
    eb[OFF_ROAD, e] = False
    ei[TRAFFIC_COLLISIONS, e] = 0


@njit(cache=True)
def driver_values(e_headway, e_accel, e_decel, e_reaction, e_duration, eagerness, dp):
    """``(6, n)`` human-like drivers' parameters (:class:`lcsim.traffic.DriverParams` fields, in order) from the
    exponentials of their scaled normal draws (numpy's ``exp``, made by the caller) and the medians ``dp``:
    headway, accel, decel, reaction time, lane-change duration, ``dt``; the numpy code's operations in its order."""
    n = e_headway.shape[0]
    out = np.empty((6, n))
    for v in range(n):
        a = dp[1] * e_accel[v]
        b = dp[2] * e_decel[v]
        out[0, v] = dp[0] * e_headway[v]
        out[1, v] = a
        out[2, v] = 0.5 / math.sqrt(a * b)
        out[3, v] = min(1.0, dp[5] / max(dp[3] * e_reaction[v], 1e-9)) if dp[3] > 0 else 1.0
        out[4, v] = 1.0 / (dp[4] * e_duration[v])
        out[5, v] = eagerness[v]
    return out


@njit(cache=True)
def spawn_noise(e, noise_z, wander_z, accel_noise, lane_wander, vf, vb):
    """The human-like drivers' acceleration noise and lane wander of environment ``e`` at spawn (from standard
    normal draws ``(N,)``; none for a vehicle that is not traffic), the wander added to ``y``."""
    traffic = vb[IS_TRAFFIC, e]
    for v in range(vf.shape[2]):
        tr = 1.0 if traffic[v] else 0.0
        vf[NOISE, e, v] = (accel_noise * noise_z[v]) * tr
        w = (min(max(wander_z[v], -WANDER_CLIP_SIGMAS), WANDER_CLIP_SIGMAS) * lane_wander) * tr
        vf[W_BASE, e, v] = w
        vf[W_NEXT, e, v] = w
        vf[W_STEP, e, v] = 0.0
        vf[Y, e, v] = vf[Y, e, v] + w


# ------------------------------------------------------------------------------------------------ neighbour index
@njit(cache=True)
def _build_index_env(e, p, ip, vf, vi, vb, scratch_lanes):
    """The neighbour index of environment ``e``: sorted order, lane membership, leaders, gaps, leader speeds."""
    n = vf.shape[2]
    num_lanes = ip[NUM_LANES]
    x, y, yaw, speed = vf[X, e], vf[Y, e], vf[YAW, e], vf[SPEED, e]
    length, width = vf[LENGTH, e], vf[WIDTH, e]
    order, pos_of, lo, hi, extra, lead = vi[ORDER, e], vi[POS_OF, e], vi[LO, e], vi[HI, e], vi[EXTRA, e], vi[LEAD, e]
    lc_active, target = vb[LC_ACTIVE, e], vi[TARGET, e]
    inv_lw, margin = 1.0 / p[LW], p[MARGIN]
    # Insertion sort from the previous order, by (x, index): a step rarely changes it.
    for i in range(1, n):
        v = order[i]
        xv = x[v]
        j = i - 1
        while j >= 0:
            u = order[j]
            xu = x[u]
            if xu > xv or (xu == xv and u > v):
                order[j + 1] = u
                j -= 1
            else:
                break
        order[j + 1] = v
    for i in range(n):
        pos_of[order[i]] = i
    # Lanes each body touches, and the target lane of a traffic vehicle changing lanes.
    for v in range(n):
        if yaw[v] == 0.0:
            half = 0.5 * width[v] + margin
        else:
            sy = abs(math.sin(yaw[v]))
            half = 0.5 * (sy * length[v] + math.sqrt(1.0 - sy * sy) * width[v]) + margin
        lo[v] = math.floor((y[v] - half) * inv_lw)
        hi[v] = math.floor((y[v] + half) * inv_lw)
        extra[v] = target[v] if lc_active[v] else -1
    # Leaders: scan from the front, keeping the nearest member of every lane seen so far.
    nearest = scratch_lanes
    for lane in range(num_lanes):
        nearest[lane] = n
    gap, lead_speed = vf[GAP, e], vf[LEAD_SPEED, e]
    for q in range(n - 1, -1, -1):
        v = order[q]
        a, b, c = max(lo[v], 0), min(hi[v], num_lanes - 1), extra[v]
        best = n
        for lane in range(a, b + 1):
            if nearest[lane] < best:
                best = nearest[lane]
        if 0 <= c < num_lanes and (c < a or c > b) and nearest[c] < best:
            best = nearest[c]
        if best < n:
            u = order[best]
            lead[v] = u
            gap[v] = (x[u] - x[v]) - 0.5 * (length[v] + length[u])
            lead_speed[v] = speed[u]
        else:
            lead[v] = -1
            gap[v] = np.inf
            lead_speed[v] = 0.0
        for lane in range(a, b + 1):
            nearest[lane] = q
        if 0 <= c < num_lanes:
            nearest[c] = q


@njit(cache=True)
def build_index(envs, p, ip, vf, vi, vb, fresh):
    """Rebuild the neighbour index of environments ``envs`` (``fresh``: forget the previous order first)."""
    n = vf.shape[2]
    scratch = np.empty(max(ip[NUM_LANES], 1), dtype=np.int64)
    for e in envs:
        if fresh:
            for i in range(n):
                vi[ORDER, e, i] = i
        _build_index_env(e, p, ip, vf, vi, vb, scratch)


@njit(cache=True)
def finish_spawn(envs, p, ip, vf, vi, vb, ei, eb, hist, pid_err, pid_count):
    """After :func:`spawn_env` of environments ``envs``: unfreeze them, clear their PID windows, build their
    neighbour index afresh and fill their position history with the spawn positions (one entry)."""
    build_index(envs, p, ip, vf, vi, vb, True)
    for e in envs:
        eb[FROZEN, e] = False
        pid_err[e] = 0.0
        pid_count[e] = 0
        for t in range(hist.shape[1]):
            for v in range(hist.shape[2]):
                hist[e, t, v, 0] = vf[X, e, v]
                hist[e, t, v, 1] = vf[Y, e, v]
        ei[HIST_COUNT, e] = 1


@njit(cache=True, inline="always")
def _is_member(vi, e, v, lane):
    return (vi[LO, e, v] <= lane <= vi[HI, e, v]) or vi[EXTRA, e, v] == lane


@njit(cache=True)
def member_at_rank(vi, num_lanes, e, pos, lane, ahead, rank):
    """The ``rank``-th nearest member (1: the nearest) of ``lane`` ahead of (behind) sorted position ``pos`` of
    environment ``e``: a vehicle index, -1 when there are fewer or the lane does not exist."""
    if lane < 0 or lane >= num_lanes:
        return -1
    order = vi[ORDER, e]
    n, k = order.shape[0], 0
    step = 1 if ahead else -1
    q = pos + step
    while 0 <= q < n:
        if _is_member(vi, e, order[q], lane):
            k += 1
            if k == rank:
                return order[q]
        q += step
    return -1


@njit(cache=True, inline="always")
def nearest_in_lane(vi, num_lanes, e, pos, lane, ahead):
    """The nearest member of ``lane`` ahead of (behind) sorted position ``pos`` of environment ``e``: a vehicle
    index, -1 when none or the lane does not exist."""
    return member_at_rank(vi, num_lanes, e, pos, lane, ahead, 1)


@njit(cache=True)
def nearest_many(vi, num_lanes, envs, vehicles, lanes, ahead):
    """:func:`nearest_in_lane` elementwise over 1-D ``envs``, ``vehicles`` (start vehicles, -1: none) and ``lanes``."""
    out = np.empty(envs.shape[0], dtype=np.int64)
    for i in range(envs.shape[0]):
        v = vehicles[i]
        if v < 0:
            out[i] = -1
        else:
            out[i] = nearest_in_lane(vi, num_lanes, envs[i], vi[POS_OF, envs[i], v], lanes[i], ahead)
    return out


@njit(cache=True)
def lane_members(vi, num_lanes, e, vehicle, lane, ahead, count):
    """The ``count`` members of ``lane`` nearest ahead of (behind) ``vehicle``, nearest first (fewer when there are)."""
    out = np.empty(count, dtype=np.int64)
    pos, k = vi[POS_OF, e, vehicle], 0
    while k < count:
        u = nearest_in_lane(vi, num_lanes, e, pos, lane, ahead)
        if u < 0:
            break
        out[k] = u
        pos, k = vi[POS_OF, e, u], k + 1
    return out[:k]


# ------------------------------------------------------------------------------------------------------- collision
@njit(cache=True)
def obb_overlap_one(xa, ya, yawa, la, wa, xb, yb, yawb, lb, wb):
    """Exact overlap of two oriented rectangles (separating-axis theorem; touching edges count as overlap)."""
    dx, dy = xb - xa, yb - ya
    ca, sa, cb, sb = math.cos(yawa), math.sin(yawa), math.cos(yawb), math.sin(yawb)
    hla, hwa, hlb, hwb = 0.5 * la, 0.5 * wa, 0.5 * lb, 0.5 * wb
    for k in range(4):
        if k == 0:
            ux, uy = ca, sa
        elif k == 1:
            ux, uy = -sa, ca
        elif k == 2:
            ux, uy = cb, sb
        else:
            ux, uy = -sb, cb
        dist = abs(dx * ux + dy * uy)
        ra = hla * abs(ca * ux + sa * uy) + hwa * abs(-sa * ux + ca * uy)
        rb = hlb * abs(cb * ux + sb * uy) + hwb * abs(-sb * ux + cb * uy)
        if dist > ra + rb:
            return False
    return True


@njit(cache=True)
def _sensors_env(e, p, vf, vi, ei, eb, ego_y_prev):
    """Collisions (a vehicle and its leader closer than a metre along x, decided exactly), lane invasion, off-road."""
    n = vf.shape[2]
    x, y, yaw, length, width, gap = vf[X, e], vf[Y, e], vf[YAW, e], vf[LENGTH, e], vf[WIDTH, e], vf[GAP, e]
    lead = vi[LEAD, e]
    ei[COLLISION_WITH, e] = -1
    for v in range(n):
        if gap[v] < 1.0:
            u = lead[v]
            if obb_overlap_one(x[v], y[v], yaw[v], length[v], width[v], x[u], y[u], yaw[u], length[u], width[u]):
                if v == 0 or u == 0:
                    if ei[COLLISION_WITH, e] < 0:
                        ei[COLLISION_WITH, e] = u if v == 0 else v
                else:
                    ei[TRAFFIC_COLLISIONS, e] += 1
    lw = p[LW]
    k_prev, k_new = math.floor(ego_y_prev / lw), math.floor(y[0] / lw)
    ei[LANE_INVASION, e] = int(max(k_prev, k_new)) if k_prev != k_new else -1
    off_road = y[0] < 0.0 or y[0] > p[ROAD_W]
    if eb[OFF_ROAD, e] != off_road:  # (written only when it changes: threads share this row's cache lines)
        eb[OFF_ROAD, e] = off_road


# ------------------------------------------------------------------------------------------------- one sim step
@njit(cache=True)
def _next_knots(e, p, ip, vf, vb, ei, keys):
    """Human-like drivers at a check: the acceleration noise of the coming period and the next wander knot."""
    n = vf.shape[2]
    step, base = ei[STEP, e], keys[NOISE_BASE, e]
    c = ip[CHECK_EVERY]
    rho, scale, rho_w, scale_w, limit = p[NOISE_RHO], p[NOISE_SCALE], p[WANDER_RHO], p[WANDER_SCALE], p[WANDER_LIMIT]
    inv_c = 1.0 / c
    noise, w_base, w_next, w_step = vf[NOISE, e], vf[W_BASE, e], vf[W_NEXT, e], vf[W_STEP, e]
    traffic = vb[IS_TRAFFIC, e]
    for v in range(n):
        z = (uniform_one(base, step, v) - 0.5) * _SQRT12
        zw = (uniform_one(base, step, n + v) - 0.5) * _SQRT12
        tr = 1.0 if traffic[v] else 0.0
        noise[v] = (noise[v] * rho + scale * z) * tr
        b = w_next[v]
        nxt = min(max(b * rho_w + scale_w * zw, -limit), limit) * tr
        w_base[v] = b
        w_next[v] = nxt
        w_step[v] = (nxt - b) * inv_c


@njit(cache=True)
def _traffic_lane_changes(e, p, ip, vf, vi, vb, ef, ei, keys):
    """Traffic-Manager-like lane changes at a check: when blocked (or at random), into a free side lane."""
    n = vf.shape[2]
    num_lanes, c, human = ip[NUM_LANES], ip[CHECK_EVERY], ip[HUMAN]
    step, t, base = ei[STEP, e], ef[T_S, e], keys[LANE_CHANGE_BASE, e]
    x, y, speed, length, v0 = vf[X, e], vf[Y, e], vf[SPEED, e], vf[LENGTH, e], vf[V0, e]
    gap, lead_speed = vf[GAP, e], vf[LEAD_SPEED, e]
    lc_active, traffic = vb[LC_ACTIVE, e], vb[IS_TRAFFIC, e]
    side = 1 if (step // c) % 2 == 0 else -1  # one side per check period: two vehicles never merge into one gap
    lw, p_spont = p[LW], p[P_SPONT]
    for v in range(n):
        if not traffic[v] or lc_active[v]:
            continue
        g = gap[v]
        u = uniform_one(base, step, v)
        spontaneous = u < p_spont
        blocked = g < np.inf and g >= p[BLK_MIN] and g <= p[BLK_MAX] and lead_speed[v] < v0[v] - p[BLK_MARGIN]
        if human:
            blocked = blocked and u < vf[EAGERNESS, e, v]
        if not (blocked or spontaneous):
            continue
        tl = vi[LANE, e, v] + side
        if tl < 0 or tl >= num_lanes:
            continue
        pos = vi[POS_OF, e, v]
        f = nearest_in_lane(vi, num_lanes, e, pos, tl, True)
        r = nearest_in_lane(vi, num_lanes, e, pos, tl, False)
        front_gap = (x[f] - x[v]) - 0.5 * (length[v] + length[f]) if f >= 0 else np.inf
        rear_gap = (x[v] - x[r]) - 0.5 * (length[v] + length[r]) if r >= 0 else np.inf
        rear_need = p[LC_REAR] + p[LC_REAR_HW] * (speed[r] if r >= 0 else 0.0)
        if front_gap >= p[LC_FRONT] and rear_gap >= rear_need and (front_gap > g + 5.0 or spontaneous):
            lc_active[v] = True
            vf[LC_T0, e, v] = t
            y0 = y[v]
            if human:  # from the lane-keeping position
                y0 = y0 - (vf[W_BASE, e, v] + vf[W_STEP, e, v] * (step % c))
            vf[LC_Y0, e, v] = y0
            vf[LC_Y1, e, v] = (tl + 0.5) * lw
            vi[TARGET, e, v] = tl


@njit(cache=True)
def _substep_env(e, p, ip, vf, vi, vb, ef, ei, eb, keys, pid_err, pid_count, pid_slot, new, scratch_lanes):
    """One simulation step of environment ``e`` (``pid_slot``: the PID window's slot of the previous error)."""
    n = vf.shape[2]
    dt, num_lanes, c, human = p[DT], ip[NUM_LANES], ip[CHECK_EVERY], ip[HUMAN]
    step, t = ei[STEP, e], ef[T_S, e]
    check = step % c == 0
    if human and check:
        _next_knots(e, p, ip, vf, vb, ei, keys)
    x, y, speed, accel, v0 = vf[X, e], vf[Y, e], vf[SPEED, e], vf[ACCEL, e], vf[V0, e]
    gap, lead_speed = vf[GAP, e], vf[LEAD_SPEED, e]
    new_x, new_y, new_yaw, new_speed, new_acc = new[0], new[1], new[2], new[3], new[4]
    # Car following, then (human-like drivers) their noise and reaction lag.
    delta_int, delta = ip[IDM_DELTA_INT], p[IDM_DELTA]
    for v in range(n):
        if human:
            a = idm(speed[v], v0[v], gap[v], speed[v] - lead_speed[v], vf[MAX_ACCEL, e, v], vf[HEADWAY, e, v],
                    vf[INV_2SQRT_AB, e, v], True, p[IDM_S0], delta_int, delta, p[MAX_DECEL])
            a = (((a + vf[NOISE, e, v]) - accel[v]) * vf[LAG, e, v]) + accel[v]
        else:
            a = idm(speed[v], v0[v], gap[v], speed[v] - lead_speed[v], p[IDM_A], p[IDM_T], p[IDM_2SQRT_AB], False,
                    p[IDM_S0], delta_int, delta, p[MAX_DECEL])
        new_acc[v] = a
    if ip[LANE_CHANGES] and check:
        _traffic_lane_changes(e, p, ip, vf, vi, vb, ef, ei, keys)
    # Ballistic longitudinal update; lateral: the wander of lane keepers, the minimum-jerk profile of lane changers.
    lc_active = vb[LC_ACTIVE, e]
    phase_next = float(step % c + 1)
    for v in range(n):
        s = max(new_acc[v] * dt + speed[v], 0.0)
        new_speed[v] = s
        new_x[v] = (speed[v] + s) * (0.5 * dt) + x[v]
        ny = y[v] + vf[W_STEP, e, v] if human else y[v]
        yaw = 0.0
        if lc_active[v]:
            inv_dur = vf[LC_INV_DUR, e, v] if human else p[LC_DUR_INV]
            tau = (t + (dt - vf[LC_T0, e, v])) * inv_dur
            tt = min(max(tau, 0.0), 1.0)
            t2 = tt * tt
            u = 1.0 - tt
            prof = t2 * tt * (10.0 - 15.0 * tt + 6.0 * t2)
            dprof = 30.0 * t2 * (u * u)
            y0 = vf[LC_Y0, e, v]
            dy = vf[LC_Y1, e, v] - y0
            ny = y0 + dy * prof
            if human:
                ny = ny + (vf[W_BASE, e, v] + vf[W_STEP, e, v] * phase_next)
            yaw = math.atan2(dy * dprof * inv_dur, max(s, 1e-3))
            lc_active[v] = tau < 1.0
        new_y[v] = ny
        new_yaw[v] = yaw
    ego_y_prev = y[0]
    ego_target = vi[TARGET, e, 0]
    if not ip[AUTOPILOT_EGO]:  # the ego: PID control on its planned path, a bicycle-model step
        pid_count[e, 0] += 1
        r = ego_law(p, x[0], y[0], vf[YAW, e, 0], speed[0], gap[0], ef[PATH_X0, e], ef[PATH_LEN, e], ef[PATH_Y0, e],
                    ef[PATH_Y1, e], ef[STEER, e], ef[EGO_ACCEL, e], ip[ADAPTIVE_CRUISE] != 0, pid_err[e],
                    (pid_slot + 1) % pid_err.shape[1], pid_count[e, 0])
        ex, ey, eyaw, espeed, eaccel, esteer, ethrottle, ebrake = r
        ef[EGO_ACCEL, e], ef[STEER, e], ef[THROTTLE, e], ef[BRAKE, e] = eaccel, esteer, ethrottle, ebrake
        if eb[EGO_LC_ACTIVE, e] and ex >= ef[PATH_X0, e] + ef[PATH_LEN, e] and abs(ey - ef[PATH_Y1, e]) < p[LC_TOLERANCE]:
            eb[EGO_LC_ACTIVE, e] = False
        new_x[0], new_y[0], new_yaw[0], new_speed[0], new_acc[0] = ex, ey, eyaw, espeed, eaccel
    lane, target = vi[LANE, e], vi[TARGET, e]
    lw = p[LW]
    for v in range(n):
        x[v], y[v], vf[YAW, e, v], speed[v], accel[v] = new_x[v], new_y[v], new_yaw[v], new_speed[v], new_acc[v]
        k = min(max(math.floor(new_y[v] / lw), 0), num_lanes - 1)
        lane[v] = k
        if not lc_active[v]:
            target[v] = k
    if not ip[AUTOPILOT_EGO]:
        target[0] = ego_target if eb[EGO_LC_ACTIVE, e] else lane[0]
    ei[STEP, e] = step + 1
    ef[T_S, e] = t + dt
    _build_index_env(e, p, ip, vf, vi, vb, scratch_lanes)
    _sensors_env(e, p, vf, vi, ei, eb, ego_y_prev)


@njit(cache=True, nogil=True)
def advance(steps, stop_on_event, p, ip, vf, vi, vb, ef, ei, eb, keys, hist, hist_ptr, pid_err, pid_count, pid_ptr,
            e0, e1):
    """Advance environments ``e0 .. e1 - 1`` not frozen (``eb[FROZEN]``) by ``steps`` simulation steps.

    With ``stop_on_event``, an environment that meets an event (its ego in contact, off the road, or past the route's
    end) is frozen from there for the rest of the call. A frozen environment keeps its state; its history ring is
    written all the same (its position repeats). ``hist_ptr`` and ``pid_ptr`` are the shared ring positions before
    the call; each advances by ``steps``. Nothing outside those environments' own state is read or written, so
    threads may advance disjoint ranges of one batch at the same time (the Python lock is released).
    """
    _advance(steps, stop_on_event, p, ip, vf, vi, vb, ef, ei, eb, keys, hist, hist_ptr, pid_err, pid_count, pid_ptr,
             np.empty((0, 0, 0)), np.empty(0, dtype=np.int64), e0, e1)


@njit(cache=True, nogil=True)
def advance_logged(steps, stop_on_event, p, ip, vf, vi, vb, ef, ei, eb, keys, hist, hist_ptr, pid_err, pid_count,
                   pid_ptr, log, log_count, e0, e1):
    """:func:`advance`, and a row of the step log (:func:`log_state`) of every step each environment runs.

    ``log`` ``(E, S, log_width(N))`` with ``S >= steps``: environment e's steps go to ``log[e, :log_count[e]]``
    (an environment frozen before a step logs nothing for it).
    """
    _advance(steps, stop_on_event, p, ip, vf, vi, vb, ef, ei, eb, keys, hist, hist_ptr, pid_err, pid_count, pid_ptr,
             log, log_count, e0, e1)


@njit(cache=True)
def _advance(steps, stop_on_event, p, ip, vf, vi, vb, ef, ei, eb, keys, hist, hist_ptr, pid_err, pid_count, pid_ptr,
             log, log_count, e0, e1):
    n = vf.shape[2]
    h, w = hist.shape[1], pid_err.shape[1]
    new = np.empty((5, n))
    scratch = np.empty(max(ip[NUM_LANES], 1), dtype=np.int64)
    route = p[ROUTE]
    logging = log.shape[0] > 0
    for e in range(e0, e1):
        frozen = eb[FROZEN, e]
        logged = 0
        for s in range(steps):
            if not frozen:
                _substep_env(e, p, ip, vf, vi, vb, ef, ei, eb, keys, pid_err, pid_count, (pid_ptr + s) % w, new,
                             scratch)
                if logging:
                    log_state(e, ip, vf, vi, vb, ef, ei, eb, log[e, logged])
                    logged += 1
                if stop_on_event and (ei[COLLISION_WITH, e] >= 0 or eb[OFF_ROAD, e] or vf[X, e, 0] >= route):
                    frozen = True
                    eb[FROZEN, e] = True
            slot = (hist_ptr + s + 1) % h
            for v in range(n):
                hist[e, slot, v, 0] = vf[X, e, v]
                hist[e, slot, v, 1] = vf[Y, e, v]
            ei[HIST_COUNT, e] += 1
        if logging:
            log_count[e] = logged


# ------------------------------------------------------------------------------------------------------ step log
# What a recorder keeps of a simulation step of one environment (lcdata.record), as one float64 row: these
# scalars (integers and booleans exactly), then x, y, yaw, speed, accel, lane and target_lane of the N vehicles
# (LOG_VEHICLE_ROWS, N values each). ``lc_active`` is the ego's lane change in progress (its autopilot's when the
# autopilot drives it).
LOG_NAMES = ("step", "t_s", "speed", "lane", "collision_with", "lane_invasion", "off_road", "steer", "throttle",
             "brake", "lc_active")
LOG_VEHICLE_ROWS = ("x", "y", "yaw", "speed", "accel", "lane", "target_lane")
(LOG_STEP, LOG_T, LOG_SPEED, LOG_LANE, LOG_COLLISION, LOG_INVASION, LOG_OFF_ROAD, LOG_STEER, LOG_THROTTLE, LOG_BRAKE,
 LOG_LC_ACTIVE) = range(len(LOG_NAMES))
LOG_HEAD = len(LOG_NAMES)


def log_width(num_vehicles: int) -> int:
    """The length of a step log row for N vehicles."""
    return LOG_HEAD + len(LOG_VEHICLE_ROWS) * num_vehicles


@njit(cache=True)
def log_state(e, ip, vf, vi, vb, ef, ei, eb, out):
    """Write environment ``e``'s present state into the step log row ``out`` (:data:`LOG_NAMES`)."""
    n = vf.shape[2]
    out[0] = ei[STEP, e]
    out[1] = ef[T_S, e]
    out[2] = vf[SPEED, e, 0]
    out[3] = vi[LANE, e, 0]
    out[4] = ei[COLLISION_WITH, e]
    out[5] = ei[LANE_INVASION, e]
    out[6] = eb[OFF_ROAD, e]
    out[7] = ef[STEER, e]
    out[8] = ef[THROTTLE, e]
    out[9] = ef[BRAKE, e]
    out[10] = vb[LC_ACTIVE, e, 0] if ip[AUTOPILOT_EGO] else eb[EGO_LC_ACTIVE, e]
    at = LOG_HEAD
    for row in (X, Y, YAW, SPEED, ACCEL):
        for v in range(n):
            out[at + v] = vf[row, e, v]
        at += n
    for row in (LANE, TARGET):
        for v in range(n):
            out[at + v] = vi[row, e, v]
        at += n


# --------------------------------------------------------------------------------------------------- observation
@njit(cache=True)
def _slot_neighbours(vi, vf, e, num_lanes, slots, range2, out):
    """The vehicles of the lane slots of environment ``e`` (``slots`` rows: lane offset from the ego's target lane,
    ahead (1) or behind (0), rank), -1 where a slot is empty or beyond the sensing range."""
    ego_lane, pos = vi[TARGET, e, 0], vi[POS_OF, e, 0]
    x, y = vf[X, e], vf[Y, e]
    for j in range(slots.shape[0]):
        found = member_at_rank(vi, num_lanes, e, pos, ego_lane + slots[j, 0], slots[j, 1] != 0, slots[j, 2])
        if found >= 0:
            dx, dy = x[found] - x[0], y[found] - y[0]
            if dx * dx + dy * dy > range2:
                found = -1
        out[j] = found


@njit(cache=True)
def _nearest_neighbours(vf, e, range2, out):
    """The ``len(out)`` vehicles nearest to the ego of environment ``e`` (by distance, then index), -1 beyond the
    sensing range or where there are fewer."""
    x, y = vf[X, e], vf[Y, e]
    n, k = x.shape[0], out.shape[0]
    d2 = np.empty(n)
    for v in range(n):
        d2[v] = (x[v] - x[0]) ** 2 + (y[v] - y[0]) ** 2
    d2[0] = np.inf
    taken = np.zeros(n, dtype=np.bool_)
    for j in range(k):
        best = -1
        for v in range(1, n):
            if not taken[v] and (best < 0 or d2[v] < d2[best]):
                best = v
        if best >= 0:
            taken[best] = True
            out[j] = best if d2[best] <= range2 else -1
        else:
            out[j] = -1


@njit(cache=True, nogil=True)
def observe(ids, nearest_mode, slots, range2, with_accel, num_lanes, vf, vi, hist, hist_ptr, hist_count, neighbours,
            current, history):
    """The ``current`` and ``history`` observations of environments ``ids`` (see
    :meth:`lcsim.core.LaneChangeCore.observe`), written into ``current`` ``(B, 1+K, F)`` and ``history``
    ``(B, K, H, 3)`` (float32), and the vehicles of the K slots into ``neighbours`` ``(B, K)``."""
    h = hist.shape[1]
    for b in range(ids.shape[0]):
        e = ids[b]
        nb = neighbours[b]
        if nearest_mode:
            _nearest_neighbours(vf, e, range2, nb)
        else:
            _slot_neighbours(vi, vf, e, num_lanes, slots, range2, nb)
        ex, ey, eyaw, ev = vf[X, e, 0], vf[Y, e, 0], vf[YAW, e, 0], vf[SPEED, e, 0]
        c, s = math.cos(eyaw), math.sin(eyaw)
        cur = current[b]
        for j in range(nb.shape[0] + 1):
            v = 0 if j == 0 else nb[j - 1]
            row = cur[j]
            if v < 0:
                row[:] = 0.0
                continue
            px, py, yaw, speed = vf[X, e, v], vf[Y, e, v], vf[YAW, e, v], vf[SPEED, e, v]
            dx, dy = px - ex, py - ey
            if j == 0:  # the ego row holds its own velocity and heading
                rvx, rvy, rel_yaw = ev * c, ev * s, eyaw
            else:
                rvx, rvy, rel_yaw = speed * math.cos(yaw) - ev * c, speed * math.sin(yaw) - ev * s, yaw - eyaw
            row[0] = c * dx + s * dy
            row[1] = -s * dx + c * dy
            row[2] = c * rvx + s * rvy
            row[3] = -s * rvx + c * rvy
            row[4] = rel_yaw
            row[5] = speed
            row[6] = vi[LANE, e, v]
            row[7] = vi[TARGET, e, v]
            row[8] = 1.0
            if with_accel:
                row[9] = vf[ACCEL, e, v]
        # The last H positions of the same vehicles, oldest first, in the ego frame of now, with validity.
        first_valid = h - min(hist_count[e], h)
        hb = history[b]
        for j in range(nb.shape[0]):
            v = nb[j]
            for t in range(h):
                out = hb[j, t]
                if v < 0 or t < first_valid:
                    out[:] = 0.0
                    continue
                slot = (hist_ptr - h + 1 + t) % h
                hdx, hdy = hist[e, slot, v, 0] - ex, hist[e, slot, v, 1] - ey
                out[0] = c * hdx + s * hdy
                out[1] = -s * hdx + c * hdy
                out[2] = 1.0


# ------------------------------------------------------------------------------------------------------ decisions
OUT_RUNNING, OUT_SUCCESS, OUT_COLLISION, OUT_OFF_ROAD, OUT_TIMEOUT = range(5)  # outcome codes (lcsim.core names them)
KEEP_ACTION = 1


@njit(cache=True)
def start_lane_changes(change, direction, p, vf, vi, ef, eb):
    """Plan a BasicAgent-style lane change for the ego of every environment where ``change`` is set and none is
    under way: keep the lane for ``same_lane_time * speed``, move sideways over ``lane_change_time * speed`` metres
    (at least a waypoint spacing), then follow the target lane ``direction`` (+1 left, -1 right) of the current
    target lane. A target beyond the edge lanes leads off the road, as in CARLA."""
    lw = p[LW]
    for e in range(change.shape[0]):
        if not change[e] or eb[EGO_LC_ACTIVE, e]:
            continue
        v = vf[SPEED, e, 0]
        cur = vi[TARGET, e, 0]
        new = cur + direction[e]
        ef[PATH_X0, e] = vf[X, e, 0] + p[SAME_LANE_TIME] * v
        ef[PATH_LEN, e] = max(p[LANE_CHANGE_TIME] * v, p[WP_SPACING])
        ef[PATH_Y0, e] = (cur + 0.5) * lw
        ef[PATH_Y1, e] = (new + 0.5) * lw
        vi[TARGET, e, 0] = new
        eb[EGO_LC_ACTIVE, e] = True


@njit(cache=True)
def begin_decision(actions, refuse_invalid, code, p, ip, vf, vi, ef, eb, x_before, refused):
    """Apply one decision per environment (0 right, 1 keep, 2 left; ignored during a change under way), refusing
    a change towards a lane that does not exist when ``refuse_invalid`` (``refused`` is set), note the ego's ``x``
    and freeze the environments whose episode has ended (``code`` not running)."""
    num_envs = actions.shape[0]
    change = np.zeros(num_envs, dtype=np.bool_)
    direction = np.zeros(num_envs, dtype=np.int64)
    for e in range(num_envs):
        refused[e] = False
        if not ip[AUTOPILOT_EGO] and actions[e] != KEEP_ACTION:
            d = 1 if actions[e] == 2 else -1
            target = vi[TARGET, e, 0] + d
            if (refuse_invalid and not eb[EGO_LC_ACTIVE, e] and code[e] == OUT_RUNNING
                    and (target < 0 or target >= ip[NUM_LANES])):
                refused[e] = True
            else:
                change[e] = True
                direction[e] = d
        x_before[e] = vf[X, e, 0]
        eb[FROZEN, e] = code[e] != OUT_RUNNING
    start_lane_changes(change, direction, p, vf, vi, ef, eb)


@njit(cache=True)
def end_decision(code, refused, x_before, next_milestone, milestone_x, milestone_r, p, vf, ef, ei, eb, components,
                 reward, terminated, truncated):
    """Score a decision: the outcome of every environment that ended inside it (contact first, then the road edge,
    then the route's end), its reward components (collision, off-road, forward, success: rows of ``components``)
    and their sum, the milestones passed (in order, each once), and the timeout; unfreeze every environment."""
    for e in range(code.shape[0]):
        was_running = code[e] == OUT_RUNNING
        collided = was_running and ei[COLLISION_WITH, e] >= 0
        left_road = was_running and not collided and eb[OFF_ROAD, e]
        reached = vf[X, e, 0]
        if collided:
            code[e] = OUT_COLLISION
        elif left_road:
            code[e] = OUT_OFF_ROAD
        elif was_running and reached >= p[ROUTE]:
            code[e] = OUT_SUCCESS
        bonus = 0.0
        if not (collided or left_road):
            m = next_milestone[e]
            while m < milestone_r.shape[0] and reached >= milestone_x[m]:
                bonus += milestone_r[m]
                m += 1
            next_milestone[e] = m
        components[0, e] = p[R_COLLISION] if collided else 0.0
        components[1, e] = p[R_OFF_ROAD] if (left_road or refused[e]) else 0.0
        components[2, e] = p[R_FORWARD] * (reached - x_before[e])
        components[3, e] = bonus
        reward[e] = components[0, e] + components[1, e] + components[2, e] + components[3, e]
        terminated[e] = code[e] != OUT_RUNNING
        truncated[e] = not terminated[e] and ef[T_S, e] >= p[TIME_LIMIT] - 1e-9
        if truncated[e]:
            code[e] = OUT_TIMEOUT
        eb[FROZEN, e] = False


# ------------------------------------------------------------------------------------------- the rule-based driver
@njit(cache=True)
def lane_gaps(vf, vi, num_lanes, out):
    """Exact gaps around the ego of every environment in the lanes right of, at and left of its target lane, into
    ``out`` ``(4, E, 3)``: front gap, rear gap (m, bumper to bumper; inf when the lane is empty that way, -inf when
    it does not exist), front speed, rear speed (m/s; 0 when none)."""
    for e in range(vf.shape[1]):
        ego_x, ego_len, pos = vf[X, e, 0], vf[LENGTH, e, 0], vi[POS_OF, e, 0]
        for j in range(3):
            lane = vi[TARGET, e, 0] + j - 1
            valid = 0 <= lane < num_lanes
            for side in range(2):  # front, rear
                v = nearest_in_lane(vi, num_lanes, e, pos, lane, side == 0) if valid else -1
                if not valid:
                    gap = -np.inf
                elif v < 0:
                    gap = np.inf
                else:
                    dx = vf[X, e, v] - ego_x
                    gap = (dx if side == 0 else -dx) - 0.5 * (ego_len + vf[LENGTH, e, v])
                out[side, e, j] = gap
                out[2 + side, e, j] = vf[SPEED, e, v] if v >= 0 else 0.0


RULE_NAMES = ("horizon_s", "trigger_time_s", "trigger_gap_m", "min_front_gap_m", "min_front_time_s",
              "min_rear_gap_m", "rear_time_s", "gain_s", "urgent_time_s", "urgent_rear_gap_m")
"""The rule-based driver's parameters (:class:`lcsim.drivers.RuleDriverConfig`), in the order the kernel reads."""


@njit(cache=True)
def rule_actions(rp, mask, vf, vi, num_lanes, actions):
    """The rule-based driver's decisions (:class:`lcsim.drivers.RuleBasedDriver`) of every environment into
    ``actions``: when the leader gets close (in time or distance), the side lane (allowed by ``mask``) whose leader
    it would reach last, if safe and at least ``gain_s`` better than its own lane; the left one on a tie."""
    num_envs = vf.shape[1]
    g = np.empty((4, num_envs, 3))
    lane_gaps(vf, vi, num_lanes, g)
    horizon, trigger_t, trigger_g, min_front, min_front_t = rp[0], rp[1], rp[2], rp[3], rp[4]
    min_rear, rear_t, gain, urgent_t, urgent_rear = rp[5], rp[6], rp[7], rp[8], rp[9]
    reach = np.empty(3)
    for e in range(num_envs):
        v = vf[SPEED, e, 0]
        for j in range(3):
            reach[j] = min(g[0, e, j] / max(v - g[2, e, j], 0.05), horizon)
        own_front, own_reach = g[0, e, 1], reach[1]
        actions[e] = KEEP_ACTION
        if not (own_front < trigger_g or own_reach < trigger_t):
            continue
        best, best_score = -1, -np.inf
        for j in (0, 2):
            front, rear = g[0, e, j], g[1, e, j]
            rear_need = max(min_rear, rear_t * max(g[3, e, j] - v, 0.0))
            safe = front >= min_front and reach[j] >= min_front_t and rear >= rear_need
            if own_reach < urgent_t and front >= own_front + 2.0 and rear >= urgent_rear:
                safe = True
            if safe and reach[j] >= own_reach + gain and mask[e, j]:
                score = reach[j] + (0.01 if j == 2 else 0.0)
                if score > best_score:
                    best, best_score = j, score
        if best >= 0:
            actions[e] = best


@njit(cache=True)
def action_mask(vi, eb, num_lanes, autopilot_ego, mask):
    """``mask`` ``(E, 3)``: right / keep / left allowed. A change in progress allows only keep; no lane, no change."""
    for e in range(mask.shape[0]):
        idle = autopilot_ego or not eb[EGO_LC_ACTIVE, e]
        lane = vi[TARGET, e, 0]
        mask[e, 0] = idle and lane > 0
        mask[e, 1] = True
        mask[e, 2] = idle and lane < num_lanes - 1
