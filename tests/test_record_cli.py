"""lc-record in-process: both scenarios at tiny sizes, deterministic names, overwrite rules, bad input."""

from __future__ import annotations

import hashlib
import pathlib

import numpy as np
import pytest

from lccli.record import record_main, scenario_config
from lcdata import read_episode, replay
from lcdata.record import MAX_USER_SEED
from lcsim import corpus_scenario, paper_scenario

TINY = ["--vehicles", "6", "--steps", "30"]


def names(directory: pathlib.Path) -> list[str]:
    """The episode files in ``directory`` (lc-record also keeps its flags there, in record.json)."""
    return sorted(p.name for p in directory.glob("*.mcap"))


def test_lane_change_and_overwrite(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--episodes", "2", "--seed", "3", "--out", str(tmp_path), *TINY]
    assert record_main(argv) == 0
    out = capsys.readouterr().out
    assert "recorded 2 episodes" in out and "timeout 2" in out and "MB" in out
    assert names(tmp_path) == ["paper_rule_s0000003.mcap", "paper_rule_s0000004.mcap"]
    ep = read_episode(tmp_path / "paper_rule_s0000004.mcap")
    md = ep.metadata
    assert (md["seed"], md["driver"], md["scenario"], md["autopilot"]) == (4, "rule", "paper", False)
    assert md["config"]["traffic"]["num_vehicles"] == 6 and ep.tracks["vehicle_id"].max() == 6
    assert ep.tracks["step"].max() == 30 and len(ep.image_steps) == 3
    assert replay(ep.path).matches
    mtime = (tmp_path / "paper_rule_s0000003.mcap").stat().st_mtime_ns
    sha = hashlib.sha256((tmp_path / "paper_rule_s0000003.mcap").read_bytes()).hexdigest()
    assert record_main(argv) == 0  # the same command: every episode is there, nothing is rewritten
    assert "nothing to record" in capsys.readouterr().out
    assert (tmp_path / "paper_rule_s0000003.mcap").stat().st_mtime_ns == mtime
    assert record_main([*argv[:-1], "31"]) == 2  # other flags: refused, naming the difference
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--overwrite" in err and "steps: 30 there, 31 now" in err
    assert (tmp_path / "paper_rule_s0000003.mcap").stat().st_mtime_ns == mtime
    (tmp_path / "record.json").unlink()  # files there without their flags (an older version's): refused
    assert record_main(argv) == 2
    assert "2 of 2" in capsys.readouterr().err
    assert record_main([*argv, "--overwrite"]) == 0
    # the same command gives the same bytes: the start time derives from the seed
    assert hashlib.sha256((tmp_path / "paper_rule_s0000003.mcap").read_bytes()).hexdigest() == sha
    assert (tmp_path / "paper_rule_s0000003.mcap").stat().st_mtime_ns != mtime


def test_corpus_defaults_to_autopilot(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert record_main(["--scenario", "corpus", "--out", str(tmp_path / "c"), "--vehicles", "4", "--steps", "40"]) == 0
    assert names(tmp_path / "c") == ["corpus_autopilot_s0000000.mcap"]
    ep = read_episode(tmp_path / "c" / "corpus_autopilot_s0000000.mcap")
    assert ep.metadata["autopilot"] is True and ep.metadata["driver"] == "autopilot"
    assert "/camera/bev_semantic" not in ep.topics and len(ep.tracks) == 41 * 5
    assert "recorded 1 episodes" in capsys.readouterr().out


def test_workers_do_not_change_results(tmp_path: pathlib.Path) -> None:
    common = ["--episodes", "2", "--driver", "random", "--no-images", *TINY]
    assert record_main([*common, "--out", str(tmp_path / "w1")]) == 0
    assert record_main([*common, "--out", str(tmp_path / "w2"), "--workers", "2"]) == 0
    assert record_main([*common, "--out", str(tmp_path / "w3"), "--writer", "inline"]) == 0
    assert names(tmp_path / "w1") == names(tmp_path / "w2") == names(tmp_path / "w3")
    for name in names(tmp_path / "w1"):
        a = read_episode(tmp_path / "w1" / name)
        for other in ("w2", "w3"):
            b = read_episode(tmp_path / other / name)
            assert a.tracks.drop(columns="episode").equals(b.tracks.drop(columns="episode"))
            np.testing.assert_array_equal(a.steps["action"], b.steps["action"])


def test_defaults_are_the_papers() -> None:
    assert scenario_config("paper") == paper_scenario()
    assert scenario_config("corpus") == corpus_scenario()
    assert scenario_config("corpus").max_steps == 2000


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--episodes", "0"], "--episodes: must be >= 1"),
        (["--episodes", "two"], "expected an integer"),
        (["--seed", "-1"], "--seed: must be >= 0"),
        (["--workers", "0"], "--workers: must be >= 1"),
        (["--steps", "0"], "--steps: must be >= 1"),
        (["--driver", "fast"], "invalid choice"),
        (["--writer", "fast"], "invalid choice"),
        (["--scenario", "town06"], "unknown scenario"),
        (["--vehicles", "100000"], "does not fit"),
        (["--bogus"], "unrecognized arguments"),
    ],
)
def test_bad_options(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str) -> None:
    assert record_main(["--out", str(tmp_path), *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-record: error:") and message in err and err.count("\n") == 1
    assert "Traceback" not in err and not list(tmp_path.iterdir())


def test_bad_output_directory(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    file = tmp_path / "file"
    file.write_text("x")
    assert record_main(["--out", str(file)]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert record_main(["--out", str(file / "sub")]) == 2
    assert "cannot create output directory" in capsys.readouterr().err
    assert record_main([]) == 2
    assert "--out" in capsys.readouterr().err


def test_help_has_an_example(capsys: pytest.CaptureFixture[str]) -> None:
    assert record_main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "lc-record --scenario paper --episodes" in out and "--workers" in out


def test_resume_sees_an_edited_scenario_file_and_overwrite_leaves_no_mixed_flags(tmp_path, capsys):
    import json

    scenario_file = tmp_path / "s.json"
    scenario_file.write_text(json.dumps({"traffic": {"num_vehicles": 4}}))
    out = tmp_path / "rec"
    common = ["--scenario", str(scenario_file), "--steps", "20", "--no-images", "--out", str(out)]
    assert record_main([*common, "--episodes", "2"]) == 0
    scenario_file.write_text(json.dumps({"traffic": {"num_vehicles": 2}}))
    assert record_main([*common, "--episodes", "4"]) == 2  # the file says something else now
    assert "scenario_config" in capsys.readouterr().err
    assert record_main([*common, "--episodes", "1", "--overwrite"]) == 2  # seed 1 would stay as it was
    assert "other episodes" in capsys.readouterr().err
    assert record_main([*common, "--episodes", "2", "--overwrite"]) == 0
    assert record_main([*common, "--episodes", "3"]) == 0  # resumes, with one set of flags
    assert names(out) == [f"s_rule_s000000{i}.mcap" for i in range(3)]


# -- large values, refusals before any write, the machine's errors ------------------------------------------------
@pytest.mark.parametrize(("argv", "message"), [
    (["--start-time", "9999-12-31T23:59:59Z"], "after 2262-01-01"),
    (["--start-time", "2300-01-01T00:00:00Z"], "after 2262-01-01"),
    (["--seed", "10000000000"], f"--seed: must be <= {MAX_USER_SEED}"),  # no record.json, no lock left behind
    (["--seed", str(MAX_USER_SEED), "--episodes", "2"], f"reaches seed {MAX_USER_SEED + 1}"),
    (["--scenario", "SCENARIO:history_steps = 100000000000000000000"], "history_steps must be at most"),
    (["--scenario", "SCENARIO:[traffic]\nspeed_kmh = 1e308"], "speed_kmh must be at most"),
    (["--scenario", "SCENARIO:time_limit_s = 1e9"], "time_limit_s must be at most"),
    (["--scenario", "SCENARIO:dt_s = 1e-12\ndecision_period_s = 5e-12"], "dt_s must be >="),
    (["--scenario", "SCENARIO:x = " + "[" * 5000 + "]" * 5000], "nested too deeply"),
])
def test_absurd_values_are_refused_before_anything_is_written(tmp_path: pathlib.Path,
                                                              capsys: pytest.CaptureFixture[str],
                                                              argv: list[str], message: str) -> None:
    if argv[1].startswith("SCENARIO:"):
        (tmp_path / "s.toml").write_text(argv[1].removeprefix("SCENARIO:") + "\n")
        argv = [argv[0], str(tmp_path / "s.toml")]
    out = tmp_path / "out"
    assert record_main(["--out", str(out), *TINY, *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-record: error:") and message in err and err.count("\n") == 1
    assert not out.exists()


def test_the_last_start_time_a_file_can_hold_records(tmp_path: pathlib.Path) -> None:
    assert record_main(["--out", str(tmp_path), *TINY, "--no-images", "--start-time", "2261-12-31T00:00:00Z"]) == 0
    assert names(tmp_path) == ["paper_rule_s0000000.mcap"] and not list(tmp_path.glob("*.partial"))


def test_the_root_and_the_home_directory_are_refused(tmp_path: pathlib.Path, monkeypatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("HOME", str(tmp_path))
    for out, why in (("/", "filesystem root"), (str(tmp_path), "home directory"), (f"{tmp_path}/.", "home")):
        assert record_main(["--out", out, *TINY]) == 2
        err = capsys.readouterr().err
        assert why in err and err.count("\n") == 1
    assert not list(tmp_path.iterdir()) and not pathlib.Path("/record.json").exists()


def test_a_second_recording_into_the_same_out_is_refused(tmp_path: pathlib.Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """While one lc-record writes in --out (it holds the folder's lock), another one there is refused in one
    line instead of recording the same files at once."""
    from lccli.record import LOCK_NAME
    from lckit.fileio import folder_lock

    with folder_lock(tmp_path, "lc-record", LOCK_NAME):  # what the first process holds while it records
        assert record_main(["--out", str(tmp_path), *TINY]) == 2
    err = capsys.readouterr().err
    assert "another lc-record" in err and "is writing in" in err and err.count("\n") == 1
    assert names(tmp_path) == [] and not (tmp_path / "record.json").exists()
    assert record_main(["--out", str(tmp_path), *TINY]) == 0  # the lock is gone with its holder


def test_a_full_disk_is_one_line(tmp_path: pathlib.Path) -> None:
    """A disk that fills up while recording (a file-size limit: writes past it fail like ENOSPC) ends in one
    line, not a traceback; rerunning the same command on room records the missing episode."""
    import resource
    import subprocess
    import sys

    argv = ["--out", str(tmp_path / "out"), *TINY]
    code = f"import sys; sys.argv[0] = 'lc-record'; from lccli.record import record_main; sys.exit(record_main({argv!r}))"

    def small_disk() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (16 << 10, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, preexec_fn=small_disk,
                          timeout=300)
    err = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert err[-1].startswith("lc-record: error: recording into") and "File too large" in err[-1]
    assert record_main(argv) == 0 and names(tmp_path / "out") == ["paper_rule_s0000000.mcap"]
