"""One function per data stream: a recorded :class:`~lcdata.reader.Episode` -> Rerun entities.

Every function takes the recording stream, the episode and the entity-path prefix of the episode
(``""`` when it has a recording of its own, ``episodes/<id>`` when episodes are shown side by side),
and logs whole columns with :func:`rerun.send_columns`: one call per entity for the whole episode.
Two time lines: ``step`` (simulation step, a sequence) and ``sim_time`` (simulation time, a duration).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pandas as pd
import rerun as rr

from lcdata.decider_records import CANDIDATES
from lcdata.reader import Episode
from lcdata.viewer.geometry import TrackGrid, box_corners, screen
from lcsim.core import ACTION_NAMES
from lcsim.render import CLASS_NAMES, PALETTE

log = logging.getLogger(__name__)

STEP, SIM_TIME = "step", "sim_time"
EGO_RGB = tuple(int(c) for c in PALETTE[4])  # the bird's-eye image's ego colour
TRAFFIC_RGB = (90, 150, 255)
PREDICTED_RGB = (255, 120, 40)
ACTUAL_RGB = (60, 220, 120)
UNKNOWN_CLASS = 255
# Plot colours: mid-saturation, at least 3:1 contrast against both the light and the dark theme's
# background, and far apart (CIELAB distance > 30) from every other series of their plot.
GOLD, PURPLE, BLUE, TEAL = (180, 130, 0), (148, 103, 189), (31, 119, 180), (0, 150, 150)
GREEN, RED, ORANGE, MAGENTA, BROWN = (44, 160, 44), (214, 39, 40), (230, 110, 20), (200, 60, 160), (140, 86, 75)
SERIES_RGB = {
    "ego": GOLD, "target": PURPLE, "traffic_mean": BLUE,  # plots/speed (the ego's colour, a darker yellow)
    "total": TEAL, "forward": GREEN, "collision": RED, "off_road": ORANGE, "success": BLUE,  # plots/reward
    "return": TEAL,  # plots/return
    "target_lane": PURPLE, "action": MAGENTA,  # plots/lane (with "ego")
    "right": MAGENTA, "keep": TEAL, "left": ORANGE, "overridden": RED,  # plots/planner, and the imagined paths
}  # fmt: skip
"""Colour of each time series by key (every series has one)."""
EPISODE_RGB = (GOLD, TEAL, RED, GREEN, MAGENTA, BROWN, ORANGE)
"""Side by side, the k-th episode's return and ego speed (drawn together in one plot) get colour k (cycled);
none is the target's or the traffic's colour, drawn next to the ego speed in an episode's own plot."""


def path(prefix: str, *parts: str) -> str:
    """Entity path under an episode prefix."""
    return "/".join(p for p in (prefix, *parts) if p)


def times(steps: np.ndarray, t: np.ndarray) -> list[rr.TimeColumn]:
    """The two time columns for rows at simulation ``steps`` (int) and times ``t`` (s)."""
    return [
        rr.TimeColumn(STEP, sequence=np.asarray(steps, dtype=np.int64)),
        rr.TimeColumn(SIM_TIME, duration=np.asarray(t, dtype=np.float64)),
    ]


def _series(rec: rr.RecordingStream, entity: str, steps: np.ndarray, t: np.ndarray, values: np.ndarray,
            name: str, key: str | None = None, rgb: tuple[int, int, int] | None = None) -> None:  # fmt: skip
    """A named scalar time series (one row per step) in colour ``rgb`` (default: ``SERIES_RGB[key]``)."""
    key = key or name
    episode_prefix = entity.split("/plots/")[0] if "/plots/" in entity else ""
    if episode_prefix:  # side by side: say which episode a line belongs to
        name = f"{episode_prefix.rsplit('/', 1)[-1]}: {name}"
    rec.log(entity, rr.SeriesLines(names=name, colors=[rgb or SERIES_RGB[key]], widths=2.0), static=True)
    if len(steps):
        rec.send_columns(entity, indexes=times(steps, t), columns=rr.Scalars.columns(scalars=values))


# -- world ------------------------------------------------------------------------------------------
ROAD_MARGIN_M = 100.0
"""The road is drawn this far before the first and past the last vehicle position."""
MAX_LANES = 64
MAX_ROAD_DASHES = 1_000_000
"""The most lane-marking dashes drawn (a 5 km road of 4 lanes has about 1,700)."""


def road_x_range(tracks: pd.DataFrame) -> tuple[float, float]:
    """The x range the road is drawn over: the vehicles' finite positions and :data:`ROAD_MARGIN_M` around them
    (around 0 without any)."""
    x = tracks["x"].to_numpy()
    x = x[np.isfinite(x)]
    if not len(x):
        return -ROAD_MARGIN_M, ROAD_MARGIN_M
    return float(x.min()) - ROAD_MARGIN_M, float(x.max()) + ROAD_MARGIN_M


def road_shape(config: Any, x_range: tuple[float, float]) -> tuple[int, float, float, float, float] | None:
    """The road of an episode's config as :func:`log_road` draws it: ``(num_lanes, lane_width_m,
    shoulder_width_m, dash_length_m, dash_gap_m)``, or None when the config describes no road.

    Raises:
        ValueError: a road that cannot be drawn (one line): not numbers, not 1 to :data:`MAX_LANES` lanes,
            lengths that are not finite and >= 0, or more than :data:`MAX_ROAD_DASHES` dashes over ``x_range``.
    """
    if not isinstance(config, dict) or "road" not in config:
        return None
    road = config["road"]
    try:
        num_lanes = int(road.get("num_lanes", 4))
        lengths = [float(road.get(key, default)) for key, default in
                   (("lane_width_m", 3.5), ("shoulder_width_m", 2.5), ("dash_length_m", 3.0), ("dash_gap_m", 6.0))]  # fmt: skip
    except (AttributeError, TypeError, ValueError, OverflowError):
        raise ValueError(f"the config's road is not a table of numbers: {str(road)[:80]}") from None
    w, shoulder, dash, gap = lengths
    if not 1 <= num_lanes <= MAX_LANES:
        raise ValueError(f"the config's road has {num_lanes} lanes; 1 to {MAX_LANES} can be drawn")
    if not all(np.isfinite(v) and v >= 0 for v in lengths) or dash + gap <= 0:
        raise ValueError(f"the config's road has lane width {w}, shoulder {shoulder}, dashes {dash} m with gaps of "
                         f"{gap} m: lengths must be finite and >= 0, dash and gap not both 0")  # fmt: skip
    x0, x1 = x_range
    dashes = (num_lanes - 1) * ((x1 - x0) / (dash + gap) + 1)
    if dashes > MAX_ROAD_DASHES:
        raise ValueError(f"the road to draw spans x from {x0:.4g} to {x1:.4g} m (the vehicles' positions): "
                         f"{dashes:.3g} lane-marking dashes, more than the {MAX_ROAD_DASHES:,} drawn")  # fmt: skip
    return num_lanes, w, shoulder, dash, gap


def log_road(rec: rr.RecordingStream, episode: Episode, prefix: str, x_range: tuple[float, float]) -> None:
    """Static road: solid edges, broken lane markings (dash by dash), shoulders, faint lane centres. None for an
    episode whose config describes no road (traffic imported from a SUMO network, which has any shape).

    Raises:
        ValueError: a road that cannot be drawn (:func:`road_shape`).
    """
    shape = road_shape(episode.metadata["config"], x_range)
    if shape is None:
        return
    num_lanes, w, shoulder, dash, gap = shape
    x0, x1 = x_range
    edges = [screen(np.array([x0, x1]), np.full(2, y)) for y in (0.0, num_lanes * w)]
    rec.log(path(prefix, "world/road/edges"), rr.LineStrips2D(edges, colors=[(235, 235, 235)], radii=0.1,
                                                             draw_order=2.0), static=True)  # fmt: skip
    shoulders = [screen(np.array([x0, x1]), np.full(2, y)) for y in (-shoulder, num_lanes * w + shoulder)]
    rec.log(path(prefix, "world/road/shoulders"), rr.LineStrips2D(shoulders, colors=[(110, 110, 110)],
                                                                  radii=0.05, draw_order=1.0), static=True)  # fmt: skip
    starts = np.arange(np.floor(x0 / (dash + gap)) * (dash + gap), x1, dash + gap)
    inner = np.arange(1, num_lanes) * w
    if len(inner) and len(starts):
        xs = np.stack([starts, starts + dash], axis=-1)  # (D, 2) dash ends
        sx = np.broadcast_to(xs[None], (len(inner), *xs.shape)).reshape(-1, 2)
        sy = np.repeat(inner, len(starts))[:, None].repeat(2, axis=1)
        rec.log(path(prefix, "world/road/markings"), rr.LineStrips2D(screen(sx, sy), colors=[(220, 220, 220)],
                                                                     radii=0.075, draw_order=2.0), static=True)  # fmt: skip
    centres = [screen(np.array([x0, x1]), np.full(2, (k + 0.5) * w)) for k in range(num_lanes)]
    rec.log(path(prefix, "world/road/lane_centres"), rr.LineStrips2D(centres, colors=[(90, 90, 90)], radii=0.03,
                                                                     draw_order=1.0), static=True)  # fmt: skip


def log_vehicles(rec: rr.RecordingStream, episode: Episode, prefix: str, grid: TrackGrid,
                 tracks: pd.DataFrame) -> None:  # fmt: skip
    """Traffic as oriented boxes (line strips of the 4 corners) and every vehicle's short trail.

    ``world/vehicles/boxes``: one strip per traffic vehicle per step; ``world/vehicles/trails``: the
    last 2 s of every vehicle, the ego's included.
    """
    if not len(tracks):
        return
    traffic = ~tracks["is_ego"].to_numpy()
    corners = box_corners(*(tracks[c].to_numpy()[traffic] for c in ("x", "y", "yaw", "length", "width")))
    per_step = np.bincount(grid.row[traffic], minlength=len(grid.steps))
    rec.log(path(prefix, "world/vehicles/boxes"), rr.LineStrips2D.from_fields(colors=[TRAFFIC_RGB], radii=0.12,
                                                                             draw_order=4.0), static=True)  # fmt: skip
    rec.send_columns(path(prefix, "world/vehicles/boxes"), indexes=times(grid.steps, grid.t),
                     columns=rr.LineStrips2D.columns(strips=corners).partition(per_step))  # fmt: skip
    trails = grid.trails(np.ones(len(tracks), dtype=bool))
    rec.log(path(prefix, "world/vehicles/trails"), rr.LineStrips2D.from_fields(colors=[(150, 150, 170, 150)],
                                                                              radii=0.08, draw_order=3.0), static=True)  # fmt: skip
    rec.send_columns(path(prefix, "world/vehicles/trails"), indexes=times(grid.steps, grid.t),
                     columns=rr.LineStrips2D.columns(strips=trails).partition(grid.counts))  # fmt: skip


def log_ego(
    rec: rr.RecordingStream, episode: Episode, prefix: str, grid: TrackGrid, tracks: pd.DataFrame
) -> None:
    """The ego frame ``world/ego`` (a translation per step, followed by the scene view) and its box.

    The box ``world/ego/box`` is drawn in that frame (rotated, not translated), filled-looking with a
    thick outline in the ego colour of the bird's-eye image.
    """
    ego = tracks[tracks["is_ego"].to_numpy()]
    if not len(ego):
        return
    steps, t = ego["step"].to_numpy(), ego["t"].to_numpy()
    xy = screen(ego["x"].to_numpy(), ego["y"].to_numpy())
    translation = np.concatenate([xy, np.zeros((len(ego), 1), dtype=np.float32)], axis=1)
    rec.send_columns(path(prefix, "world/ego"), indexes=times(steps, t),
                     columns=rr.Transform3D.columns(translation=translation))  # fmt: skip
    zeros = np.zeros(len(ego))
    corners = box_corners(
        zeros, zeros, ego["yaw"].to_numpy(), ego["length"].to_numpy(), ego["width"].to_numpy()
    )
    rec.log(path(prefix, "world/ego/box"), rr.LineStrips2D.from_fields(colors=[EGO_RGB], radii=0.25, labels=["ego"],
                                                                       draw_order=6.0), static=True)  # fmt: skip
    rec.send_columns(path(prefix, "world/ego/box"), indexes=times(steps, t),
                     columns=rr.LineStrips2D.columns(strips=corners).partition(np.ones(len(ego), dtype=np.int64)))  # fmt: skip


def log_predictions(rec: rr.RecordingStream, episode: Episode, prefix: str, grid: TrackGrid) -> None:
    """Predicted trajectories of the nearest vehicles next to what they really did (``/prediction`` only).

    At every decision with a prediction: ``world/prediction/predicted`` (from the current position
    through the F predicted points) and ``world/prediction/actual`` (the recorded positions over the
    same F steps; the prediction's k-th point is k simulation steps ahead).
    """
    pred = episode.predictions
    if not len(pred) or not len(grid.steps):
        return
    pred = pred[pred["vehicle_id"].to_numpy() >= 0].sort_values(["step", "slot", "k"], kind="stable")
    horizon = int(pred["k"].max())
    whole = pred.groupby(["step", "slot"], sort=False)["k"].transform("size").to_numpy() == horizon
    if not whole.all():
        log.warning("%s: skipping predictions with missing horizon points", episode.path)
        pred = pred[whole]
    heads = pred.iloc[::horizon]
    xy = pred[["x", "y"]].to_numpy().reshape(-1, horizon, 2)
    hs, hv = heads["step"].to_numpy(), heads["vehicle_id"].to_numpy()
    step_index = np.clip(np.searchsorted(grid.steps, hs), 0, len(grid.steps) - 1)
    col = np.clip(np.searchsorted(grid.ids, hv), 0, len(grid.ids) - 1)
    known = (grid.steps[step_index] == hs) & (grid.ids[col] == hv)
    step_index, col, xy = step_index[known], col[known], xy[known]
    if not len(xy):
        return
    actual, valid = grid.future(step_index, col, horizon)
    start = actual[:, :1]
    predicted = screen(*np.concatenate([start, xy], axis=1).transpose(2, 0, 1))
    actual = np.where(valid[..., None], actual, start)  # past the end of the recording: stay put
    actual_pts = screen(actual[..., 0], actual[..., 1])
    pred_steps, per_step = np.unique(step_index, return_counts=True)
    idx = times(grid.steps[pred_steps], grid.t[pred_steps])
    for name, pts, rgb in (("predicted", predicted, PREDICTED_RGB), ("actual", actual_pts, ACTUAL_RGB)):
        entity = path(prefix, "world/prediction", name)
        rec.log(entity, rr.LineStrips2D.from_fields(colors=[rgb], radii=0.15, draw_order=5.0), static=True)
        rec.send_columns(entity, indexes=idx, columns=rr.LineStrips2D.columns(strips=pts).partition(per_step))


IMAGINED_RADIUS_M, EXECUTED_RADIUS_M = 0.1, 0.3
"""The width of an imagined path drawn, and of the paths of the candidate executed."""


def log_planner(rec: rr.RecordingStream, episode: Episode, prefix: str) -> None:
    """What a planning driver thought at each decision where it had a choice (``/planner/decision`` only).

    ``plots/planner/right|keep|left``: each candidate's score (the share of its imagined futures it survived; none
    where it was not scored); ``plots/planner/overridden``: a point at the executed candidate's score where the
    planner overrode the proposal; ``log/planner``: a line per decision (overrides at INFO, the rest at DEBUG);
    ``world/planner/imagined``: the ego's paths in the imagined futures kept, in the colour of their candidate, the
    executed candidate's wider; ``world/planner/crashes``: where the imagined futures not survived ended. Both are
    emptied at the decisions without paths, so that a path shows only at its own decision.
    """
    decisions = episode.decisions
    if not len(decisions):
        return
    s, t = decisions["step"].to_numpy(), decisions["t"].to_numpy()
    scores = decisions[[f"score_{name}" for name in CANDIDATES]].to_numpy()
    for k, name in enumerate(CANDIDATES):
        scored = np.isfinite(scores[:, k])
        _series(rec, path(prefix, "plots/planner", name), s[scored], t[scored], scores[scored, k], name)
    executed, proposed = decisions["executed"].to_numpy(), decisions["proposed"].to_numpy()
    over = decisions["overridden"].to_numpy()
    entity = path(prefix, "plots/planner/overridden")
    rec.log(entity, rr.SeriesPoints(names="overridden", colors=[SERIES_RGB["overridden"]], marker_sizes=4.0),
            static=True)  # fmt: skip
    if over.any():
        rec.send_columns(entity, indexes=times(s[over], t[over]),
                         columns=rr.Scalars.columns(scalars=scores[np.flatnonzero(over), executed[over]]))  # fmt: skip
    names = np.asarray(CANDIDATES, dtype=object)
    text = [f"decision {d}: {names[p]} proposed, {names[e]} executed{' (overridden)' if o else ''}; survived: "
            + ", ".join(f"{n} {v:.2f}" for n, v in zip(CANDIDATES, row, strict=True) if np.isfinite(v))
            for d, p, e, o, row in zip(decisions["decision"], proposed, executed, over, scores, strict=True)]  # fmt: skip
    rec.send_columns(path(prefix, "log/planner"), indexes=times(s, t),
                     columns=rr.TextLog.columns(text=text, level=np.where(over, "INFO", "DEBUG").tolist()))  # fmt: skip
    _log_imagined_paths(rec, episode, prefix, dict(zip(s.tolist(), executed.tolist(), strict=True)))


def _log_imagined_paths(rec: rr.RecordingStream, episode: Episode, prefix: str, executed: dict[int, int]) -> None:
    """``world/planner/imagined`` and ``world/planner/crashes`` (see :func:`log_planner`); ``executed``: the
    decision executed at each step with a report."""
    points = episode.imagined_paths
    if not len(points):
        return
    points = points.sort_values("step", kind="stable")  # a path's points stay in their order
    steps = episode.steps
    at = pd.concat([steps[["step", "t"]], points[["step", "t"]]]).drop_duplicates("step").sort_values("step")
    s = points["step"].to_numpy()
    starts = np.flatnonzero(points["k"].to_numpy() == 0)  # every path starts at its decision (k = 0)
    xy = screen(points["x"].to_numpy(), points["y"].to_numpy())
    strips = np.split(xy, starts[1:])
    strip_step, action = s[starts], points["action"].to_numpy()[starts]
    chosen = action == np.array([executed.get(k, -1) for k in strip_step.tolist()], dtype=np.int64)
    rgb = np.array([SERIES_RGB[name] for name in CANDIDATES], dtype=np.uint8)[action]
    ends = np.r_[starts[1:], len(s)] - 1
    crashed = ~points["survived"].to_numpy()[starts]
    steps_at = at["step"].to_numpy()
    per_step = np.searchsorted(strip_step, steps_at, side="right") - np.searchsorted(strip_step, steps_at)
    crash_step = strip_step[crashed]
    per_crash = np.searchsorted(crash_step, steps_at, side="right") - np.searchsorted(crash_step, steps_at)
    idx = times(steps_at, at["t"].to_numpy())
    entity = path(prefix, "world/planner/imagined")
    rec.log(entity, rr.LineStrips2D.from_fields(draw_order=4.5), static=True)
    rec.send_columns(entity, indexes=idx, columns=rr.LineStrips2D.columns(
        strips=strips, colors=rgb, radii=np.where(chosen, EXECUTED_RADIUS_M, IMAGINED_RADIUS_M)).partition(per_step))  # fmt: skip
    entity = path(prefix, "world/planner/crashes")
    rec.log(entity, rr.Points2D.from_fields(colors=[RED], radii=0.6, draw_order=4.6), static=True)
    rec.send_columns(entity, indexes=idx, columns=rr.Points2D.columns(positions=xy[ends[crashed]]).partition(per_crash))


# -- camera -----------------------------------------------------------------------------------------
def class_ids(chw: np.ndarray) -> np.ndarray:
    """``(..., 3, H, W)`` palette image -> ``(..., H, W)`` uint8 class ids (255 for other colours)."""
    code = (
        (chw[..., 0, :, :].astype(np.int32) << 16)
        | (chw[..., 1, :, :].astype(np.int32) << 8)
        | chw[..., 2, :, :]
    )
    palette = (PALETTE[:, 0].astype(np.int32) << 16) | (PALETTE[:, 1].astype(np.int32) << 8) | PALETTE[:, 2]
    order = np.argsort(palette)
    pos = np.clip(np.searchsorted(palette[order], code), 0, len(palette) - 1)
    ids = order[pos].astype(np.uint8)
    ids[palette[order][pos] != code] = UNKNOWN_CLASS
    return ids


def log_camera(rec: rr.RecordingStream, episode: Episode, prefix: str) -> None:
    """The bird's-eye semantic image as a ``SegmentationImage`` whose classes are named and coloured.

    ``camera`` holds the ``AnnotationContext`` (CARLA palette, :data:`lcsim.render.CLASS_NAMES`);
    ``camera/bev`` one image per decision, logged as one column of buffers.
    """
    steps = episode.image_steps
    if not len(steps):
        return
    context = [rr.AnnotationInfo(id=k, label=name, color=tuple(int(c) for c in PALETTE[k]))
               for k, name in CLASS_NAMES.items()] + [rr.AnnotationInfo(id=UNKNOWN_CLASS, label="unknown",
                                                                         color=(255, 0, 255))]  # fmt: skip
    rec.log(path(prefix, "camera"), rr.AnnotationContext(context), static=True)
    images = np.stack([episode.image(int(s)) for s in steps])  # (M, 3, H, W)
    ids = class_ids(images)
    m, h, w = ids.shape
    fmt = rr.components.ImageFormat(width=w, height=h, channel_datatype=rr.ChannelDatatype.U8)
    entity = path(prefix, "camera/bev")
    rec.log(entity, rr.SegmentationImage.from_fields(format=fmt, opacity=1.0), static=True)
    t = _step_times(episode, steps)
    rec.send_columns(
        entity, indexes=times(steps, t), columns=rr.SegmentationImage.columns(buffer=ids.reshape(m, -1))
    )


def _step_times(episode: Episode, steps: np.ndarray) -> np.ndarray:
    """Simulation time of ``steps`` from the ego table (or the config's dt when a step is missing)."""
    ego = episode.ego
    dt = float(episode.metadata["config"].get("dt_s", 0.05))
    if len(ego):
        s, t = ego["step"].to_numpy(), ego["t"].to_numpy()
        i = np.clip(np.searchsorted(s, steps), 0, len(s) - 1)
        return np.where(s[i] == steps, t[i], steps * dt)
    return steps * dt


# -- plots ------------------------------------------------------------------------------------------
def log_speed(rec: rr.RecordingStream, episode: Episode, prefix: str, grid: TrackGrid, tracks: pd.DataFrame,
              ego_rgb: tuple[int, int, int] | None = None) -> None:  # fmt: skip
    """``plots/speed``: ego speed (in ``ego_rgb``, default the ego's), its target speed and the mean
    traffic speed (km/h)."""
    ego = episode.ego
    if len(ego):
        _series(rec, path(prefix, "plots/speed/ego"), ego["step"].to_numpy(), ego["t"].to_numpy(),
                ego["speed"].to_numpy() * 3.6, "ego", "ego", ego_rgb)  # fmt: skip
        target = episode.metadata["config"].get("ego", {}).get("target_speed_kmh")
        if target is not None:
            ends = np.array([0, len(ego) - 1])
            _series(rec, path(prefix, "plots/speed/target"), ego["step"].to_numpy()[ends], ego["t"].to_numpy()[ends],
                    np.full(2, float(target)), "ego target", "target")  # fmt: skip
    traffic = ~tracks["is_ego"].to_numpy()
    if traffic.any():
        n = np.bincount(grid.row[traffic], minlength=len(grid.steps))
        total = np.bincount(
            grid.row[traffic], weights=tracks["speed"].to_numpy()[traffic], minlength=len(grid.steps)
        )
        has = n > 0
        _series(rec, path(prefix, "plots/speed/traffic_mean"), grid.steps[has], grid.t[has],
                total[has] / n[has] * 3.6, "traffic mean", "traffic_mean")  # fmt: skip


def log_rewards(rec: rr.RecordingStream, episode: Episode, prefix: str,
                return_rgb: tuple[int, int, int] | None = None) -> None:  # fmt: skip
    """``plots/reward/*``: reward and its components per decision; ``plots/return``: cumulative return
    (in ``return_rgb``, default ``SERIES_RGB["return"]``)."""
    steps = episode.steps
    if not len(steps):
        return
    s, t = steps["step"].to_numpy(), steps["t"].to_numpy()
    _series(rec, path(prefix, "plots/reward/total"), s, t, steps["reward"].to_numpy(), "reward", "total")
    for name in ("forward", "collision", "off_road", "success"):
        _series(rec, path(prefix, "plots/reward", name), s, t, steps[f"r_{name}"].to_numpy(), name)
    _series(rec, path(prefix, "plots/return"), s, t, np.cumsum(steps["reward"].to_numpy()), "return",
            rgb=return_rgb)


def log_lanes(rec: rr.RecordingStream, episode: Episode, prefix: str, tracks: pd.DataFrame) -> None:
    """``plots/lane``: the ego's lane and target lane per step, and each decision's action (0 right, 2 left)."""
    ego = tracks[tracks["is_ego"].to_numpy()]
    if len(ego):
        s, t = ego["step"].to_numpy(), ego["t"].to_numpy()
        _series(
            rec,
            path(prefix, "plots/lane/ego"),
            s,
            t,
            ego["lane"].to_numpy().astype(np.float64),
            "lane",
            "ego",
        )
        _series(rec, path(prefix, "plots/lane/target"), s, t, ego["target_lane"].to_numpy().astype(np.float64),
                "target lane", "target_lane")  # fmt: skip
    steps = episode.steps
    if len(steps):
        rec.log(path(prefix, "plots/lane/action"), rr.SeriesPoints(names="action", colors=[SERIES_RGB["action"]],
                                                                   marker_sizes=2.0), static=True)  # fmt: skip
        rec.send_columns(path(prefix, "plots/lane/action"), indexes=times(steps["step"], steps["t"]),
                         columns=rr.Scalars.columns(scalars=steps["action"].to_numpy().astype(np.float64)))  # fmt: skip


# -- text -------------------------------------------------------------------------------------------
_LEVELS = {"debug": "DEBUG", "info": "INFO", "warning": "WARN", "error": "ERROR", "fatal": "CRITICAL"}


def log_events(rec: rr.RecordingStream, episode: Episode, prefix: str) -> None:
    """``log/events``: recorded ``/log`` events (lane-change start and end, collision, off-road, outcome).

    ``log/decisions``: every decision (lane changes at INFO, keep-lane at DEBUG) with its reward.
    """
    events = episode.events
    if len(events):
        text = [f"[{k}] {x}" if x else f"[{k}]" for k, x in zip(events["kind"], events["text"], strict=True)]
        levels = [_LEVELS.get(str(v), "INFO") for v in events["level"]]
        rec.send_columns(path(prefix, "log/events"), indexes=times(events["step"], events["t"]),
                         columns=rr.TextLog.columns(text=text, level=levels))  # fmt: skip
    steps = episode.steps
    if len(steps):
        names = np.asarray(ACTION_NAMES, dtype=object)[np.clip(steps["action"].to_numpy(), 0, 2)]
        text = [f"decision {d}: {a} (reward {r:+.1f}){' -> ' + o if o else ''}"
                for d, a, r, o in zip(steps["decision"], names, steps["reward"], steps["outcome"], strict=True)]  # fmt: skip
        levels = np.where(steps["action"].to_numpy() == ACTION_NAMES.index("keep"), "DEBUG", "INFO").tolist()
        rec.send_columns(path(prefix, "log/decisions"), indexes=times(steps["step"], steps["t"]),
                         columns=rr.TextLog.columns(text=text, level=levels))  # fmt: skip


# -- what the layout shows --------------------------------------------------------------------------
VIEWS = ("world", "camera", "speed", "reward", "return", "lane", "planner", "log")
"""The views of an episode's layout (:func:`lcdata.viewer.layout.episode_views`), named after their entities."""


def views_with_data(episode: Episode) -> frozenset[str]:
    """The :data:`VIEWS` the functions above fill for ``episode`` (the same conditions), so that the layout
    leaves out the others: a corpus recording has no bird's-eye image, a file without decisions no rewards."""
    tracks, steps = episode.tracks, episode.steps
    ego = tracks["is_ego"].to_numpy()
    filled = {
        "world": True,  # the road, at least
        "camera": len(episode.image_steps) > 0,
        "speed": len(episode.ego) > 0 or not ego.all(),
        "reward": len(steps) > 0,
        "return": len(steps) > 0,
        "lane": ego.any() or len(steps) > 0,
        "planner": len(episode.decisions) > 0,
        "log": len(episode.events) > 0 or len(steps) > 0 or len(episode.decisions) > 0,
    }
    return frozenset(view for view, has in filled.items() if has)


def describe(episode: Episode) -> dict[str, Any]:
    """Short summary of an episode for the recording's properties and the command line."""
    steps = episode.steps
    outcome = str(steps["outcome"].iloc[-1]) if len(steps) else ""
    return {
        "episode_id": episode.episode_id,
        "driver": str(episode.metadata.get("driver", "")),
        "seed": int(episode.metadata.get("seed", -1)),
        "outcome": outcome or ("incomplete" if not episode.complete else "running"),
        "return": float(steps["reward"].sum()) if len(steps) else 0.0,
    }
