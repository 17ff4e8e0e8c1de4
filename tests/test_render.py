"""The bird's-eye image: never blank, ego at the centre, vehicles where they are, and the compiled renderer
exactly as the numpy reference below."""

import dataclasses
import math

import numpy as np
import pytest

from lcsim.config import ScenarioConfig
from lcsim.core import LaneChangeCore
from lcsim.render import CLASS_NAMES, EGO, MARKING, OFF_ROAD, PALETTE, ROAD, VEHICLE, BevRenderer


def _classes(img: np.ndarray) -> np.ndarray:
    """(3, S, S) image -> (S, S) class ids via the palette."""
    flat = img.transpose(1, 2, 0).reshape(-1, 1, 3)
    match = (flat == PALETTE[None]).all(axis=-1)
    assert match.any(axis=1).all(), "every pixel has a palette colour"
    return match.argmax(axis=1).reshape(img.shape[1:])


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_image_never_blank_and_ego_centred(seed):
    core = LaneChangeCore(ScenarioConfig(), 1)
    core.reset([0], [seed])
    for action in (1, 2, 1, 1, 0, 1):
        core.step(np.array([action]))
        img = core.observe()["image"][0]
        assert img.shape == (3, 120, 120) and img.dtype == np.uint8
        cls = _classes(img)
        present = set(np.unique(cls).tolist())
        assert {ROAD, MARKING, EGO} <= present, present
        assert img.std() > 10  # never blank
        assert cls[59:61, 59:61].tolist() == [[EGO, EGO], [EGO, EGO]]  # the ego covers the centre
        if core.outcome[0]:
            break


def test_vehicle_drawn_where_it_is_and_off_road_outside():
    cfg = ScenarioConfig()
    r = BevRenderer(cfg.road, cfg.render)
    # Ego in lane 1 (y = 5.25), one car 10 m ahead in lane 2 (3.5 m to the left).
    x = np.array([[0.0, 10.0]])
    y = np.array([[5.25, 8.75]])
    z = np.zeros_like(x)
    img = r.render(x, y, z, np.array([[4.18, 5.37]]), np.array([[1.99, 1.80]]))[0]
    cls = _classes(img)
    row = 60 - int(10.0 / 0.5)  # 10 m ahead at 0.5 m/px
    col = 60 - int(3.5 / 0.5)  # 3.5 m to the left
    assert cls[row - 2:row + 2, col - 1:col + 1].min() == VEHICLE
    assert cls[60, 0] == OFF_ROAD  # 30 m to the left of lane 1 is beyond the road
    assert set(CLASS_NAMES) == {OFF_ROAD, ROAD, MARKING, VEHICLE, EGO}


def test_batch_equals_one_environment_at_a_time():
    """An environment's image does not depend on the others in its batch.

    Vehicles are given yaws (tilted strips) and some overlap the ego, which must stay on top.
    """
    core = LaneChangeCore(ScenarioConfig(), 3)
    core.reset([0, 1, 2], [11, 12, 13])
    for action in (2, 1, 1, 0, 1):
        core.step(np.array([action] * 3))
    sim = core.sim
    yaw = sim.yaw.copy()
    yaw[:, 1::3] = np.linspace(-0.4, 0.4, yaw[:, 1::3].size).reshape(yaw[:, 1::3].shape)
    x, y = sim.x.copy(), sim.y.copy()
    x[:, 5], y[:, 5] = x[:, 0] + 1.0, y[:, 0] + 0.5  # overlapping the ego
    renderer = core.renderer
    one = np.stack([renderer.render(x[i:i + 1], y[i:i + 1], yaw[i:i + 1], sim.length[i:i + 1],
                                    sim.width[i:i + 1])[0] for i in range(3)])
    batch = renderer.render(x, y, yaw, sim.length, sim.width)
    assert (_classes(one[0]) == VEHICLE).any() and (_classes(one[0]) == EGO).any()
    np.testing.assert_array_equal(one, batch)


def test_vehicle_extent_hint_gives_the_same_images():
    """The environment's renderer is told the largest vehicle (length + width) from the config; one that
    takes it from the arrays at each call draws the same images, crowded or not."""
    cfg = ScenarioConfig()
    core = LaneChangeCore(cfg, 2)
    core.reset([0, 1], [4, 5])
    assert core.renderer.vehicle_extent_m is not None
    plain = BevRenderer(cfg.road, cfg.render)
    sim = core.sim
    for action in (2, 1, 0, 1, 1):
        core.step(np.array([action, 2 - action]))
        np.testing.assert_array_equal(core.renderer.render(sim.x, sim.y, sim.yaw, sim.length, sim.width),
                                      plain.render(sim.x, sim.y, sim.yaw, sim.length, sim.width))
    x = sim.x.copy()
    x[:, 1:] = x[:, :1] + np.linspace(-25.0, 25.0, x.shape[1] - 1)  # everyone close: the nearest few drawn
    np.testing.assert_array_equal(core.renderer.render(x, sim.y, sim.yaw, sim.length, sim.width),
                                  plain.render(x, sim.y, sim.yaw, sim.length, sim.width))


# The renderer as it was first written in numpy (vectorised over the batch), kept as the reference the
# compiled one must match bit for bit.

def _reference_boxes(r: BevRenderer, x, y, yaw, length, width):
    e, n = x.shape
    s, res, strips = r.size, r.res, 4
    k = min(n, r.max_vehicles + 1)
    ex, ey = x[:, :1], y[:, :1]
    d2 = (x - ex) ** 2 + (y - ey) ** 2
    extent = r.vehicle_extent_m
    if extent is None:
        extent = float(length.max()) + float(width.max())
    reach = math.sqrt(2.0) * (r.half_extent + extent) + 1.0
    near = d2 <= reach * reach
    near[:, 0] = True
    if n > k and int(near.sum(axis=1).max()) > k:
        d2[:, 0] = -1.0
        sel = np.argsort(d2, axis=1, kind="stable")[:, :k]
        near[:] = False
        near[np.arange(e)[:, None], sel] = True
    vi = near.ravel().nonzero()[0]
    env = vi // n
    px, py, yaws, lengths, widths = x.take(vi), y.take(vi), yaw.take(vi), length.take(vi), width.take(vi)
    cs = np.array([np.cos(yaws), np.sin(yaws)])[:, :, None]
    lx = lengths[:, None] * ((np.arange(strips) + 0.5) / strips - 0.5)
    centre = np.array([px, py])[:, :, None] + cs * lx
    centre -= np.array([ex.take(env), ey.take(env)])[:, :, None]
    hl = (lengths / (2 * strips))[:, None]
    hw = (0.5 * widths)[:, None]
    a = np.abs(cs)
    half = a * hl + a[::-1] * hw
    first = np.maximum(np.ceil(s / 2 - 0.5 - (centre + half) / res), 0).astype(np.intp)
    last = np.minimum(np.floor(s / 2 - 0.5 - (centre - half) / res), s - 1).astype(np.intp)
    fits = first <= last
    return env, vi == env * n, first[0], last[0], first[1], last[1], fits[0] & fits[1]


def _reference_render(r: BevRenderer, x, y, yaw, length, width) -> np.ndarray:
    e, s = x.shape[0], r.size
    ex, ey = x[:, :1], y[:, :1]
    li = ((ey + r.offsets[None, :] - r.lut_lo) * (1.0 / 0.01)).astype(np.intp)
    col_cls = r.lut[np.clip(li, 0, r.lut.size - 1)]
    dash_on = (np.mod(ex + r.offsets[None, :], r.period) < r.road.dash_length_m).astype(np.intp)
    rgb = r.rgb_table[col_cls]  # (E, S columns, 2, 3)
    out = rgb[np.arange(e)[:, None, None], np.arange(s)[None, None, :], dash_on[:, :, None]]  # (E, rows, cols, 3)
    out = np.ascontiguousarray(out.transpose(0, 3, 1, 2))
    env, is_ego, r0, r1, c0, c1, ok = _reference_boxes(r, x, y, yaw, length, width)
    for own in (False, True):  # traffic, then the ego on top
        colour = PALETTE[EGO if own else VEHICLE][:, None, None]
        for m in np.flatnonzero(is_ego == own):
            for j in np.flatnonzero(ok[m]):
                out[env[m], :, r0[m, j]:r1[m, j] + 1, c0[m, j]:c1[m, j] + 1] = colour
    return out


def _assert_as_reference(r: BevRenderer, *arrays: np.ndarray) -> None:
    np.testing.assert_array_equal(r.render(*arrays), _reference_render(r, *arrays))


@pytest.mark.parametrize("envs", [1, 5])
def test_compiled_renderer_matches_the_reference_on_episodes(envs):
    cfg = ScenarioConfig()
    core = LaneChangeCore(cfg, envs)
    core.reset(list(range(envs)), [21 + i for i in range(envs)])
    plain = BevRenderer(cfg.road, cfg.render)
    view = BevRenderer(cfg.road, cfg.render, size_px=480, resolution_m_per_px=0.125)  # the env's rgb_array view
    rng = np.random.default_rng(envs)
    sim = core.sim
    for _ in range(8):
        core.step(rng.integers(0, 3, size=envs))
        arrays = (sim.x, sim.y, sim.yaw, sim.length, sim.width)
        for r in (core.renderer, plain, view):
            _assert_as_reference(r, *arrays)


def _random_batch(rng, e, n, spread_m):
    """Vehicles scattered around egos anywhere on (and off) a long road, at any yaw and size."""
    ex = rng.choice([0.0, -3.0, 1234.5, 1e6]) + rng.uniform(-50.0, 3000.0, (e, 1)).round(rng.choice([0, 1, 2, 6]))
    ey = rng.uniform(-8.0, 22.0, (e, 1))
    x = ex + rng.uniform(-spread_m, spread_m, (e, n))
    y = ey + rng.uniform(-spread_m, spread_m, (e, n))
    x[:, 0], y[:, 0] = ex[:, 0], ey[:, 0]
    yaw = np.where(rng.random((e, n)) < 0.5, 0.0, rng.normal(0.0, rng.choice([0.05, 1.0, 4.0]), (e, n)))
    length = rng.uniform(0.5, 12.0, (e, n))
    width = rng.uniform(0.3, 3.0, (e, n))
    return x, y, yaw, length, width


@pytest.mark.parametrize("seed", range(12))
def test_compiled_renderer_matches_the_reference_on_random_batches(seed):
    """Any yaw and size, egos off the road and far along it, crowds above ``max_vehicles_drawn`` (so only
    the nearest are drawn), vehicles across the image's edges, image sizes and resolutions."""
    rng = np.random.default_rng(seed)
    cfg = ScenarioConfig()
    size = int(rng.choice([16, 61, 120, 128]))
    res = float(rng.choice([0.125, 0.3, 0.5, 1.0]))
    road = dataclasses.replace(cfg.road, num_lanes=int(rng.integers(2, 7)))
    render = dataclasses.replace(cfg.render, max_vehicles_drawn=int(rng.choice([1, 5, 32])))
    for extent in (None, 15.0):
        r = BevRenderer(road, render, size_px=size, resolution_m_per_px=res, vehicle_extent_m=extent)
        for e, n in ((1, 1), (1, 40), (7, 101), (64, 12)):
            _assert_as_reference(r, *_random_batch(rng, e, n, spread_m=float(rng.choice([5.0, 40.0, 200.0]))))


def test_dash_phase_on_exact_boundaries():
    """Egos whose rows fall exactly on a dash's start or end, or a period's, at any distance along."""
    cfg = ScenarioConfig()
    r = BevRenderer(cfg.road, cfg.render)
    period = cfg.road.dash_length_m + cfg.road.dash_gap_m
    along = np.array([0.0, 0.25, 3.0, period, -period, -3.0, 1e3 * period, 1e6 * period + 3.0, 2.0**40, -7.75])
    x = np.stack([along, along + 50.0], axis=1)
    y = np.full_like(x, 5.25)
    ones = np.ones_like(x)
    _assert_as_reference(r, x, y, np.zeros_like(x), 4.5 * ones, 1.9 * ones)
