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


class BevRenderer:
    """Renders ``(E, 3, S, S)`` uint8 images around vehicle 0 of each environment."""

    def __init__(self, road: RoadConfig, render: RenderConfig, size_px: int | None = None,
                 resolution_m_per_px: float | None = None) -> None:
        self.road = road
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
        np.clip(li, 0, self.lut.size - 1, out=li)
        col_cls = self.lut[li]  # (E, S) lateral class of each column
        dash_on = (np.mod(ex + self.offsets[None, :], self.period) < self.road.dash_length_m).astype(np.intp)
        # Two RGB row templates per environment and channel (broken markings off / on); every image row
        # is one of them, copied whole by a row take.
        tmpl = self.rgb_table[col_cls]  # (E, S, 2, 3)
        tmpl = np.ascontiguousarray(tmpl.transpose(0, 3, 2, 1)).reshape(e * 6, s)  # rows (E, 3, 2)
        src = (np.arange(e)[:, None, None] * 6 + np.arange(0, 6, 2)[None, :, None]) + dash_on[:, None, :]
        out = tmpl.take(src.reshape(-1), axis=0).reshape(e, 3, s, s)
        flat = out.reshape(-1)
        for env, idx, cls in self._covered(x, y, yaw, length, width):  # traffic, then the ego on top
            if env.size:
                pix = (env * 3)[None, :] * (s * s) + idx[None, :] + (np.arange(3) * (s * s))[:, None]
                flat[pix] = PALETTE[cls][:, None]
        return out

    def _covered(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray,
                 width: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, int]]:
        """Pixels covered by traffic and by the ego: ``(env, flat pixel index, class)`` for each, in drawing order.

        The ego and its nearest ``max_vehicles_drawn`` vehicles are drawn. Only vehicles close enough
        to reach the image are rasterised: when no more than that many are within reach (always, at
        normal densities), they are exactly the drawn ones that show.
        """
        e, n = x.shape
        s, res = self.size, self.res
        k = min(n, self.max_vehicles + 1)
        ex, ey = x[:, :1], y[:, :1]
        d2 = (x - ex) ** 2 + (y - ey) ** 2
        reach = math.sqrt(2.0) * (self.half_extent + float(length.max()) + float(width.max())) + 1.0
        near = d2 <= reach * reach
        near[:, 0] = True
        if n > k and int(near.sum(axis=1).max()) > k:  # crowded: the nearest k, ties by index
            d2[:, 0] = -1.0
            sel = np.argsort(d2, axis=1, kind="stable")[:, :k]
            near[:] = False
            near[np.arange(e)[:, None], sel] = True
        vi = np.flatnonzero(near)
        env = vi // n
        ego = env * n
        x, y, yaw, length, width = x.take(vi), y.take(vi), yaw.take(vi), length.take(vi), width.take(vi)
        ex, ey = ex.take(env), ey.take(env)
        c, sn = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        frac = (np.arange(_STRIPS) + 0.5) / _STRIPS - 0.5
        lx = length[:, None] * frac  # (M, strips) strip centres along the body
        hl = (length / (2 * _STRIPS))[:, None]
        hw = (0.5 * width)[:, None]
        cu = x[:, None] + c * lx - ex[:, None]  # metres ahead of the ego
        cv = y[:, None] + sn * lx - ey[:, None]  # metres left of the ego
        hu = np.abs(c) * hl + np.abs(sn) * hw
        hv = np.abs(sn) * hl + np.abs(c) * hw
        # Pixel i has its centre at s/2 - i - 0.5 (in pixels): covered rows/cols are the centres inside.
        r0 = np.maximum(np.ceil(s / 2 - 0.5 - (cu + hu) / res), 0).astype(np.intp)
        r1 = np.minimum(np.floor(s / 2 - 0.5 - (cu - hu) / res), s - 1).astype(np.intp)
        c0 = np.maximum(np.ceil(s / 2 - 0.5 - (cv + hv) / res), 0).astype(np.intp)
        c1 = np.minimum(np.floor(s / 2 - 0.5 - (cv - hv) / res), s - 1).astype(np.intp)
        ok = (r0 <= r1) & (c0 <= c1)
        is_ego = (vi == ego)[:, None]
        out = []
        for part, cls in ((ok & ~is_ego, VEHICLE), (ok & is_ego, EGO)):  # traffic, then the ego on top
            m_env = np.broadcast_to(env[:, None], part.shape)[part]
            a0, a1, b0, b1 = r0[part], r1[part], c0[part], c1[part]
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
