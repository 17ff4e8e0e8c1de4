"""Traffic statistics from tracks (lcsim.stats) on drawn tracks with known answers, and lc-calibrate end to end on a
highD-layout recording the test makes from the simulator's own traffic with known parameters."""

from __future__ import annotations

import contextlib
import io
import json
import math
import pathlib

import numpy as np
import pytest

from lccli.calibrate import main
from lccli.importer import main as import_main
from lcsim.config import RoadConfig, ScenarioConfig, TrafficConfig
from lcsim.registry import scenario
from lcsim.stats import (
    CORE_SHARE,
    TrackArrays,
    sampling_intervals,
    simulate_tracks,
    summarise,
    traffic_samples,
)
from tests.test_importers import highd_meta, highd_row, highd_rows, write_highd_tables

DT = 0.05
LANE_W = 3.5
CENTRES = np.array([0.5, 1.5, 2.5]) * LANE_W


def min_jerk(tau: np.ndarray) -> np.ndarray:
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10 - 15 * tau + 6 * tau**2)


def drawn(profile, seconds: float = 20.0, start_s: float = 5.0, duration_s: float = 4.0, gap_m: float = 30.0,
          speed: float = 20.0) -> TrackArrays:  # fmt: skip
    """Vehicle 0 drives lane 0 and changes to lane 1 from ``start_s`` over ``duration_s`` (``profile`` of the time
    share, 0 -> 1); vehicle 1 follows it in lane 0, ``gap_m`` centre to centre behind; both at ``speed``."""
    t = np.arange(round(seconds / DT) + 1) * DT
    x = np.stack([100.0 + speed * t, 100.0 - gap_m + speed * t], axis=1)
    y = np.stack([CENTRES[0] + LANE_W * profile((t - start_s) / duration_s), np.full(len(t), CENTRES[0])], axis=1)
    lane = np.floor(y / LANE_W).astype(np.int64)
    full = np.ones(x.shape, dtype=bool)
    return TrackArrays(DT, x, y, np.full(x.shape, speed), np.zeros(x.shape), lane, full, np.array([5.0, 5.0]), CENTRES)


def test_a_lane_change_its_duration_rate_time_gaps_and_offsets():
    track = drawn(min_jerk)
    samples = traffic_samples([track])
    stats = summarise(samples)
    assert stats["lane_changes"] == 1 and samples.changes.tolist() == [1, 0]
    km = 2 * 20.0 * 20.0 / 1000.0  # two vehicles, 20 s at 20 m/s
    assert stats["vehicle_km"] == pytest.approx(km)
    assert stats["lane_changes_per_vehicle_km"] == pytest.approx(1 / km)
    assert stats["lane_change_duration_mean_s"] == pytest.approx(4.0, abs=0.01)  # the minimum-jerk duration itself
    # the follower's time gap while the leader is in its lane: (30 m - 5 m) / 20 m/s, bumper to bumper
    # (until the leader's centre crosses the marking at 7 s: samples at 0, 0.5, ..., 6.5 s)
    assert np.allclose(samples.time_gap, 1.25) and len(samples.time_gap) == 14
    # lane keeping only: exactly on the centre; the change (5 s to 9 s) and 0.5 s either side are not lane keeping
    assert np.all(samples.offset == 0.0)
    assert len(samples.offset) == 2 * 41 - 11  # 41 samples each; the changer's from 4.5 s to 9.5 s left out
    # free driving needs 100 m of road seen ahead: neither vehicle has it here
    assert len(samples.free_speed) == 0


def test_a_linear_lane_change_measures_its_core_and_a_cut_one_has_no_duration():
    linear = summarise(traffic_samples([drawn(lambda u: np.clip(u, 0.0, 1.0))]))
    assert linear["lane_change_duration_mean_s"] == pytest.approx(0.8 * 4.0 / CORE_SHARE, abs=0.01)
    cut = traffic_samples([drawn(min_jerk, seconds=20.0, start_s=17.5)])  # the track ends before 90%
    stats = summarise(cut)
    assert stats["lane_changes"] == 1 and len(cut.duration) == 0 and math.isnan(stats["lane_change_duration_mean_s"])
    assert np.abs(cut.offset).max() == 0.0  # the unfinished change is no lane keeping
    early = summarise(traffic_samples([drawn(min_jerk, start_s=1.0)], warmup_s=5.0))  # started in the warm-up
    assert early["lane_changes"] == 0 and early["vehicle_km"] == pytest.approx(2 * 15 * 20 / 1000)


def test_sampling_intervals_resample_vehicles():
    rng = np.random.default_rng(0)
    tracks = []
    for _ in range(3):
        track = drawn(min_jerk, speed=float(rng.uniform(15, 25)))
        tracks.append(track)
    samples = traffic_samples(tracks)
    stats, iv = summarise(samples), sampling_intervals(samples, reps=100, seed=1)
    lo, hi = iv["speed_mean_kmh"]
    assert lo < stats["speed_mean_kmh"] < hi and hi - lo > 1.0  # six vehicles at three speeds: a wide interval
    assert json.dumps(iv) == json.dumps(sampling_intervals(samples, reps=100, seed=1))  # (NaN where nothing to measure)
    weights = np.zeros(samples.vehicles)
    weights[[0, 1]] = 1.0  # the first episode's vehicles alone
    assert summarise(samples, weights)["speed_mean_kmh"] == pytest.approx(summarise(traffic_samples(tracks[:1]))[
        "speed_mean_kmh"])  # fmt: skip


# -- a highD-layout recording of known traffic -------------------------------------------------------------------
TRUTH = ScenarioConfig(
    road=RoadConfig(num_lanes=3, lane_width_m=3.75), render_image=False,
    traffic=TrafficConfig(num_vehicles=45, speed_kmh=90.0, speed_spread_kmh=8.0, idm_time_headway_s=1.4,
                          lane_change_duration_s=4.0, min_spawn_gap_m=25.0, random_lane_change_rate_per_min=1.0),
)  # fmt: skip
WINDOW_M = (900.0, 1400.0)
"""The stretch of road the 'drone' sees."""


def write_simulated_highd(folder: pathlib.Path, seconds: float = 40.0, seed: int = 3) -> pathlib.Path:
    """``TRUTH``'s traffic seen over ``WINDOW_M`` as highD's lower carriageway (driving +x, image y down, lane ids
    4..6 from the top, 6 the rightmost), one frame per simulation step (20 Hz)."""
    [track], _ = simulate_tracks(TRUTH, 1, seconds, seed)
    tracks, meta = [], []
    for v in range(track.x.shape[1]):
        frames = [k for k in range(len(track.x)) if WINDOW_M[0] <= track.x[k, v] <= WINDOW_M[1]]
        if len(frames) < 2:
            continue
        width = 1.99 if v == 0 else TRUTH.traffic.width_m
        for k in frames:
            tracks.append(highd_row(k + 1, v + 1, track.x[k, v] - WINDOW_M[0] + 10.0, 30.0 - track.y[k, v],
                                    float(track.length[v]), width, float(track.speed[k, v]), 0.0,
                                    6 - int(track.lane[k, v]), ax=float(track.accel[k, v])))  # fmt: skip
        meta.append(highd_meta(v + 1, float(track.length[v]), width, [f + 1 for f in frames], "Car", 2,
                               float(track.speed[frames, v].mean()), 0))  # fmt: skip
    return write_highd_tables(folder, tracks, meta, prefix="07")


SMALL = ["--iterations", "4", "--episodes", "4", "--seconds", "20", "--report-episodes", "4", "--bootstrap", "20"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    root = tmp_path_factory.mktemp("highd-known")
    csv = write_simulated_highd(root / "highd")
    assert import_main(["highd", str(csv), "--out", str(root / "data"), "--frame-rate", "20", "-q"]) == 0
    return root / "data"


@pytest.fixture(scope="module")
def calibrated(recorded: pathlib.Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[pathlib.Path, str]:
    out = tmp_path_factory.mktemp("calibrated")
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        rc = main([str(recorded), "--out", str(out / "known.toml"), "--json", str(out / "known.json"), "-q", *SMALL])
    assert rc == 0
    return out, text.getvalue()


def test_calibration_recovers_the_known_traffic(calibrated: tuple[pathlib.Path, str]):
    out, printed = calibrated
    fitted = scenario(out / "known.toml")  # the file lc-eval / lc-record take as --scenario
    assert fitted.road.num_lanes == 3 and fitted.road.lane_width_m == pytest.approx(3.75, abs=0.05)
    t = fitted.traffic
    assert t.speed_kmh == pytest.approx(TRUTH.traffic.speed_kmh, rel=0.15)
    assert t.lane_change_duration_s == pytest.approx(TRUTH.traffic.lane_change_duration_s, rel=0.25)
    assert fitted.ego == ScenarioConfig().ego and fitted.reward == ScenarioConfig().reward  # the base's (paper)
    report = json.loads((out / "known.json").read_text())
    assert report["distance"]["calibrated"] < report["distance"]["default"] / 10
    assert sum(report["within"]["calibrated"].values()) > sum(report["within"]["default"].values())
    assert len(report["history"]) <= 4 and report["recorded_road"]["num_lanes"] == 3
    # the table: recorded, default and calibrated side by side, each compared statistic a row
    assert "| statistic | recorded [95% interval] |" in printed and printed.count("| speed, mean (km/h) |") == 1
    assert "calibrated: " in printed and "default: " in printed


def test_calibration_is_a_function_of_its_inputs(recorded: pathlib.Path, calibrated: tuple[pathlib.Path, str],
                                                 tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]):  # fmt: skip
    out, _ = calibrated
    assert main([str(recorded), "--out", str(tmp_path / "again.toml"), "--json", str(tmp_path / "again.json"), "-q",
                 *SMALL]) == 0  # fmt: skip
    assert (tmp_path / "again.toml").read_bytes() == (out / "known.toml").read_bytes()
    assert json.loads((tmp_path / "again.json").read_text()) == json.loads((out / "known.json").read_text())
    capsys.readouterr()
    assert main([str(recorded), "--out", str(tmp_path / "other.toml"), "--seed", "1", "-q", *SMALL]) == 0
    assert (tmp_path / "other.toml").read_bytes() != (out / "known.toml").read_bytes()  # another seed, other runs


def one_line_error(capsys: pytest.CaptureFixture[str], *words: str) -> None:
    err = capsys.readouterr().err
    assert err.startswith("lc-calibrate: error: ") and err.count("\n") == 1, err
    for word in words:
        assert word in err, err


def test_bad_input_is_one_line_and_writes_nothing(recorded: pathlib.Path, tmp_path: pathlib.Path,
                                                  capsys: pytest.CaptureFixture[str]):  # fmt: skip
    out = tmp_path / "s.toml"
    assert main([str(tmp_path / "missing"), "--out", str(out), "-q"]) == 2
    one_line_error(capsys, "does not exist")
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty"), "--out", str(out), "-q"]) == 2
    one_line_error(capsys, "no .mcap episode files")
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    assert main([str(tmp_path / "junk.mcap"), "--out", str(out), "-q"]) == 2
    one_line_error(capsys, "junk.mcap")
    assert main([str(recorded), "--out", str(tmp_path / "s.yaml"), "-q"]) == 2
    one_line_error(capsys, ".toml or .json")
    assert main([str(recorded), "--out", str(out), "--iterations", "0", "-q"]) == 2
    one_line_error(capsys, "--iterations")
    assert main([str(recorded), "--out", str(out), "--base", "nowhere", "-q"]) == 2
    one_line_error(capsys, "unknown scenario")
    assert main([str(recorded), "--out", str(out), "--seconds", "8", "-q"]) == 2
    one_line_error(capsys, "--seconds")
    out.write_text("# mine\n")
    assert main([str(recorded), "--out", str(out), "-q"]) == 2
    one_line_error(capsys, "already exists", "--overwrite")
    assert out.read_text() == "# mine\n"
    # a recording where each carriageway holds one vehicle: no lane to change to, no leader to follow
    tracks, meta = highd_rows()
    lone = write_highd_tables(tmp_path / "lone", [r for r in tracks if r["id"] in (1, 3)],
                              [m for m in meta if m["id"] in (1, 3)])  # fmt: skip
    assert import_main(["highd", str(lone), "--out", str(tmp_path / "lone-data"), "-q"]) == 0
    assert main([str(tmp_path / "lone-data"), "--out", str(tmp_path / "lone.toml"), *SMALL, "-q"]) == 2
    one_line_error(capsys, "one lane")
    assert not (tmp_path / "lone.toml").exists() and not (tmp_path / "s.yaml").exists()


def test_help_has_an_example(capsys: pytest.CaptureFixture[str]):
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "lc-calibrate runs/sumo/corpus --out scenarios/sumo.toml" in text and "--iterations" in text


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--bootstrap", "100000000"], ("--bootstrap", "must be <= 10000")),
        (["--episodes", "1000000"], ("--episodes", "must be <= 1024")),
        (["--report-episodes", "1000000"], ("--report-episodes", "must be <= 1024")),
        (["--iterations", "100000000"], ("--iterations", "must be <=")),
        (["--episodes", "1000", "--seconds", "3000"], ("1000 episodes x 3000 s", "GiB of tracks", "more than 4 GiB")),
        (["--seconds", "1e9"], ("GiB of tracks",)),
    ],
)  # fmt: skip
def test_sizes_are_bounded_before_anything_is_simulated(recorded: pathlib.Path, tmp_path: pathlib.Path,
                                                        capsys: pytest.CaptureFixture[str], argv, words) -> None:
    """The bootstrap and the simulated episodes have stated caps, and an evaluation's tracks must fit in
    ``MAX_TRACK_BYTES`` (refused after reading the recording, before the bootstrap)."""
    assert main([str(recorded), "--out", str(tmp_path / "s.toml"), "-q", *argv]) == 2
    one_line_error(capsys, *words)
    assert not list(tmp_path.iterdir())


def test_the_library_bounds_what_it_simulates_and_draws() -> None:
    from lcsim.calibrate import CalibrationOptions
    from lcsim.stats import MAX_BOOTSTRAP_DRAWS, TrafficSamples

    for bad in ({"episodes": 10**6}, {"report_episodes": 0}, {"iterations": 10**8}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            CalibrationOptions(**bad)
    with pytest.raises(ValueError, match="GiB of tracks"):  # before the simulator allocates anything
        simulate_tracks(TRUTH, 10**6, 75.0)
    empty = TrafficSamples(**{f: np.zeros(0) for f in TrafficSamples.__dataclass_fields__})
    with pytest.raises(ValueError, match=f"1 to {MAX_BOOTSTRAP_DRAWS} draws"):
        sampling_intervals(empty, reps=10**8)
