"""tools/bench_bases.py: the analytic bases on a tiny recorded corpus, and its one-line errors."""

from __future__ import annotations

import pathlib
import sys

import numpy as np
import pytest

TOOLS = pathlib.Path(__file__).resolve().parent.parent / "tools"
sys.path.insert(0, str(TOOLS))

import bench_bases  # noqa: E402

from lccli.record import record_main  # noqa: E402


@pytest.fixture(scope="module")
def corpus_dir(tmp_path_factory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("corpus")
    assert record_main(["--scenario", "corpus", "--episodes", "3", "--seed", "5", "--vehicles", "6", "--steps", "120",
                        "--out", str(out)]) == 0  # fmt: skip
    return out


def test_state_fits_are_exact_on_their_own_motion_models() -> None:
    k = np.arange(-19, 61, dtype=np.float64)[:, None]
    track = (np.array([2.0, -1.0]) + k * np.array([0.3, 0.02]) + 0.5 * k**2 * np.array([0.004, -0.001]))[None]
    pos, vel, accel = bench_bases.state_fit(track[:, :20], 20, 2)
    np.testing.assert_allclose(bench_bases.extrapolate(pos, vel, accel, 60, None), track[:, 20:], atol=1e-9)
    line = track - 0.5 * k**2 * np.array([0.004, -0.001])
    pos, vel, accel = bench_bases.state_fit(line[:, :20], 10, 1)
    assert not accel.any()
    np.testing.assert_allclose(bench_bases.extrapolate(pos, vel, accel, 60, 5.0), line[:, 20:], atol=1e-9)


def test_table_on_validation_episodes_and_one_line_errors(corpus_dir: pathlib.Path, capsys, tmp_path) -> None:
    assert bench_bases.main(["--data", f"lcsim={corpus_dir}", "--data", f"val={corpus_dir}:val", "--max-windows", "300"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ") and "---" not in line]
    assert len(rows) == 1 + len(bench_bases.candidates())
    fv = next(line for line in rows if line.startswith("| FV, 10 steps |"))
    assert fv.count("(+0.0% / +0.0%)") == 2  # the reference of every relative figure
    for argv, words in (
        (["--data", str(corpus_dir)], "NAME=FOLDER"),
        (["--data", f"x={tmp_path}"], "not a folder of .mcap"),
    ):
        assert bench_bases.main(argv) == 2
        last = capsys.readouterr().err.splitlines()[-1]  # after any progress line
        assert last.startswith("bench_bases.py: error:") and words in last, last
