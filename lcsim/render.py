"""Bird's-eye semantic image, ego-centred and road-aligned, rendered in numpy for a batch at once.

The image is centred on the ego with rows along the road (row 0 is ahead) and columns across it
(column 0 is the left), like an aerial camera that follows the ego on a gimbal aligned with the road.
On a straight road this makes the background separable: a column's lateral class (road, off-road,
solid or broken marking) times a row's dash phase, one broadcast look-up for the whole batch.
Vehicles, the ego included, are drawn as their true oriented rectangles, each cut into a few strips
along its length whose pixel-aligned boxes are filled through a 2-D difference array (two cumulative
sums), so any yaw is drawn without per-vehicle Python loops. Colours follow CARLA's semantic
(CityScapes) palette.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from lcsim.config import RenderConfig, RoadConfig

# Class ids and colours (CARLA semantic palette; CARLA has no ego class, so the ego gets its own).
OFF_ROAD, ROAD, MARKING, VEHICLE, EGO = 0, 1, 2, 3, 4
_DASH = 5  # internal: a broken marking's column, resolved by the row's dash phase
CLASS_NAMES = {OFF_ROAD: "off-road", ROAD: "road", MARKING: "lane marking", VEHICLE: "vehicle", EGO: "ego"}
PALETTE = np.array([
    [145, 170, 100],  # off-road: CARLA "Terrain"
    [128, 64, 128],   # road: CARLA "Road"
    [157, 234, 50],   # lane marking: CARLA "RoadLine"
    [0, 0, 142],      # vehicle: CARLA "Car"
    [255, 200, 0],    # ego: not a CARLA class; a colour no other class uses
], dtype=np.uint8)

_LUT_RES_M = 0.01
_STRIPS = 4
# Up to this many boxes in a batch, vehicles are filled box by box (slices) rather than by pixel index.
_LOOP_MAX_BOXES = 160
_COLOUR_COLUMNS = PALETTE[:, :, None, None]  # (class, 3, 1, 1): broadcasts over a box
_STRIP_FRAC = (np.arange(_STRIPS) + 0.5) / _STRIPS - 0.5  # strip centres, fractions of the length


@lru_cache(maxsize=16)
def _template_rows(e: int) -> np.ndarray:
    """``(E, 3, 1)``: the row of each environment's and channel's "broken markings off" template."""
    return np.arange(e)[:, None, None] * 6 + np.arange(0, 6, 2)[None, :, None]


class BevRenderer:
    """Renders ``(E, 3, S, S)`` uint8 images around vehicle 0 of each environment."""

    def __init__(self, road: RoadConfig, render: RenderConfig, size_px: int | None = None,
                 resolution_m_per_px: float | None = None, vehicle_extent_m: float | None = None) -> None:
        """``vehicle_extent_m``: an upper bound of any vehicle's length + width (m), when the caller knows
        one (it only bounds which vehicles are rasterised: any bound gives the same image); None: taken
        from the arrays at each call."""
        self.road = road
        self.vehicle_extent_m = vehicle_extent_m
        self.size = s = size_px or render.image_size_px
        self.res = resolution_m_per_px or render.resolution_m_per_px
        self.max_vehicles = render.max_vehicles_drawn
        self.offsets = (s / 2 - np.arange(s) - 0.5) * self.res  # row: metres ahead; column: metres left
        self.half_extent = 0.5 * s * self.res
        # Lateral look-up table; markings are at least one pixel wide so they never vanish.
        half_line = max(road.marking_width_m, self.res) / 2
        self.lut_lo = -self.half_extent - 1.0
        n = int((road.width_m + 2 * (self.half_extent + 1.0)) / _LUT_RES_M) + 1
        ys = self.lut_lo + np.arange(n) * _LUT_RES_M
        lut = np.where((ys >= 0) & (ys <= road.width_m), ROAD, OFF_ROAD).astype(np.uint8)
        for k in range(road.num_lanes + 1):
            lut[np.abs(ys - k * road.lane_width_m) <= half_line] = MARKING if k in (0, road.num_lanes) else _DASH
        self.lut = lut
        self.period = road.dash_length_m + road.dash_gap_m
        table = np.arange(6, dtype=np.uint8)[:, None].repeat(2, axis=1)  # (class, dash_on) -> class
        table[_DASH] = (ROAD, MARKING)
        self.table = table
        self.rgb_table = PALETTE[table[:5 + 1]]  # (lateral class, dash_on, channel)

    def render(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray,
               width: np.ndarray) -> np.ndarray:
        """Render one image per environment around vehicle 0 (the ego).

        Args:
            x, y, yaw, length, width: ``(E, N)`` vehicle poses and sizes; column 0 is the ego.

        Returns:
            ``(E, 3, S, S)`` uint8 in the palette :data:`PALETTE`; row 0 is ahead, column 0 left.
        """
        e, s = x.shape[0], self.size
        ex, ey = x[:, :1], y[:, :1]
        li = ((ey + self.offsets[None, :] - self.lut_lo) * (1.0 / _LUT_RES_M)).astype(np.intp)
        np.minimum(np.maximum(li, 0, out=li), self.lut.size - 1, out=li)  # np.clip, without its overhead
        col_cls = self.lut[li]  # (E, S) lateral class of each column
        dash_on = (np.mod(ex + self.offsets[None, :], self.period) < self.road.dash_length_m).astype(np.intp)
        # Two RGB row templates per environment and channel (broken markings off / on); every image row
        # is one of them, copied whole by a row take.
        tmpl = self.rgb_table[col_cls]  # (E, S, 2, 3)
        tmpl = np.ascontiguousarray(tmpl.transpose(0, 3, 2, 1)).reshape(e * 6, s)  # rows (E, 3, 2)
        src = _template_rows(e) + dash_on[:, None, :]
        out = tmpl.take(src.reshape(-1), axis=0).reshape(e, 3, s, s)
        env, is_ego, r0, r1, c0, c1, ok = self._boxes(x, y, yaw, length, width)
        if ok.size <= _LOOP_MAX_BOXES:
            # Few boxes (a single environment): one slice assignment per box beats building pixel indices.
            strips = range(ok.shape[1])
            boxes = zip([k for k in env.tolist() for _ in strips], [own for own in is_ego.tolist() for _ in strips],
                        r0.ravel().tolist(), r1.ravel().tolist(), c0.ravel().tolist(), c1.ravel().tolist(),
                        ok.ravel().tolist(), strict=True)
            ego_boxes = []
            vehicle, ego = _COLOUR_COLUMNS[VEHICLE], _COLOUR_COLUMNS[EGO]
            for k, own, a0, a1, b0, b1, show in boxes:
                if not show:
                    continue
                if own:
                    ego_boxes.append((k, a0, a1, b0, b1))
                else:
                    out[k, :, a0:a1 + 1, b0:b1 + 1] = vehicle
            for k, a0, a1, b0, b1 in ego_boxes:  # the ego on top
                out[k, :, a0:a1 + 1, b0:b1 + 1] = ego
            return out
        parts = []
        for part in (ok & ~is_ego[:, None], ok & is_ego[:, None]):  # traffic, then the ego on top
            parts.append((np.broadcast_to(env[:, None], part.shape)[part], r0[part], r1[part], c0[part], c1[part]))
        flat = out.reshape(-1)
        for m_env, idx, cls in self._covered(parts):
            if m_env.size:
                pix = (m_env * 3)[None, :] * (s * s) + idx[None, :] + (np.arange(3) * (s * s))[:, None]
                flat[pix] = PALETTE[cls][:, None]
        return out

    def _boxes(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray,
               width: np.ndarray) -> tuple[np.ndarray, ...]:
        """Pixel boxes of the vehicles that may show, each cut into ``_STRIPS`` strips along its length.

        Returns ``env`` (M,), ``is_ego`` (M,), then ``r0, r1, c0, c1`` (M, strips): inclusive row and
        column ranges, and ``ok`` (M, strips): the box holds at least one pixel. The ego and its nearest
        ``max_vehicles_drawn`` vehicles are drawn. Only vehicles close enough to reach the image are
        rasterised: when no more than that many are within reach (always, at normal densities), they are
        exactly the drawn ones that show.
        """
        e, n = x.shape
        s, res = self.size, self.res
        k = min(n, self.max_vehicles + 1)
        ex, ey = x[:, :1], y[:, :1]
        d2 = (x - ex) ** 2 + (y - ey) ** 2
        extent = self.vehicle_extent_m
        if extent is None:
            extent = float(length.max()) + float(width.max())
        reach = math.sqrt(2.0) * (self.half_extent + extent) + 1.0
        near = d2 <= reach * reach
        near[:, 0] = True
        if n > k and (np.count_nonzero(near) if e == 1 else int(near.sum(axis=1).max())) > k:
            # crowded: the nearest k, ties by index
            d2[:, 0] = -1.0
            sel = np.argsort(d2, axis=1, kind="stable")[:, :k]
            near[:] = False
            near[np.arange(e)[:, None], sel] = True
        vi = near.ravel().nonzero()[0]
        env = vi // n
        # Along (u, metres ahead of the ego) and across (v, metres left) stacked on a leading axis of 2:
        # the same elementwise operations as one array per axis, in half the calls.
        px, py, yaws, lengths, widths = x.take(vi), y.take(vi), yaw.take(vi), length.take(vi), width.take(vi)
        cs = np.array([np.cos(yaws), np.sin(yaws)])[:, :, None]  # (2, M, 1): cos, sin
        lx = lengths[:, None] * _STRIP_FRAC  # (M, strips) strip centres along the body
        centre = np.array([px, py])[:, :, None] + cs * lx
        centre -= np.array([ex.take(env), ey.take(env)])[:, :, None]  # (2, M, strips)
        hl = (lengths / (2 * _STRIPS))[:, None]
        hw = (0.5 * widths)[:, None]
        a = np.abs(cs)
        half = a * hl + a[::-1] * hw  # (2, M, 1): |c| hl + |s| hw along, |s| hl + |c| hw across
        # Pixel i has its centre at s/2 - i - 0.5 (in pixels): covered rows/cols are the centres inside.
        first = np.maximum(np.ceil(s / 2 - 0.5 - (centre + half) / res), 0).astype(np.intp)
        last = np.minimum(np.floor(s / 2 - 0.5 - (centre - half) / res), s - 1).astype(np.intp)
        fits = first <= last
        ok = fits[0] & fits[1]
        return env, vi == env * n, first[0], last[0], first[1], last[1], ok

    def _covered(self, parts: tuple[tuple[np.ndarray, ...], ...]) -> list[tuple[np.ndarray, np.ndarray, int]]:
        """Pixels covered by the boxes of :meth:`_boxes`: ``(env, flat pixel index, class)`` per part."""
        s = self.size
        out = []
        for (m_env, a0, a1, b0, b1), cls in zip(parts, (VEHICLE, EGO), strict=True):
            if m_env.size == 0:
                out.append((m_env, m_env, cls))
                continue
            nr, nc = int((a1 - a0).max()) + 1, int((b1 - b0).max()) + 1
            rr = a0[:, None, None] + np.arange(nr)[None, :, None]
            cc = b0[:, None, None] + np.arange(nc)[None, None, :]
            inside = (rr <= a1[:, None, None]) & (cc <= b1[:, None, None])
            idx = (rr * s + cc)[inside]
            out.append((np.broadcast_to(m_env[:, None, None], inside.shape)[inside], idx, cls))
        return out
