"""lc-view: MCAP episodes -> Rerun, checked by reading the saved .rrd back (no screen needed)."""

from __future__ import annotations

import dataclasses
import pathlib
from collections import defaultdict

import numpy as np
import pyarrow as pa
import pytest
from mcap.writer import Writer as McapWriter
from rerun.chunk import RrdReader

from lccli.record import record_main
from lccli.view import main
from lcdata import EpisodeWriter, read_episode
from lcdata.viewer.geometry import box_corners
from lcdata.viewer.streams import UNKNOWN_CLASS, class_ids
from lcsim.config import paper_scenario
from lcsim.core import KEEP, LaneChangeCore
from lcsim.drivers import RuleBasedDriver
from lcsim.render import PALETTE
from tests.test_mcap_reader import assemble, rewrite_with_mcap_package, take_apart, zeros_chunk
from tests.test_mcap_reader import chunk as mcap_chunk

N_TRAFFIC = 6
HORIZON = 5


def record(
    path: pathlib.Path,
    *,
    seed: int = 1,
    decisions: int = 12,
    predictions: bool = True,
    chunk_size: int = 1 << 20,
) -> pathlib.Path:
    """A small real episode: the simulator (6 traffic vehicles, 60 x 60 image) written with EpisodeWriter.

    Vehicles and ego state every simulation step (through the simulator's sub-step hook); image,
    RL step, lane-change events and a constant-velocity "prediction" of the nearest vehicles at
    every decision.
    """
    base = paper_scenario()
    config = dataclasses.replace(
        base, traffic=dataclasses.replace(base.traffic, num_vehicles=N_TRAFFIC, spawn_behind_m=60.0,
                                          spawn_ahead_m=120.0),
        render=dataclasses.replace(base.render, image_size_px=60),
    )  # fmt: skip
    core = LaneChangeCore(config, 1)
    sim = core.sim
    with EpisodeWriter(path, metadata={"config": config.to_dict(), "seed": seed, "driver": "rule"},
                       start_time_ns=10**18, chunk_size=chunk_size) as w:  # fmt: skip

        def write_step(s: object = None) -> None:
            step, t = int(sim.step[0]), float(sim.t_s[0])
            w.write_vehicles(step, t, sim.ids, sim.x[0], sim.y[0], sim.yaw[0], sim.speed[0], sim.accel[0],
                             sim.lane[0], sim.target_lane[0], sim.length[0], sim.width[0])  # fmt: skip
            w.write_ego(step, t, speed=float(sim.speed[0, 0]), lane=int(sim.lane[0, 0]))

        core.reset([0], [seed])
        write_step()
        sim.hooks.append(write_step)
        driver = RuleBasedDriver()
        obs = core.observe()
        for d in range(decisions):
            step, t = int(sim.step[0]), float(sim.t_s[0])
            mask = core.action_mask()
            action = (
                int(driver(obs, mask, core)[0]) if d != 2 else 2 if mask[0, 2] else 0
            )  # one forced change
            w.write_image(step, t, obs["image"][0])
            if predictions:
                ids = core.neighbours(np.array([0]))[0]
                v = np.stack([np.cos(sim.yaw[0]), np.sin(sim.yaw[0])], -1) * sim.speed[0][:, None]
                k = np.arange(1, HORIZON + 1)[None, :, None] * config.dt_s
                xy = np.stack([sim.x[0], sim.y[0]], -1)[ids][:, None, :] + v[ids][:, None, :] * k
                w.write_prediction(step, t, ids, xy)
            if action != KEEP:
                w.write_event(step, t, "lane_change_start", f"lane {int(sim.lane[0, 0])}")
            result = core.step(np.array([action]))
            w.write_rl_step(step, t, action=action, action_mask=mask[0], reward=float(result.reward[0]),
                            reward_components={k: float(v[0]) for k, v in result.components.items()},
                            outcome=str(result.outcome[0]), decision=d)  # fmt: skip
            obs = core.observe()
        w.write_event(int(sim.step[0]), float(sim.t_s[0]), "outcome", "timeout", "warning")
    return path


def read_rrd(path: pathlib.Path) -> dict[str, list[tuple[bool, pa.RecordBatch]]]:
    """Entity path -> [(is_static, record batch)] of every chunk of the first recording in ``path``."""
    out: dict[str, list[tuple[bool, pa.RecordBatch]]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        out[chunk.entity_path.lstrip("/")].append((chunk.is_static, chunk.to_record_batch()))
    return out


def temporal(chunks: list[tuple[bool, pa.RecordBatch]], column: str) -> dict[str, np.ndarray]:
    """``step``, ``sim_time`` and the per-row length of list ``column`` over the temporal chunks, by step."""
    steps, times, lengths = [], [], []
    for static, batch in chunks:
        if static or column not in batch.schema.names:
            continue
        steps.append(batch.column("step").to_numpy())
        times.append(batch.column("sim_time").cast(pa.int64()).to_numpy() / 1e9)
        lengths.append(np.asarray(batch.column(column).value_lengths().fill_null(0)))
    order = np.argsort(np.concatenate(steps), kind="stable")
    return {"step": np.concatenate(steps)[order], "sim_time": np.concatenate(times)[order],
            "count": np.concatenate(lengths)[order]}  # fmt: skip


@pytest.fixture(scope="module")
def episode_file(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    return record(tmp_path_factory.mktemp("view") / "ep.mcap")


@pytest.fixture(scope="module")
def saved(episode_file: pathlib.Path) -> dict[str, list[tuple[bool, pa.RecordBatch]]]:
    out = episode_file.with_suffix(".rrd")
    assert main([str(episode_file), "--save", str(out)]) == 0
    return read_rrd(out)


def test_entities(saved: dict[str, list[tuple[bool, pa.RecordBatch]]]) -> None:
    expected = {
        "world/road/edges", "world/road/markings", "world/road/shoulders", "world/road/lane_centres",
        "world/vehicles/boxes", "world/vehicles/trails", "world/ego", "world/ego/box",
        "world/prediction/predicted", "world/prediction/actual", "camera", "camera/bev",
        "plots/speed/ego", "plots/speed/target", "plots/speed/traffic_mean", "plots/reward/total",
        "plots/reward/forward", "plots/reward/collision", "plots/reward/off_road", "plots/reward/success",
        "plots/return", "plots/lane/ego", "plots/lane/target", "plots/lane/action", "log/events", "log/decisions",
    }  # fmt: skip
    assert expected <= set(saved), sorted(expected - set(saved))
    for entity in ("world/road/edges", "world/road/markings", "camera"):
        assert all(static for static, _ in saved[entity]), entity


def test_vehicle_boxes_per_step(
    saved: dict[str, list[tuple[bool, pa.RecordBatch]]], episode_file: pathlib.Path
) -> None:
    episode = read_episode(episode_file)
    tracks = episode.tracks
    per_step = tracks[~tracks["is_ego"]].groupby("step").size()
    boxes = temporal(saved["world/vehicles/boxes"], "LineStrips2D:strips")
    np.testing.assert_array_equal(boxes["step"], per_step.index.to_numpy())
    np.testing.assert_array_equal(boxes["count"], per_step.to_numpy())
    assert (boxes["count"] == N_TRAFFIC).all()
    # time lines: simulation step and simulation time, one row per recorded step
    ego = episode.ego
    np.testing.assert_array_equal(boxes["step"], ego["step"].to_numpy())
    np.testing.assert_allclose(boxes["sim_time"], ego["t"].to_numpy(), atol=1e-9)
    trails = temporal(saved["world/vehicles/trails"], "LineStrips2D:strips")
    assert (trails["count"] == N_TRAFFIC + 1).all()
    ego_box = temporal(saved["world/ego/box"], "LineStrips2D:strips")
    assert (ego_box["count"] == 1).all() and len(ego_box["step"]) == len(ego)


def test_other_streams(
    saved: dict[str, list[tuple[bool, pa.RecordBatch]]], episode_file: pathlib.Path
) -> None:
    episode = read_episode(episode_file)
    images = temporal(saved["camera/bev"], "SegmentationImage:buffer")
    np.testing.assert_array_equal(images["step"], episode.image_steps)
    assert (images["count"] == 1).all()  # one blob per image, one class id per pixel in it
    blobs = [b.column("SegmentationImage:buffer").flatten() for s, b in saved["camera/bev"] if not s]
    assert all((np.asarray(blob.value_lengths()) == 60 * 60).all() for blob in blobs)
    pred = temporal(saved["world/prediction/predicted"], "LineStrips2D:strips")
    actual = temporal(saved["world/prediction/actual"], "LineStrips2D:strips")
    expected = episode.predictions.query("k == 1 and vehicle_id >= 0").groupby("step").size()
    np.testing.assert_array_equal(pred["step"], expected.index.to_numpy())
    np.testing.assert_array_equal(pred["count"], expected.to_numpy())
    np.testing.assert_array_equal(actual["count"], pred["count"])
    rewards = temporal(saved["plots/return"], "Scalars:scalars")
    np.testing.assert_array_equal(rewards["step"], episode.steps["step"].to_numpy())
    ret = np.concatenate(
        [b.column("Scalars:scalars").flatten().to_numpy() for s, b in saved["plots/return"] if not s]
    )
    np.testing.assert_allclose(np.sort(ret) if (np.diff(ret) >= 0).all() else ret,
                               np.cumsum(episode.steps["reward"].to_numpy()), rtol=1e-9)  # fmt: skip
    events = temporal(saved["log/events"], "TextLog:text")
    assert len(events["step"]) == len(episode.events)
    texts = [
        t for s, b in saved["log/events"] if not s for t in b.column("TextLog:text").flatten().to_pylist()
    ]
    assert any("lane_change_start" in t for t in texts) and any("[outcome] timeout" in t for t in texts)
    decisions = temporal(saved["log/decisions"], "TextLog:text")
    assert len(decisions["step"]) == len(episode.steps)


def test_no_prediction_topic_no_prediction_entities(tmp_path: pathlib.Path) -> None:
    path = record(tmp_path / "nopred.mcap", decisions=3, predictions=False)
    out = tmp_path / "nopred.rrd"
    assert main([str(path), "--save", str(out)]) == 0
    entities = read_rrd(out)
    assert "world/vehicles/boxes" in entities and not any(e.startswith("world/prediction") for e in entities)


def test_several_episodes(tmp_path: pathlib.Path) -> None:
    a = record(tmp_path / "a.mcap", seed=1, decisions=3)
    b = record(tmp_path / "b.mcap", seed=2, decisions=4)
    # side by side: one recording, one prefix per episode
    assert main([str(a), str(b), "--side-by-side", "--save", str(tmp_path / "both.rrd")]) == 0
    both = read_rrd(tmp_path / "both.rrd")
    assert {"episodes/a/world/vehicles/boxes", "episodes/b/world/vehicles/boxes"} <= set(both)
    steps_a = temporal(both["episodes/a/world/ego/box"], "LineStrips2D:strips")["step"]
    steps_b = temporal(both["episodes/b/world/ego/box"], "LineStrips2D:strips")["step"]
    assert len(steps_a) == len(read_episode(a).ego) and len(steps_b) == len(read_episode(b).ego)
    # separate recordings: one file (and recording id) per episode
    assert main([str(a), str(b), "--save", str(tmp_path / "sep.rrd")]) == 0
    for name in ("a", "b"):
        reader = RrdReader(tmp_path / f"sep.{name}.rrd")
        assert [r.recording_id for r in reader.recordings()] == [name]
        assert "world/vehicles/boxes" in read_rrd(tmp_path / f"sep.{name}.rrd")


def test_truncated_file_shows_recovered_part(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    full = record(tmp_path / "full.mcap", decisions=40, predictions=False, chunk_size=16 << 10)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    out = tmp_path / "cut.rrd"
    assert main([str(cut), "--save", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "truncated" in err and "Traceback" not in err
    boxes = temporal(read_rrd(out)["world/vehicles/boxes"], "LineStrips2D:strips")
    assert 0 < len(boxes["step"]) < len(read_episode(full).ego)



def _shown(rrd: dict[str, list[tuple[bool, pa.RecordBatch]]]) -> dict[str, int]:
    """Rows logged over time per entity: what the viewer shows, counted."""
    return {e: sum(b.num_rows for static, b in chunks if not static) for e, chunks in rrd.items()
            if not e.startswith("__")}  # fmt: skip


@pytest.mark.parametrize("compression", ["lz4", "zstd", ""])
def test_another_writers_file_shows_what_ours_does(
    episode_file: pathlib.Path, saved: dict[str, list[tuple[bool, pa.RecordBatch]]], tmp_path: pathlib.Path,
    capsys: pytest.CaptureFixture[str], compression: str,
) -> None:  # fmt: skip
    """The episode written again by the mcap package (each compression of the specification): the same
    entities with the same rows. An lz4 file gave a "truncated" warning and an .rrd of nothing."""
    other = rewrite_with_mcap_package(episode_file, tmp_path / "other.mcap", compression)
    out = tmp_path / "other.rrd"
    assert main([str(other), "--save", str(out)]) == 0
    assert "warning" not in capsys.readouterr().err
    assert _shown(read_rrd(out)) == _shown(saved)


def test_hostile_files_are_refused_in_one_line_writing_nothing(
    episode_file: pathlib.Path, tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A small file whose chunk claims 32 MiB from a few hundred bytes, the same episode twice in one file, and
    a file of 2,100 steps each with a vehicle of a new id (a grid of 2,100 x 2,100 cells: with 12,000 steps
    the viewer took 2.6 GB)."""
    head, defs, messages = take_apart(episode_file)
    bomb = assemble(tmp_path / "bomb.mcap", [*head, mcap_chunk(b"".join(defs + messages)), zeros_chunk(b"", 32 << 20)])
    twice = assemble(tmp_path / "twice.mcap", [*head, mcap_chunk(b"".join(defs + messages)), mcap_chunk(b"".join(messages))])
    sparse = tmp_path / "sparse.mcap"
    one = np.ones(1)
    with EpisodeWriter(sparse, metadata={"driver": "crafted"}, start_time_ns=0) as w:
        for k in range(2100):
            w.write_vehicles(k, k * 0.05, np.array([k]), one * k, one, one * 0, one, one * 0, np.array([1]),
                             np.array([1]), one * 4, one * 2)  # fmt: skip
    for path, why in ((bomb, "more than 1000 to 1"), (twice, "holds the same message twice"),
                      (sparse, "2,100 steps x 2,100 vehicle ids would make a track grid of 4,410,000 cells")):  # fmt: skip
        out = tmp_path / f"{path.stem}.rrd"
        assert main([str(path), "--save", str(out)]) == 2, path
        err = capsys.readouterr().err
        assert err.startswith(f"lc-view: error: {path}: ") and err.count("\n") == 1 and why in err, err
        assert not out.exists()


def _two_vehicles(path: pathlib.Path, far_x: float, **road: float) -> pathlib.Path:
    """20 steps of two vehicles under the paper scenario's config, the second at ``far_x``, the road changed."""
    config = paper_scenario().to_dict()
    config["road"] = {**config["road"], **road}
    two = np.ones(2)
    with EpisodeWriter(path, metadata={"driver": "crafted", "config": config}, start_time_ns=0) as w:
        for k in range(20):
            w.write_vehicles(k, k * 0.05, np.array([0, 1]), np.array([k, far_x]), two, two * 0, two, two * 0,
                             np.array([1, 1]), np.array([1, 1]), two * 4, two * 2)  # fmt: skip
    return path


@pytest.mark.parametrize(
    ("far_x", "road", "why"),
    [
        (1e9, {}, "the road to draw spans x from -100 to 1e+09 m (the vehicles' positions): 3.33e+08 lane-marking "
                  "dashes, more than the 1,000,000 drawn"),
        (10.0, {"num_lanes": 10**8}, "the config's road has 100000000 lanes; 1 to 64 can be drawn"),
        (10.0, {"dash_length_m": 0.0, "dash_gap_m": 0.0}, "dash and gap not both 0"),
        (10.0, {"lane_width_m": float("inf")}, "lengths must be finite and >= 0"),
    ],
)  # fmt: skip
def test_a_road_that_cannot_be_drawn_is_refused_in_one_line(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str], far_x: float, road: dict[str, float], why: str
) -> None:
    """The road is drawn from the file's config and positions: a vehicle at x = 1e9 m asked for 333 million
    dashes (5 GB), 100 million lanes for 39 GB, dashes of 0 m divided by zero: each a traceback."""
    path = _two_vehicles(tmp_path / "road.mcap", far_x, **road)
    out = tmp_path / "road.rrd"
    assert main([str(path), "--save", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"lc-view: error: {path}: ") and why in err and err.count("\n") == 1, err
    assert not out.exists()


def test_positions_that_are_not_numbers_leave_the_road_where_the_others_are(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _two_vehicles(tmp_path / "nan.mcap", float("nan"))
    assert main([str(path), "--save", str(tmp_path / "nan.rrd")]) == 0
    (edges,) = [b for static, b in read_rrd(tmp_path / "nan.rrd")["world/road/edges"] if static]
    strips = np.asarray(edges.column("LineStrips2D:strips").to_pylist()[0], dtype=float)  # (2 edges, 2 ends, xy)
    assert strips[..., 0].min() == -100.0 and strips[..., 0].max() == 119.0  # 0..19 m, and 100 m around

# -- colours of the plots ---------------------------------------------------------------------------
BACKGROUNDS = {"light": (255, 255, 255), "dark": (13, 16, 17)}
"""The plot backgrounds of Rerun's light and dark themes (white; the dark theme's near-black)."""


def _linear(rgb: tuple[int, ...]) -> np.ndarray:
    c = np.asarray(rgb[:3], dtype=np.float64) / 255
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def contrast(a: tuple[int, ...], b: tuple[int, ...]) -> float:
    """WCAG contrast ratio of two sRGB colours (1 to 21; 3 is the least for lines and marks)."""
    la, lb = sorted(float(_linear(c) @ [0.2126, 0.7152, 0.0722]) for c in (a, b))
    return (lb + 0.05) / (la + 0.05)


def lab(rgb: tuple[int, ...]) -> np.ndarray:
    """CIELAB (D65) of an sRGB colour: distances of more than about 25 read as different colours."""
    xyz = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]) @ _linear(rgb)
    f = np.cbrt(xyz / [0.9505, 1.0, 1.089])
    return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])


def series_colours(chunks: dict[str, list[tuple[bool, pa.RecordBatch]]]) -> dict[str, tuple[int, int, int, int]]:
    """Entity -> the RGBA colour of its series, for every entity holding scalars (None where it has none)."""
    out = {}
    for entity, batches in chunks.items():
        names = {n for _, b in batches for n in b.schema.names}
        if "Scalars:scalars" not in names:
            continue
        packed = [c for _, b in batches for n in ("SeriesLines:colors", "SeriesPoints:colors") if n in b.schema.names
                  for c in b.column(n).flatten().to_pylist()]  # fmt: skip
        out[entity] = tuple(packed[-1].to_bytes(4, "big")) if packed else None
    return out


def assert_plot_colours(colours: dict[str, tuple[int, int, int, int] | None], plot_of) -> None:
    """Every series has a colour of some saturation that reads on both themes, unlike every other series
    of its plot (``plot_of(entity)``)."""
    assert colours and all(c is not None for c in colours.values()), colours
    for entity, rgba in colours.items():
        for theme, background in BACKGROUNDS.items():
            assert contrast(rgba, background) >= 3.0, (entity, rgba, theme)
        assert max(rgba[:3]) - min(rgba[:3]) >= 60, (entity, rgba, "grey")
    plots = defaultdict(list)
    for entity, rgba in colours.items():
        plots[plot_of(entity)].append((entity, rgba))
    for plot, series in plots.items():
        for i, (a, ca) in enumerate(series):
            for b, cb in series[i + 1 :]:
                assert np.linalg.norm(lab(ca) - lab(cb)) > 25, (plot, a, ca, b, cb)


def test_every_series_has_a_colour_for_both_themes(
    saved: dict[str, list[tuple[bool, pa.RecordBatch]]], tmp_path: pathlib.Path
) -> None:
    colours = series_colours(saved)
    assert {"plots/speed/ego", "plots/speed/target", "plots/reward/total", "plots/return",
            "plots/lane/action"} <= set(colours)  # fmt: skip
    assert_plot_colours(colours, lambda entity: entity.split("/")[1])  # plots/<plot>/...
    # side by side: the returns (and ego speeds) of all episodes are drawn in one plot
    paths = [record(tmp_path / f"{name}.mcap", seed=k + 1, decisions=3, predictions=False)
             for k, name in enumerate("abc")]  # fmt: skip
    assert main([*map(str, paths), "--side-by-side", "--save", str(tmp_path / "abc.rrd")]) == 0
    both = series_colours(read_rrd(tmp_path / "abc.rrd"))
    assert_plot_colours(both, lambda entity: "/".join(entity.split("/")[:4]))  # episodes/<id>/plots/<plot>/...
    shared = {e: c for e, c in both.items() if e.endswith(("plots/return", "plots/speed/ego"))}
    assert len(shared) == 6
    assert_plot_colours(shared, lambda entity: entity.split("/", 2)[2])  # one plot per stream


# -- the layout ---------------------------------------------------------------------------------------
def blueprint_views(path: pathlib.Path) -> list[dict[str, object]]:
    """The views of the default blueprint saved in ``path``: class (``2D``, ``TimeSeries``, ``TextLog``),
    origin and content queries (``$origin/**``, ``/world/**`` or entity paths)."""
    reader = RrdReader(path)
    (store,) = reader.blueprints()
    views: dict[str, dict[str, object]] = defaultdict(dict)
    for chunk in reader.stream(store=store):
        parts = chunk.entity_path.strip("/").split("/")
        batch = chunk.to_record_batch()
        for column in ("ViewBlueprint:class_identifier", "ViewBlueprint:space_origin", "ViewContents:query"):
            if parts[0] == "view" and column in batch.schema.names:
                views[parts[1]][column.split(":")[1]] = batch.column(column).to_pylist()[-1]
    return [{"class": v["class_identifier"][0], "origin": v["space_origin"][0], "query": v["query"]}
            for v in views.values()]  # fmt: skip


def assert_views_have_data(views: list[dict[str, object]], entities: set[str]) -> None:
    """Each view shows at least one logged entity: no empty panel."""
    for view in views:
        shown = set()
        for query in view["query"]:
            query = query.replace("$origin", "/" + view["origin"]).lstrip("+ ").strip("/")
            if query.endswith("/**"):
                base = query.removesuffix("/**")
                shown |= {e for e in entities if e == base or e.startswith(base + "/")}
            else:
                shown |= {e for e in entities if e == query}
        assert shown, view


def test_layout_shows_only_views_with_data(
    episode_file: pathlib.Path, tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A corpus recording (lc-record --scenario corpus: no bird's-eye image) gets no image view."""
    assert record_main(["--scenario", "corpus", "--out", str(tmp_path), "--vehicles", "4", "--steps", "40"]) == 0
    (corpus,) = tmp_path.glob("*.mcap")
    assert "/camera/bev_semantic" not in read_episode(corpus).topics
    assert main([str(corpus), "--save", str(tmp_path / "corpus.rrd")]) == 0
    views = blueprint_views(tmp_path / "corpus.rrd")
    assert not [v for v in views if v["origin"].startswith("camera")], views
    assert {v["origin"] for v in views} >= {"world/ego", "world", "plots/speed", "plots/return", "log"}
    assert_views_have_data(views, set(read_rrd(tmp_path / "corpus.rrd")))
    # a file with images keeps its image view; side by side each episode's tab has the views of its own data
    assert main([str(episode_file), "--save", str(tmp_path / "images.rrd")]) == 0
    assert "camera" in {v["origin"] for v in blueprint_views(tmp_path / "images.rrd")}
    both = tmp_path / "both.rrd"
    assert main([str(corpus), str(episode_file), "--side-by-side", "--save", str(both)]) == 0
    views = blueprint_views(both)
    cameras = [v["origin"] for v in views if v["origin"].endswith("/camera")]
    assert cameras == ["episodes/ep/camera"], cameras
    assert_views_have_data(views, set(read_rrd(both)))
    capsys.readouterr()


def test_bad_input_one_line_error(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("hello\n")
    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        writer = McapWriter(f)
        writer.start()
        schema = writer.register_schema("other.Thing", "jsonschema", b"{}")
        channel = writer.register_channel("/thing", "json", schema)
        writer.add_message(channel, log_time=1, data=b"{}", publish_time=1)
        writer.finish()
    for path in (tmp_path / "missing.mcap", not_mcap, foreign, tmp_path):
        assert main([str(path), "--headless"]) == 2, path
        err = capsys.readouterr().err
        assert err.startswith("lc-view: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert main([str(foreign), "--save", str(tmp_path / "x.txt")]) == 2


def test_help_has_example(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "lc-view runs/" in text and "--side-by-side" in text and "--web" in text


def test_class_ids_and_box_corners() -> None:
    img = PALETTE[np.array([[0, 1], [3, 4]])].transpose(2, 0, 1).copy()  # (3, 2, 2)
    img[:, 0, 0] = (1, 2, 3)  # not a palette colour
    np.testing.assert_array_equal(class_ids(img), [[UNKNOWN_CLASS, 1], [3, 4]])
    c = box_corners(
        np.array([10.0]), np.array([2.0]), np.array([np.pi / 2]), np.array([4.0]), np.array([2.0])
    )
    assert c.shape == (1, 5, 2)
    np.testing.assert_allclose(c[0, 0], c[0, 4])
    # heading +y (left of the road): the nose is 2 m further left, drawn 2 m higher on screen (y mirrored)
    np.testing.assert_allclose(c[0, :4].mean(axis=0), [10.0, -2.0], atol=1e-6)
    np.testing.assert_allclose(c[0, :4, 1].min(), -4.0, atol=1e-6)
