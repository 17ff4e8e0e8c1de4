"""Bird's-eye semantic image, ego-centred and road-aligned, rendered by one compiled loop over a batch.

The image is centred on the ego with rows along the road (row 0 is ahead) and columns across it
(column 0 is the left), like an aerial camera that follows the ego on a gimbal aligned with the road.
On a straight road this makes the background separable: a column's lateral class (road, off-road,
solid or broken marking) and a row's dash phase decide a pixel, so every row of an image is one of two
RGB row templates (broken markings off, on) and each run of rows with one phase is a single copy.
Vehicles, the ego included, are drawn as their true oriented rectangles, each cut into a few strips
along its length whose pixel-aligned boxes are filled, traffic first and the ego on top. The work is
compiled with numba (:func:`_render_batch`, cached on disk after the first compilation). Colours follow
CARLA's semantic (CityScapes) palette.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from lcsim.config import RenderConfig, RoadConfig
from lcsim.threads import run_shards

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
_STRIP_FRAC = (np.arange(_STRIPS) + 0.5) / _STRIPS - 0.5  # strip centres, fractions of the length


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
        table = np.arange(_DASH + 1, dtype=np.uint8)[:, None].repeat(2, axis=1)  # (class, dash_on) -> class
        table[_DASH] = (ROAD, MARKING)
        self.rgb_table = np.ascontiguousarray(PALETTE[table])  # (lateral class, dash_on, channel)

    def render(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray,
               width: np.ndarray, *, shards: int = 1) -> np.ndarray:
        """Render one image per environment around vehicle 0 (the ego).

        The ego and its nearest ``max_vehicles_drawn`` vehicles are drawn (ties by index).

        Args:
            x, y, yaw, length, width: ``(E, N)`` vehicle poses and sizes (float64); column 0 is the ego.
            shards: threads that draw contiguous shards of the images at the same time
                (:func:`lcsim.threads.run_shards`; the same bytes however many).

        Returns:
            ``(E, 3, S, S)`` uint8 in the palette :data:`PALETTE`; row 0 is ahead, column 0 left.
        """
        x, y, yaw, length, width = (np.ascontiguousarray(a, dtype=np.float64) for a in (x, y, yaw, length, width))
        out = self.empty(x.shape[0])
        extent = self.extent(length, width)
        run_shards(lambda a, b: self.draw(out[a:b], x[a:b], y[a:b], yaw[a:b], length[a:b], width[a:b], extent),
                   x.shape[0], shards)
        return out

    def empty(self, num: int) -> np.ndarray:
        """``(num, 3, S, S)`` uint8, uninitialised: for :meth:`draw`."""
        return np.empty((num, 3, self.size, self.size), dtype=np.uint8)

    def extent(self, length: np.ndarray, width: np.ndarray) -> float:
        """The bound of a vehicle's length + width that :meth:`draw` takes: ``vehicle_extent_m``, or the longest
        length plus the widest width of ``(E, N)`` float64 arrays."""
        return _vehicle_extent(length, width) if self.vehicle_extent_m is None else float(self.vehicle_extent_m)

    def draw(self, out: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray,
             width: np.ndarray, extent: float) -> None:
        """:meth:`render` into ``out`` ``(E, 3, S, S)`` uint8 (C-contiguous), from C-contiguous ``(E, N)`` float64
        arrays and :meth:`extent` (of the whole batch: the bound only limits which vehicles are tried, so any
        bound gives the same image). Each image depends on its own environment only: threads may draw disjoint
        rows of one batch at the same time."""
        e, s = out.shape[0], self.size
        _render_batch(out.reshape((e, 3, s * s)), x, y, yaw, length, width, extent, s, self.res, self.half_extent,
                      self.max_vehicles, self.offsets, self.lut, self.lut_lo, self.period, self.road.dash_length_m,
                      self.rgb_table)


@njit(cache=True)
def _vehicle_extent(length, width):
    """The longest vehicle's length plus the widest one's width (m), of ``(E, N)`` arrays."""
    longest = 0.0
    widest = 0.0
    for i in range(length.shape[0]):
        for j in range(length.shape[1]):
            longest = max(longest, length[i, j])
            widest = max(widest, width[i, j])
    return longest + widest


@njit(cache=True, nogil=True)
def _render_batch(out, x, y, yaw, length, width, extent, s, res, half_extent, max_vehicles, offsets, lut, lut_lo,
                  period, dash_length, rgb_table):
    """The images of :meth:`BevRenderer.render` into ``out`` ``(E, 3, S * S)`` uint8, from ``(E, N)`` float64 arrays.

    ``extent`` is an upper bound of any vehicle's length + width (m); ``offsets`` ``(S,)`` the pixel centres in
    metres from the ego (ahead for a row, left for a column); ``lut`` the lateral class every ``_LUT_RES_M`` from
    ``lut_lo``; ``rgb_table`` ``(class, dash_on, 3)`` the colour of a lateral class in a row with broken markings
    off or on. Each image depends on its own environment only, so threads may draw disjoint shards at once (the
    Python lock is released).
    """
    e, n = x.shape
    # A vehicle whose centre is farther than this from the ego cannot reach the image.
    reach = math.sqrt(2.0) * (half_extent + extent) + 1.0
    reach2 = reach * reach
    k = min(n, max_vehicles + 1)
    centre_px = s / 2 - 0.5
    tiles = np.empty((3, 2, s * s), dtype=np.uint8)
    dash_on = np.empty(s, dtype=np.intp)
    near = np.empty(n, dtype=np.intp)
    near_d2 = np.empty(n, dtype=np.float64)
    for i in range(e):
        ex = x[i, 0]
        ey = y[i, 0]
        _background(out[i], tiles, dash_on, ex, ey, offsets, lut, lut_lo, period, dash_length, rgb_table)
        # The ego and the vehicles within reach; when more than k, the ego and its k - 1 nearest (ties by
        # index).
        m = 0
        for j in range(n):
            dx = x[i, j] - ex
            dy = y[i, j] - ey
            d2 = dx * dx + dy * dy
            if j == 0 or d2 <= reach2:
                near[m] = j
                near_d2[m] = -1.0 if j == 0 else d2
                m += 1
        drawn = near[:m]
        if n > k and m > k:
            drawn = drawn[np.argsort(near_d2[:m], kind="mergesort")[:k]]
        for j in drawn:  # traffic first, the ego on top
            if j != 0:
                _fill_vehicle(out[i], s, res, centre_px, ex, ey, x[i, j], y[i, j], yaw[i, j], length[i, j],
                              width[i, j], PALETTE[VEHICLE])
        _fill_vehicle(out[i], s, res, centre_px, ex, ey, ex, ey, yaw[i, 0], length[i, 0], width[i, 0],
                      PALETTE[EGO])


@njit(cache=True)
def _background(out, tiles, dash_on, ex, ey, offsets, lut, lut_lo, period, dash_length, rgb_table):
    """Write one image's road into ``out`` ``(3, S * S)``, given the ego at ``(ex, ey)``.

    A column's lateral class gives two colours per channel (broken markings off, on) and a row's dash
    phase picks one, so every row is one of two templates. ``tiles`` ``(3, 2, S * S)`` gets each template
    repeated over as many rows as the longest run of rows with its phase, and each run is one copy.
    ``dash_on`` ``(S,)`` is scratch.
    """
    s = offsets.size
    inv_lut_res = 1.0 / _LUT_RES_M
    lut_last = lut.size - 1
    for c in range(s):
        t = (ey + offsets[c] - lut_lo) * inv_lut_res
        li = int(t) if t >= 0.0 else 0  # truncation, as a cast; a NaN lands on 0
        cls = lut[min(li, lut_last)]
        for d in range(2):
            for ch in range(3):
                tiles[ch, d, c] = rgb_table[cls, d, ch]
    longest = np.zeros(2, dtype=np.intp)  # per phase
    run = 0
    for r in range(s):
        d = dash_on[r] = _dash_on(ex + offsets[r], period, dash_length)
        run = run + 1 if r > 0 and d == dash_on[r - 1] else 1
        longest[d] = max(longest[d], run)
    for d in range(2):
        rows = 1
        while rows < longest[d]:  # doubling the rows already there
            more = min(rows, longest[d] - rows)
            for ch in range(3):
                _copy(tiles[ch, d, rows * s:(rows + more) * s], tiles[ch, d, :more * s])
            rows += more
    r = 0
    while r < s:
        end = r + 1
        while end < s and dash_on[end] == dash_on[r]:
            end += 1
        for ch in range(3):
            _copy(out[ch, r * s:end * s], tiles[ch, dash_on[r], :(end - r) * s])
        r = end


@njit(cache=True, inline="always")
def _dash_on(along, period, dash_length):
    """1 where ``along`` (m) falls on a dash of a broken marking (``along mod period < dash_length``,
    the floored modulo of numpy and Python), else 0.

    The modulo is taken through one division; only a phase within rounding error of a dash's start or
    end is decided by the exact (and slower) modulo.
    """
    phase = along - np.floor(along / period) * period
    tol = 1e-12 * (abs(along) + period)  # far above the rounding error of the phase
    if tol < phase < dash_length - tol:
        return 1
    if dash_length + tol < phase < period - tol:
        return 0
    return 1 if along % period < dash_length else 0


@njit(cache=True)
def _copy(dst, src):
    """``dst[:] = src`` for 1-D arrays, as a loop the compiler vectorises."""
    for t in range(src.size):
        dst[t] = src[t]


@njit(cache=True, inline="always")
def _fill_vehicle(out, s, res, centre_px, ex, ey, px, py, yaw, length, width, colour):
    """Fill a vehicle's strips in ``out`` ``(3, S * S)``: each strip's pixel-aligned bounding box, the
    pixels whose centres it holds. ``(px, py)`` the vehicle's centre, ``(ex, ey)`` the ego's (m)."""
    cos_yaw = math.cos(yaw)
    sin_yaw = math.sin(yaw)
    hl = length / (2 * _STRIPS)
    hw = 0.5 * width
    half_u = abs(cos_yaw) * hl + abs(sin_yaw) * hw  # along the road
    half_v = abs(sin_yaw) * hl + abs(cos_yaw) * hw  # across
    for strip in range(_STRIPS):
        lx = length * _STRIP_FRAC[strip]
        u = px + cos_yaw * lx - ex
        v = py + sin_yaw * lx - ey
        # Pixel p has its centre at centre_px - p (in pixels): covered rows and columns are the centres inside.
        r0 = np.ceil(centre_px - (u + half_u) / res)
        r1 = np.floor(centre_px - (u - half_u) / res)
        c0 = np.ceil(centre_px - (v + half_v) / res)
        c1 = np.floor(centre_px - (v - half_v) / res)
        if not (r0 <= r1 and c0 <= c1):  # empty (or not a number)
            continue
        r0, r1 = max(r0, 0.0), min(r1, s - 1.0)
        c0, c1 = max(c0, 0.0), min(c1, s - 1.0)
        if r0 > r1 or c0 > c1:  # outside the image
            continue
        first_col, cols = int(c0), int(c1 - c0) + 1
        for r in range(int(r0), int(r1) + 1):
            start = r * s + first_col
            for ch in range(3):
                value = colour[ch]
                for c in range(cols):
                    out[ch, start + c] = value
