"""Importers: small SUMO FCD and highD files in their real layouts -> corpus episodes, read back with the
corpus's own readers (load_tracks, read_episode, Corpus, lc-view, lc-train-predictor)."""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
import pandas as pd
import pytest

from lccli.importer import main
from lcdata import read_episode
from lcdata.corpus import Corpus, WindowOptions, load_tracks
from lcdata.importers import HighdOptions, ImportOptions, import_highd, import_sumo_fcd
from lcdata.importers.resample import Frame, resample

# -- SUMO FCD -----------------------------------------------------------------------------------------------
SUMO_DT = 0.1
SUMO_STEPS = 41  # 0.0 .. 4.0 s
LENGTH = 5.0  # SUMO's default car, the importer's default too


def sumo_vehicles(t: float) -> list[dict[str, object]]:
    """Front-bumper positions as SUMO writes them: four lanes of edge e0 (lane 0 rightmost, y = -1.6 - 3.2 * (3 - i)
    as SUMO lays lanes to the right of the edge line), heading east (angle 90)."""
    lane_y = [-11.2, -8.0, -4.8, -1.6]
    out: list[dict[str, object]] = [
        # constant 20 m/s in lane 0
        {"id": "car.a", "x": 10 + 20 * t, "y": lane_y[0], "angle": 90.0, "speed": 20.0, "lane": "e0_0"},
        # accelerating at 1 m/s² in lane 3, no acceleration attribute
        {"id": "car.b", "x": 40 + 15 * t + 0.5 * t * t, "y": lane_y[3], "angle": 90.0, "speed": 15 + t,
         "lane": "e0_3"},
        # heading north (angle 0) at 10 m/s on another edge, crossing a junction lane for a while
        {"id": "north", "x": 200.0, "y": 10 * t, "angle": 0.0, "speed": 10.0,
         "lane": ":J1_0_0" if 1.0 <= t < 1.5 else "e1_0"},
    ]  # fmt: skip
    # a lane change from lane 1 to lane 2: the lateral move over 1 s, SUMO's lane switches at t = 2.0
    y = lane_y[1] + 3.2 * min(max(t - 1.5, 0.0), 1.0)
    out.append({"id": "changer", "x": 60 + 18 * t, "y": y, "angle": 90.0 - (10.0 if 1.5 < t < 2.5 else 0.0),
                "speed": 18.0, "lane": "e0_2" if t >= 2.0 - 1e-9 else "e0_1"})  # fmt: skip
    if 1.0 - 1e-9 <= t <= 3.0 + 1e-9:  # enters at 1 s, leaves after 3 s
        out.append({"id": "late", "x": 5 + 22 * (t - 1), "y": lane_y[2], "angle": 90.0, "speed": 22.0,
                    "lane": "e0_2"})  # fmt: skip
    return out


def write_fcd(path: pathlib.Path, steps: int = SUMO_STEPS) -> pathlib.Path:
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             '<fcd-export xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" '
             'xsi:noNamespaceSchemaLocation="http://sumo.dlr.de/xsd/fcd_file.xsd">']  # fmt: skip
    for i in range(steps):
        t = round(i * SUMO_DT, 2)
        lines.append(f'    <timestep time="{t:.2f}">')
        for v in sumo_vehicles(t):
            lines.append(f'        <vehicle id="{v["id"]}" x="{v["x"]:.2f}" y="{v["y"]:.2f}" angle="{v["angle"]:.2f}" '
                         f'type="DEFAULT_VEHTYPE" speed="{v["speed"]:.2f}" pos="0.00" lane="{v["lane"]}" '
                         'slope="0.00"/>')  # fmt: skip
        lines.append('        <person id="walker" x="1.00" y="2.00" angle="0.00" speed="1.00" pos="0.00" edge="e9"/>')
        lines.append("    </timestep>")
    lines.append("</fcd-export>")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def sumo_out(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    root = tmp_path_factory.mktemp("sumo")
    import_sumo_fcd(write_fcd(root / "fcd.xml"), root / "out")
    return root / "out"


def vehicle(tracks: pd.DataFrame, episode_meta: dict[str, str], source_id: str) -> pd.DataFrame:
    vehicles = json.loads(episode_meta["vehicles"])
    vid = next(int(k) for k, v in vehicles.items() if v["source_id"] == source_id)
    return tracks[tracks["vehicle_id"] == vid].sort_values("step")


def test_sumo_positions_are_centres_on_the_corpus_grid(sumo_out: pathlib.Path) -> None:
    [tracks] = load_tracks(sumo_out)
    meta = read_episode(sumo_out / "sumo_fcd_0000.mcap").metadata
    assert np.allclose(np.diff(np.unique(tracks["t"])), 0.05)  # 10 Hz source -> 20 Hz corpus
    assert tracks["step"].min() == 0 and tracks["step"].max() == 80
    assert not tracks["is_ego"].any() and tracks["vehicle_id"].min() >= 1
    a = vehicle(tracks, meta, "car.a")
    t = a["t"].to_numpy()
    # the centre is half a length behind the front bumper; 20 m/s is 1.0 m per 0.05 s step
    assert np.allclose(a["x"], 10 + 20 * t - LENGTH / 2)
    assert np.allclose(np.diff(a["x"]), 1.0)
    assert np.allclose(a["y"], -11.2) and np.allclose(a["yaw"], 0.0) and np.allclose(a["speed"], 20.0)
    assert (a["lane"] == 0).all() and np.allclose(a["accel"], 0.0)
    # SUMO's angle 0 is north: yaw +90 degrees, the centre 2.5 m south of the bumper
    north = vehicle(tracks, meta, "north")
    assert np.allclose(north["yaw"], math.pi / 2)
    assert np.allclose(north["x"], 200.0) and np.allclose(north["y"], 10 * north["t"] - LENGTH / 2)
    # an internal (junction) lane is unknown, -1
    on_junction = (north["t"] >= 1.0 - 1e-9) & (north["t"] < 1.5 - 1e-9)
    assert (north["lane"][on_junction] == -1).all() and (north["lane"][~on_junction] == 0).all()
    # acceleration from the change of speed when the file has none
    b = vehicle(tracks, meta, "car.b")
    assert np.allclose(b["accel"][b["t"] >= 0.1], 1.0, atol=1e-6)


def test_sumo_entering_leaving_and_lane_change(sumo_out: pathlib.Path) -> None:
    [tracks] = load_tracks(sumo_out)
    meta = read_episode(sumo_out / "sumo_fcd_0000.mcap").metadata
    late = vehicle(tracks, meta, "late")
    assert late["step"].tolist() == list(range(20, 61))  # present 1.0 .. 3.0 s, not extrapolated
    changer = vehicle(tracks, meta, "changer")
    lane = dict(zip(changer["step"], changer["lane"], strict=True))
    assert lane[39] == 1 and lane[40] == 2  # sample and hold: the new lane from SUMO's first sample in it
    assert changer["yaw"].max() == pytest.approx(math.radians(10.0))
    # the predictor's corpus sees the lane change
    corpus = Corpus.from_tracks(load_tracks(sumo_out), WindowOptions(history_steps=10, future_steps=10))
    batch = corpus.gather()
    assert batch.size > 0 and batch.lane_change.any()
    vehicles = json.loads(meta["vehicles"])
    assert {v["source_id"] for v in vehicles.values()} == {"car.a", "car.b", "north", "changer", "late"}
    assert meta["source_format"] == "sumo-fcd" and meta["source_file"] == "fcd.xml"
    assert len(meta["source_sha256"]) == 64 and json.loads(meta["source_start_s"]) == 0.0


def test_sumo_import_is_deterministic_and_cut_into_episodes(tmp_path: pathlib.Path) -> None:
    fcd = write_fcd(tmp_path / "fcd.xml")
    options = ImportOptions(episode_steps=30, min_episode_steps=5)
    calls: list[tuple[int, int]] = []
    one = import_sumo_fcd(fcd, tmp_path / "one", options, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (fcd.stat().st_size,) * 2  # bytes read of the file
    two = import_sumo_fcd(fcd, tmp_path / "two", options)
    assert [e.path.name for e in one] == ["sumo_fcd_0000.mcap", "sumo_fcd_0001.mcap", "sumo_fcd_0002.mcap"]
    for a, b in zip(one, two, strict=True):
        assert a.path.read_bytes() == b.path.read_bytes()
    episodes = [read_episode(e.path) for e in one]
    assert [json.loads(e.metadata["source_start_s"]) for e in episodes] == pytest.approx([0.0, 1.5, 3.0])
    assert [e.tracks["step"].max() for e in episodes] == [29, 29, 20]  # steps restart at 0 in each
    assert not list((tmp_path / "one").glob(".*"))  # no staging folder left behind


def test_resample_keeps_source_samples_and_interpolates_between() -> None:
    def frame(t: float, ids: list[int], x: list[float], yaw: float = 0.0) -> Frame:
        n = len(ids)
        f = np.zeros(n)
        return Frame(t, np.array(ids), np.array(x), f, np.full(n, yaw), f, f, np.arange(n), f + 4, f + 2)

    # 25 Hz: grid t = 0, 0.05, ... falls on every fifth frame; vehicle 2 only in the first two frames
    frames = [frame(0.0, [1, 2], [0.0, 5.0], 3.1), frame(0.04, [1, 2], [1.0, 6.0], -3.1), frame(0.08, [1], [2.0])]
    out = list(resample(frames, 0.05))
    assert [k for k, _ in out] == [0, 1]
    assert out[0][1].ids.tolist() == [1, 2]
    assert out[1][1].ids.tolist() == [1] and out[1][1].x[0] == pytest.approx(1.25)
    yaw = list(resample(frames[:2], 0.02))[1][1].yaw[0]  # half-way through a turn across +-pi
    assert abs(abs(yaw) - math.pi) < 1e-9
    with pytest.raises(ValueError, match="does not increase"):
        list(resample([frames[1], frames[0]], 0.05))


# -- highD --------------------------------------------------------------------------------------------------
FPS = 25
FRAMES = range(1, 101)  # 4 s
LOWER = {5: 21.875, 6: 25.625}  # lane id -> image y of the lane centre (3.75 m lanes, y down)
UPPER = {2: 9.875, 3: 13.625}
SIZE = {"Car": (4.5, 1.9), "Truck": (12.0, 2.5)}


def highd_row(frame: int, vid: int, cx: float, cy: float, length: float, width: float, vx: float, vy: float,
              lane_id: int, ax: float = 0.0) -> dict[str, float]:
    """One row of XX_tracks.csv: a vehicle centred at image ``(cx, cy)`` (metres, y down) as highD writes it, by the
    upper-left corner of its bounding box."""
    return {
        "frame": frame, "id": vid, "x": cx - length / 2, "y": cy - width / 2, "width": length, "height": width,
        "xVelocity": vx, "yVelocity": vy, "xAcceleration": ax, "yAcceleration": 0.0, "frontSightDistance": 100.0,
        "backSightDistance": 100.0, "dhw": 0.0, "thw": 0.0, "ttc": 0.0, "precedingXVelocity": 0.0, "precedingId": 0,
        "followingId": 0, "leftPrecedingId": 0, "leftAlongsideId": 0, "leftFollowingId": 0, "rightPrecedingId": 0,
        "rightAlongsideId": 0, "rightFollowingId": 0, "laneId": lane_id,
    }  # fmt: skip


def highd_meta(vid: int, length: float, width: float, frames: list[int], cls: str, direction: int, speed: float,
               lane_changes: int) -> dict[str, object]:
    """One row of XX_tracksMeta.csv."""
    return {
        "id": vid, "width": length, "height": width, "initialFrame": frames[0], "finalFrame": frames[-1],
        "numFrames": len(frames), "class": cls, "drivingDirection": direction,
        "traveledDistance": speed * len(frames) / FPS, "minXVelocity": speed, "maxXVelocity": speed,
        "meanXVelocity": speed, "minDHW": -1, "minTHW": -1, "minTTC": -1, "numLaneChanges": lane_changes,
    }  # fmt: skip


def highd_rows() -> tuple[list[dict[str, float]], list[dict[str, object]]]:
    """(tracks rows, meta rows): vehicle 1 and 2 drive +x on the lower carriageway (2 changes from lane 6,
    the rightmost, to lane 5 between frames 41 and 61, its lane id switching at frame 51), vehicles 3 and 4
    drive -x on the upper one (4 enters at frame 30)."""
    specs = {
        1: dict(direction=2, cls="Truck", x0=20.0, vx=30.0, lane=lambda f: 6, cy=lambda f: LOWER[6], frames=FRAMES),
        2: dict(direction=2, cls="Car", x0=60.0, vx=35.0, lane=lambda f: 6 if f < 51 else 5,
                cy=lambda f: LOWER[6] - 3.75 * min(max((f - 41) / 20, 0.0), 1.0), frames=FRAMES),
        3: dict(direction=1, cls="Car", x0=400.0, vx=-25.0, lane=lambda f: 2, cy=lambda f: UPPER[2], frames=FRAMES),
        4: dict(direction=1, cls="Car", x0=380.0, vx=-28.0, lane=lambda f: 3, cy=lambda f: UPPER[3],
                frames=range(30, 101)),
    }  # fmt: skip
    tracks, meta = [], []
    for vid, s in specs.items():
        w, h = SIZE[s["cls"]]
        frames = list(s["frames"])
        for f in frames:
            t = (f - 1) / FPS
            cy, cy_next = s["cy"](f), s["cy"](f + 1)
            tracks.append(highd_row(f, vid, s["x0"] + s["vx"] * t, cy, w, h, s["vx"], (cy_next - cy) * FPS,
                                    s["lane"](f)))  # fmt: skip
        meta.append(highd_meta(vid, w, h, frames, s["cls"], s["direction"], abs(s["vx"]), int(vid == 2)))
    tracks.sort(key=lambda r: (r["id"], r["frame"]))  # highD's order: by track, then frame
    return tracks, meta


def write_highd_tables(folder: pathlib.Path, tracks: list[dict[str, float]], meta: list[dict[str, object]],
                       prefix: str = "01") -> pathlib.Path:  # fmt: skip
    """XX_tracks.csv and XX_tracksMeta.csv of these rows in ``folder``; the tracks file."""
    folder.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(tracks).to_csv(folder / f"{prefix}_tracks.csv", index=False)
    pd.DataFrame(meta).to_csv(folder / f"{prefix}_tracksMeta.csv", index=False)
    return folder / f"{prefix}_tracks.csv"


def write_highd(folder: pathlib.Path, prefix: str = "01") -> pathlib.Path:
    return write_highd_tables(folder, *highd_rows(), prefix=prefix)


@pytest.fixture(scope="module")
def highd_out(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    root = tmp_path_factory.mktemp("highd")
    import_highd(write_highd(root / "data"), root / "out")
    return root / "out"


def test_highd_corner_to_centre_and_direction_split(highd_out: pathlib.Path) -> None:
    names = sorted(p.name for p in highd_out.glob("*.mcap"))
    assert names == ["highd_01_dir1_0000.mcap", "highd_01_dir2_0000.mcap"]
    lower = read_episode(highd_out / "highd_01_dir2_0000.mcap")
    tracks = lower.tracks
    assert set(tracks["vehicle_id"]) == {1, 2}  # each carriageway in its own episode
    assert np.allclose(np.diff(np.unique(tracks["t"])), 0.05) and tracks["step"].max() == 79  # 25 Hz -> 20 Hz
    truck = tracks[tracks["vehicle_id"] == 1].sort_values("step")
    frame = 1 + truck["step"].to_numpy() * FPS * 0.05  # the source frame each grid step falls on
    # the centre, not the upper-left corner: x0 + vx t (x was written as centre - width / 2)
    assert np.allclose(truck["x"], 20.0 + 30.0 * (frame - 1) / FPS)
    assert np.allclose(np.diff(truck["x"]), 1.5)  # 30 m/s = 1.5 m per 0.05 s step
    # lane 6 is the rightmost of the lower carriageway: lane 0, centred at 0.5 lane widths
    assert (truck["lane"] == 0).all() and np.allclose(truck["y"], 1.875)
    assert np.allclose(truck["length"], 12.0) and np.allclose(truck["width"], 2.5)
    assert np.allclose(truck["speed"], 30.0) and np.allclose(truck["yaw"], 0.0)
    config = lower.metadata["config"]
    assert config["road"] == {"num_lanes": 2, "lane_width_m": 3.75} and config["dt_s"] == 0.05
    assert json.loads(lower.metadata["source_transform"]) == {"x_sign": 1.0, "y_sign": -1.0, "y_offset_m": 27.5}
    assert json.loads(lower.metadata["vehicles"])["1"] == {"source_id": "1", "class": "Truck"}
    assert lower.metadata["source_meta_file"] == "01_tracksMeta.csv"


def test_highd_lane_change_goes_left_in_both_directions(highd_out: pathlib.Path) -> None:
    lower = read_episode(highd_out / "highd_01_dir2_0000.mcap").tracks
    changer = lower[lower["vehicle_id"] == 2].sort_values("step")
    lane = dict(zip(changer["step"], changer["lane"], strict=True))
    assert lane[39] == 0 and lane[40] == 1  # laneId 6 -> 5 at frame 51 = step 40: to the left
    assert changer["y"].iloc[-1] == pytest.approx(5.625)  # lane 1's centre
    assert changer["y"].is_monotonic_increasing and changer["yaw"].max() > 0  # moving left: +y
    # the upper carriageway drives -x in the image: turned half round, it drives +x with its lanes kept
    upper = read_episode(highd_out / "highd_01_dir1_0000.mcap").tracks
    three = upper[upper["vehicle_id"] == 3].sort_values("step")
    assert np.allclose(np.diff(three["x"]), 1.25) and np.allclose(three["yaw"], 0.0)
    assert (three["lane"] == 0).all() and np.allclose(three["y"], 1.875)  # lane id 2 is its rightmost
    four = upper[upper["vehicle_id"] == 4]
    assert (four["lane"] == 1).all() and np.allclose(four["y"], 5.625)
    assert four["step"].min() == math.ceil((30 - 1) / (FPS * 0.05))  # enters at frame 30, not before
    corpus = Corpus.from_tracks(load_tracks(highd_out), WindowOptions(history_steps=10, future_steps=10))
    assert corpus.gather().lane_change.any()


def test_highd_import_is_deterministic(tmp_path: pathlib.Path) -> None:
    tracks = write_highd(tmp_path / "data")
    options = ImportOptions(episode_steps=40)
    calls: list[tuple[int, int]] = []
    one = import_highd(tracks, tmp_path / "one", options, HighdOptions(frame_rate_hz=25.0),
                       progress=lambda done, total: calls.append((done, total)))  # fmt: skip
    assert calls[0] == (0, 200) and calls[-1] == (200, 200)  # 100 frames of each direction
    two = import_highd(tracks, tmp_path / "two", options)
    assert [e.path.name for e in one] == ["highd_01_dir1_0000.mcap", "highd_01_dir1_0001.mcap",
                                          "highd_01_dir2_0000.mcap", "highd_01_dir2_0001.mcap"]  # fmt: skip
    for a, b in zip(one, two, strict=True):
        assert a.path.read_bytes() == b.path.read_bytes()


# -- lc-import ----------------------------------------------------------------------------------------------
def one_line_error(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err
    assert err.startswith("lc-import: error: ") and err.count("\n") == 1, err
    for word in words:
        assert word in err, err
    return err


def test_cli_imports_and_refuses_to_overwrite(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    fcd = write_fcd(tmp_path / "fcd.xml")
    out = tmp_path / "out"
    assert main(["sumo-fcd", str(fcd), "--out", str(out), "--episode-steps", "30", "-q"]) == 0
    assert "imported 3 episodes" in capsys.readouterr().out
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.mcap")}
    assert main(["sumo-fcd", str(fcd), "--out", str(out), "-q"]) == 2
    one_line_error(capsys, "already exist", "--overwrite")
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.mcap")} == before  # untouched
    # --overwrite replaces them; the episodes an earlier cut had and this one has not are removed
    assert main(["sumo-fcd", str(fcd), "--out", str(out), "--overwrite", "-q"]) == 0
    assert sorted(p.name for p in out.glob("*.mcap")) == ["sumo_fcd_0000.mcap"]
    tracks = write_highd(tmp_path / "highd")
    assert main(["highd", str(tracks), "--out", str(out), "-q"]) == 0  # another source in the same folder
    assert len(load_tracks(out)) == 3


@pytest.mark.parametrize(
    ("content", "words"),
    [
        ("", ("empty",)),
        ('<fcd-export><timestep time="0.00"><vehicle id="a" x="1"', ("malformed XML",)),
        ("this is not xml", ("malformed XML",)),
        ('<routes><vehicle id="a"/></routes>', ("not SUMO FCD output", "<routes>")),
        ('<fcd-export><timestep time="0.00"><vehicle id="a" x="1" y="2" angle="90"/></timestep></fcd-export>',
         ("'speed'",)),
        ('<fcd-export><timestep time="0.00"><vehicle id="a" x="one" y="2" angle="90" speed="1"/></timestep>'
         "</fcd-export>", ("vehicle 'a'",)),
        ('<fcd-export><timestep time="0.00"/><timestep time="0.10"/></fcd-export>', ("no vehicle",)),
        ('<fcd-export><timestep time="1.00"/><timestep time="0.50"/></fcd-export>', ("does not increase",)),
    ],
)  # fmt: skip
def test_cli_bad_sumo_input_is_one_line(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str], content: str,
                                         words: tuple[str, ...]) -> None:  # fmt: skip
    path = tmp_path / "bad.xml"
    path.write_text(content)
    assert main(["sumo-fcd", str(path), "--out", str(tmp_path / "out"), "-q"]) == 2
    one_line_error(capsys, *words)
    assert not (tmp_path / "out").exists()  # a refused import leaves nothing, not even the folder it would make


def test_cli_bad_highd_input_is_one_line(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = str(tmp_path / "out")
    assert main(["sumo-fcd", str(tmp_path / "missing.xml"), "--out", out]) == 2
    one_line_error(capsys, "no such file")
    tracks = write_highd(tmp_path / "ok")
    (tmp_path / "ok" / "01_tracksMeta.csv").unlink()
    assert main(["highd", str(tracks), "--out", out]) == 2
    one_line_error(capsys, "01_tracksMeta.csv", "no such file")
    bad = tmp_path / "bad"
    tracks = write_highd(bad)
    frame = pd.read_csv(tracks).drop(columns=["laneId"])
    frame.to_csv(tracks, index=False)
    assert main(["highd", str(tracks), "--out", out]) == 2
    one_line_error(capsys, "no column laneId")
    tracks.write_text("")
    assert main(["highd", str(tracks), "--out", out]) == 2
    one_line_error(capsys, "empty")
    other = write_highd(tmp_path / "other", prefix="02")
    pd.read_csv(other).assign(x="left").to_csv(other, index=False)
    assert main(["highd", str(other), "--out", out]) == 2
    one_line_error(capsys, "column x", "not a number")
    assert main(["highd", str(tmp_path / "x.csv"), "--out", out, "--frame-rate", "0"]) == 2
    one_line_error(capsys, "--frame-rate")
    assert main(["parquet", "x", "--out", out]) == 2
    one_line_error(capsys, "invalid choice")


def test_cli_help_has_examples(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "lc-import sumo-fcd fcd.xml --out" in text and "lc-import highd" in text
    assert main(["highd", "--help"]) == 0
    assert "--meta" in capsys.readouterr().out


# -- the corpus's consumers ---------------------------------------------------------------------------------
def test_view_and_train_predictor_run_on_imported_episodes(highd_out: pathlib.Path, tmp_path: pathlib.Path,
                                                            sumo_out: pathlib.Path) -> None:  # fmt: skip
    from rerun.chunk import RrdReader

    from lccli.predictor import train_predictor_main
    from lccli.view import main as view_main

    rrd = tmp_path / "highd.rrd"
    assert view_main([str(highd_out / "highd_01_dir2_0000.mcap"), "--save", str(rrd)]) == 0
    entities = {chunk.entity_path.lstrip("/") for chunk in RrdReader(rrd).stream()}
    assert {"world/vehicles/boxes", "world/road/edges"} <= entities
    rrd = tmp_path / "sumo.rrd"
    assert view_main([str(sumo_out / "sumo_fcd_0000.mcap"), "--save", str(rrd)]) == 0
    entities = {chunk.entity_path.lstrip("/") for chunk in RrdReader(rrd).stream()}
    assert "world/vehicles/boxes" in entities and "world/road/edges" not in entities  # a network: no road drawn
    data = tmp_path / "corpus"
    import_highd(write_highd(tmp_path / "data"), data, ImportOptions(episode_steps=40))
    out = tmp_path / "predictor"
    assert train_predictor_main(["--data", str(data), "--out", str(out), "--epochs", "1", "--batch-size", "64",
                                 "-q"]) == 0  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["constant_velocity"]["ade"] >= 0 and metrics["model"]["ade"] >= 0


def test_the_root_and_the_home_directory_are_no_output_folder(tmp_path: pathlib.Path, monkeypatch, capsys) -> None:
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    fcd = write_fcd(tmp_path / "fcd.xml")
    for out, why in (("/", "filesystem root"), (str(home), "home directory")):
        assert main(["sumo-fcd", str(fcd), "--out", out, "-q"]) == 2
        err = capsys.readouterr().err
        assert why in err and err.count("\n") == 1
    assert not list(home.iterdir())
