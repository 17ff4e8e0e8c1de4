"""Each command against a symbolic link planted in its output folder, a path read back from one of its files
that leads elsewhere, a record edited by hand, a name made of a user's values, a user's callable that fails,
and Ctrl-C: the link's target is never written or deleted, and the command refuses in one line (or writes
safely)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lccli.calibrate import main as calibrate_main
from lccli.record import record_main
from lcdata.record import episode_filename
from lckit.fileio import UnsafePathError

from .test_bench import tiny_suite  # noqa: F401  (a fixture)

TINY_TRAIN = ["--obs", "pure", "--scenario", "tiny", "--timesteps", "64", "--set", "n_envs=2", "--set",
              "n_steps=32", "--set", "eval_episodes=0", "-q"]  # fmt: skip


@pytest.fixture
def victim(tmp_path: Path) -> Path:
    """A folder elsewhere with a file that must stay as it is."""
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    (folder / "thesis.tex").write_text("years of work")
    return folder / "thesis.tex"


def untouched(victim: Path) -> bool:
    return victim.read_text() == "years of work" and sorted(p.name for p in victim.parent.iterdir()) == ["thesis.tex"]


def one_line(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert all(w in err for w in words), err
    return err


# ------------------------------------------------------------------------------------------- lc-calibrate
def test_lc_calibrate_refuses_a_partial_that_is_a_link(tmp_path: Path, victim: Path, capsys) -> None:
    out = tmp_path / "road.toml"
    (tmp_path / "road.toml.partial").symlink_to(victim)
    assert calibrate_main([str(tmp_path / "data"), "--out", str(out), "-q"]) == 2
    one_line(capsys, "lc-calibrate: error:", "symbolic link")
    (tmp_path / "road.toml.partial").unlink()
    out.symlink_to(victim)  # nor the scenario file itself, --overwrite or not
    assert calibrate_main([str(tmp_path / "data"), "--out", str(out), "--overwrite", "-q"]) == 2
    one_line(capsys, "symbolic link")
    assert untouched(victim)


# ---------------------------------------------------------------------------------------------- lc-record
def test_lc_record_refuses_a_partial_or_a_lock_that_is_a_link(tmp_path: Path, victim: Path, capsys) -> None:
    out = tmp_path / "rec"
    out.mkdir()
    rec = ["--vehicles", "8", "--steps", "40", "--no-images", "--out", str(out)]
    partial = out / (episode_filename("paper", "rule", 0) + ".partial")
    for link in (partial, out / ".lc-record.lock", out / "record.json"):
        link.symlink_to(victim)
        assert record_main(rec) == 2
        one_line(capsys, "lc-record: error:", "symbolic link")
        link.unlink()
    assert untouched(victim) and sorted(p.name for p in out.iterdir()) == []


def test_an_episode_writer_never_writes_through_a_link(tmp_path: Path, victim: Path) -> None:
    from lcdata.record import record_episode
    from lcsim.config import tiny_scenario

    (tmp_path / "ep.mcap.partial").symlink_to(victim)
    with pytest.raises(UnsafePathError):
        record_episode(tiny_scenario(), 0, "rule", tmp_path / "ep.mcap", writer="inline")
    assert untouched(victim)


