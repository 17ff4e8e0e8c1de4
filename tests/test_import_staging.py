"""An import's staging folder: removed on Ctrl-C and SIGTERM, removed (not resumed) by the next import of the
same source after a SIGKILL, left alone while its import runs; the episodes appear under their names all
together, never half-written."""

from __future__ import annotations

import fcntl
import logging
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

from lcdata.importers import ImportOptions, import_sumo_fcd
from lcdata.importers.episodes import EpisodeFiles, _signals_held
from tests.test_importers import write_fcd

ROOT = pathlib.Path(__file__).resolve().parent.parent
STAGING = ".sumo_fcd.import-staging"


def big_fcd(path: pathlib.Path, timesteps: int = 12_000) -> pathlib.Path:
    """A long FCD file (two vehicles at 0.1 s): seconds of work for an import, so that a signal finds it busy."""
    rows = ["<fcd-export>"]
    for i in range(timesteps):
        t = i * 0.1
        rows.append(f'<timestep time="{t:.1f}"><vehicle id="a" x="{10 + 20 * t:.2f}" y="-1.6" angle="90" '
                    f'speed="20" lane="e0_0"/><vehicle id="b" x="{30 + 22 * t:.2f}" y="-4.8" angle="90" speed="22" '
                    'lane="e0_1"/></timestep>')  # fmt: skip
    rows.append("</fcd-export>")
    path.write_text("\n".join(rows))
    return path


def start_import(fcd: pathlib.Path, out: pathlib.Path) -> subprocess.Popen[str]:
    """``lc-import`` in a process of its own, as a user starts it; returns once it has staged an episode."""
    proc = subprocess.Popen([sys.executable, "-c", "from lccli.importer import main; raise SystemExit(main())",
                             "sumo-fcd", str(fcd), "--out", str(out), "--episode-steps", "100", "-q"],
                            cwd=ROOT, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)  # fmt: skip
    deadline = time.monotonic() + 300
    while not list((out / STAGING).glob("*.staged")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "no episode staged in 300 s"
        time.sleep(0.02)
    return proc


def test_sigterm_removes_the_staging_folder_and_writes_nothing(tmp_path: pathlib.Path) -> None:
    out = tmp_path / "out"
    proc = start_import(big_fcd(tmp_path / "fcd.xml"), out)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip() == "lc-import: SIGTERM; nothing was written", err
    assert not out.exists()  # the folder it made is gone too: it held nothing else


def test_after_sigkill_the_next_import_removes_the_stale_staging_folder(tmp_path: pathlib.Path, caplog) -> None:
    out = tmp_path / "out"
    fcd = big_fcd(tmp_path / "fcd.xml")
    proc = start_import(fcd, out)
    proc.kill()
    proc.communicate(timeout=120)
    assert (out / STAGING).is_dir() and not list(out.glob("*.mcap"))  # killed outright: staged files, none published
    (tmp_path / "short").mkdir()
    short = write_fcd(tmp_path / "short" / "fcd.xml")  # the same source name, a shorter recording
    with caplog.at_level(logging.WARNING, logger="lcdata.importers.episodes"):
        written = import_sumo_fcd(short, out)
    assert "not resumed" in caplog.text and STAGING in caplog.text
    assert sorted(p.name for p in out.iterdir()) == [e.path.name for e in written] == ["sumo_fcd_0000.mcap"]


def test_a_staging_folder_in_use_is_left_alone(tmp_path: pathlib.Path) -> None:
    fcd = write_fcd(tmp_path / "fcd.xml")
    staging = tmp_path / "out" / STAGING
    staging.mkdir(parents=True)
    (staging / "sumo_fcd_0000.mcap.staged").write_bytes(b"being written")
    with open(staging / EpisodeFiles.LOCK_NAME, "a+") as held:  # what a running import holds
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(ValueError, match="another import of this source"):
            import_sumo_fcd(fcd, tmp_path / "out")
    assert (staging / "sumo_fcd_0000.mcap.staged").read_bytes() == b"being written"
    assert not list((tmp_path / "out").glob("*.mcap"))


def test_ctrl_c_in_an_import_leaves_the_output_as_it_was(tmp_path: pathlib.Path) -> None:
    fcd = write_fcd(tmp_path / "fcd.xml")
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("kept")

    def interrupt(done: int, total: int) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        import_sumo_fcd(fcd, out, ImportOptions(episode_steps=20, min_episode_steps=5), progress=interrupt)
    assert [p.name for p in out.iterdir()] == ["mine.txt"]


def test_signals_wait_while_the_episodes_move_into_place() -> None:
    """A signal that arrives while the files move is delivered after the last one is in place."""
    moved = False
    with pytest.raises(KeyboardInterrupt):
        with _signals_held():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # where an unheld SIGINT would have raised
            moved = True
    assert moved


def test_a_stale_staging_folder_whose_lock_is_a_link_is_refused_and_the_target_kept(tmp_path: pathlib.Path) -> None:
    fcd = write_fcd(tmp_path / "fcd.xml")
    staging = tmp_path / "out" / STAGING
    staging.mkdir(parents=True)
    target = tmp_path / "thesis.tex"
    target.write_text("years of work")
    (staging / EpisodeFiles.LOCK_NAME).symlink_to(target)
    with pytest.raises(ValueError, match="is a link, not a lock an import made"):
        import_sumo_fcd(fcd, tmp_path / "out")
    assert target.read_text() == "years of work" and staging.is_dir()
