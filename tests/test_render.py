"""The bird's-eye image: never blank, ego at the centre, vehicles where they are."""

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


def test_few_boxes_path_equals_pixel_index_path(monkeypatch):
    """A single environment fills its boxes by slices; a big batch by pixel indices: the same images.

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
    loop = np.stack([renderer.render(x[i:i + 1], y[i:i + 1], yaw[i:i + 1], sim.length[i:i + 1],
                                     sim.width[i:i + 1])[0] for i in range(3)])
    monkeypatch.setattr("lcsim.render._LOOP_MAX_BOXES", -1)  # force the pixel-index path
    indexed = renderer.render(x, y, yaw, sim.length, sim.width)
    assert (_classes(loop[0]) == VEHICLE).any() and (_classes(loop[0]) == EGO).any()
    np.testing.assert_array_equal(loop, indexed)


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
