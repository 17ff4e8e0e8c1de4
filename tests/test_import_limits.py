"""Importers and hostile input: values that are not finite or not plausible are refused by name (the file, the
line or data row, the field), and what an import writes is bounded by what it reads (time span, steps,
vehicle-rows), with the stated limits that --max-duration and --max-steps raise."""

from __future__ import annotations

import pathlib

import pytest

from lccli.importer import main
from lcdata.importers import ImportOptions, import_highd, import_sumo_fcd
from lcdata.importers.limits import DEFAULT_MAX_DURATION_S, MAX_LANE_INDEX, STEPS_PER_SAMPLE
from tests.test_importers import highd_rows, write_fcd, write_highd_tables


def one_line_error(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err
    assert err.startswith("lc-import: error: ") and err.count("\n") == 1, err
    for word in words:
        assert word in err, err
    return err


@pytest.fixture(scope="module")
def fcd_text(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The test SUMO file (41 timesteps of 0.1 s; ``car.a`` first on line 4, at x 10, speed 20, lane e0_0)."""
    return write_fcd(tmp_path_factory.mktemp("fcd") / "fcd.xml").read_text()


def sumo(tmp_path: pathlib.Path, text: str, *flags: str) -> int:
    path = tmp_path / "bad.xml"
    path.write_text(text)
    return main(["sumo-fcd", str(path), "--out", str(tmp_path / "out"), "-q", *flags])


CAR_A = 'x="10.00" y="-11.20" angle="90.00" type="DEFAULT_VEHTYPE" speed="20.00"'


@pytest.mark.parametrize(
    ("old", "new", "words"),
    [
        ('time="2.00"', 'time="inf"', ("line 153", "time 'inf'", "not a finite number")),
        ('time="2.00"', 'time="nan"', ("line 153", "time 'nan'", "not a finite number")),
        ('time="4.00"', 'time="1e12"', ("line 304", "time '1e12'", "times an import accepts")),
        ('time="0.10"', 'time="0.0000001"', ("line 10", "does not increase")),
        (CAR_A, CAR_A.replace('x="10.00"', 'x="1e308"'), ("line 4", "'car.a'", "x '1e308'", "positions")),
        (CAR_A, CAR_A.replace('x="10.00"', 'x="-inf"'), ("line 4", "x '-inf'", "not a finite number")),
        (CAR_A, CAR_A.replace('speed="20.00"', 'speed="-5"'), ("line 4", "speed '-5'", "speeds")),
        (CAR_A, CAR_A.replace('speed="20.00"', 'speed="1e300"'), ("line 4", "speed '1e300'", "speeds")),
        (CAR_A, CAR_A + ' acceleration="inf"', ("line 4", "acceleration 'inf'", "not a finite number")),
        (CAR_A, CAR_A + ' acceleration="-2e4"', ("line 4", "acceleration '-2e4'", "accelerations")),
        (CAR_A, CAR_A + ' length="-4"', ("line 4", "length '-4'", "vehicle lengths")),
        (CAR_A, CAR_A + ' width="0"', ("line 4", "width '0'", "vehicle widths")),
        (CAR_A, CAR_A.replace('angle="90.00"', 'angle="1e300"'), ("line 4", "angle '1e300'", "headings")),
        (CAR_A, CAR_A.replace('x="10.00"', 'x="ten"'), ("line 4", "x 'ten' is not a number")),
        ('lane="e0_0"', 'lane="e0_999999999"', ("line 4", "'e0_999999999'", "lane indices")),
        ('lane="e0_0"', 'lane="e0_' + "9" * 5000 + '"', ("line 4", "more than any road has")),
    ],
)  # fmt: skip
def test_sumo_values_are_refused_by_name_and_line(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str],
                                                  fcd_text: str, old: str, new: str, words: tuple[str, ...]) -> None:
    assert old in fcd_text
    assert sumo(tmp_path, fcd_text.replace(old, new, 1)) == 2
    one_line_error(capsys, "bad.xml", *words)
    assert not (tmp_path / "out").exists()  # nothing written, not even the folder


def test_a_speed_change_no_vehicle_makes_is_refused_as_an_acceleration(tmp_path, capsys, fcd_text) -> None:
    """Without an acceleration attribute it is the change of speed over the step: 140 -> 20 m/s in 0.1 s."""
    assert sumo(tmp_path, fcd_text.replace('speed="20.00"', 'speed="140.00"', 3)) == 2
    one_line_error(capsys, "line 24", "'car.a'", "from 140 to 20 m/s", "-1200 m/s^2", "accelerations")


def test_a_gap_in_the_source_cannot_write_without_end(tmp_path: pathlib.Path, capsys, fcd_text: str) -> None:
    # one timestep a billion seconds on: more than a day of source time
    assert sumo(tmp_path, fcd_text.replace('time="4.00"', 'time="1000000000"')) == 2
    one_line_error(capsys, "line 304", f"({DEFAULT_MAX_DURATION_S:g} s; --max-duration raises it)")
    # 5000 s on: within a day, but 100,000 steps for 41 source samples
    assert sumo(tmp_path, fcd_text.replace('time="4.00"', 'time="5000"')) == 2
    one_line_error(capsys, "line 304", "100000 steps", f"at most {41 * STEPS_PER_SAMPLE} steps", "--max-steps")
    assert sumo(tmp_path, fcd_text, "--max-duration", "2") == 2  # the file spans 4 s
    one_line_error(capsys, "time 2.1 s", "(2 s; --max-duration")
    assert sumo(tmp_path, fcd_text, "--max-steps", "50") == 2  # it needs 80 steps
    one_line_error(capsys, "at most 50 steps (--max-steps)")
    assert not (tmp_path / "out").exists()
    # the limit is the user's to raise: a gap of 200 s bridged with --max-steps
    assert sumo(tmp_path, fcd_text.replace('time="4.00"', 'time="200"'), "--max-steps", "5000") == 0
    assert "4000 steps" in capsys.readouterr().out


def test_vehicle_rows_are_bounded_by_the_rows_read(tmp_path: pathlib.Path) -> None:
    """Many empty timesteps buy steps, not vehicle-rows: a vehicle held over a long gap is refused."""
    steps = [f'<timestep time="{t}"/>' for t in range(100)]
    one = '<timestep time="{t}"><vehicle id="a" x="0" y="0" angle="90" speed="0"/></timestep>'
    text = "<fcd-export>" + "".join(steps) + one.format(t=100) + one.format(t=300) + "</fcd-export>"
    (tmp_path / "gap.xml").write_text(text)  # 102 samples allow 102,000 steps; 200 s are 4000 rows for 2 read
    with pytest.raises(ValueError, match="vehicle-steps per vehicle-step read"):
        import_sumo_fcd(tmp_path / "gap.xml", tmp_path / "out")
    written = import_sumo_fcd(tmp_path / "gap.xml", tmp_path / "out", ImportOptions(max_steps=10_000))
    assert sum(e.rows for e in written) == 4000  # two episodes of 2000 steps (the last step alone is too short)


@pytest.mark.parametrize(
    ("flag", "value", "words"),
    [
        ("--dt", "1e-6", ("--dt", "must be in [0.001, 1]")),
        ("--dt", "nan", ("--dt", "must be in")),
        ("--dt", "5", ("--dt", "must be in")),
        ("--episode-steps", "1000000000000", ("--episode-steps", "must be <=")),
        ("--max-duration", "inf", ("--max-duration", "must be in")),
        ("--max-steps", "0", ("--max-steps", "must be >= 1")),
    ],
)  # fmt: skip
def test_options_are_bounded(tmp_path: pathlib.Path, capsys, fcd_text: str, flag: str, value: str,
                             words: tuple[str, ...]) -> None:  # fmt: skip
    assert sumo(tmp_path, fcd_text, flag, value) == 2
    one_line_error(capsys, *words)


def test_import_options_are_checked_in_the_library() -> None:
    for bad in ({"dt_s": 1e-6}, {"dt_s": float("nan")}, {"episode_steps": 10**12}, {"max_duration_s": 0.0},
                {"max_duration_s": float("inf")}, {"max_steps": 0}, {"max_steps": 1.5}):  # fmt: skip
        with pytest.raises(ValueError, match=next(iter(bad))):
            ImportOptions(**bad)


# -- highD ----------------------------------------------------------------------------------------------------
def highd(tmp_path: pathlib.Path, change=None, meta_change=None, *flags: str) -> int:
    tracks, meta = highd_rows()
    if change is not None:
        change(tracks)
    if meta_change is not None:
        meta_change(meta)
    path = write_highd_tables(tmp_path / "data", tracks, meta)
    return main(["highd", str(path), "--out", str(tmp_path / "out"), "-q", *flags])


def _vehicle(vid: int, **values: float):
    def change(rows: list[dict[str, float]]) -> None:
        for row in rows:
            if row["id"] == vid:
                row.update(values)

    return change


@pytest.mark.parametrize(
    ("change", "meta_change", "words"),
    [
        (lambda r: r[5].update(frame=1e13), None, ("data row 6", "frame 10000000000000", "times an import accepts")),
        (lambda r: r[5].update(frame=2_500_000), None, ("data row 6", "frame 2500000", "more than an import may span")),
        (lambda r: r[5].update(frame=5.5), None, ("data row 6", "frame 5.5 is not a whole number")),
        (lambda r: r[5].update(frame=-3), None, ("data row 6", "frame -3", "frame numbers")),
        (lambda r: r[5].update(laneId=999_999_999), None, ("data row 6", "laneId 999,999,999", "lane ids")),
        (lambda r: r[5].update(laneId=40), None, ("data row 6", "laneId 40", f"({MAX_LANE_INDEX + 1} lanes)")),
        (lambda r: r[5].update(laneId=2.5), None, ("data row 6", "laneId 2.5 is not a whole number")),
        (lambda r: r[5].update(width=-4.5), None, ("data row 6", "width -4.5", "vehicle lengths")),
        (lambda r: r[5].update(height=0.0), None, ("data row 6", "height 0", "vehicle widths")),
        (lambda r: r[5].update(x=1e300), None, ("data row 6", "x 1e+300", "positions")),
        (lambda r: r[5].update(xVelocity=-1e300), None, ("data row 6", "xVelocity -1e+300", "velocity components")),
        (lambda r: r[5].update(yAcceleration=1e300), None, ("data row 6", "yAcceleration 1e+300", "accelerations")),
        (_vehicle(1, id=0), lambda m: m[0].update(id=0), ("data row 1", "id 0", "vehicle ids")),
        (_vehicle(1, id=1e30), lambda m: m[0].update(id=1e30), ("data row 1", "id 1e+30", "vehicle ids")),
        (_vehicle(1, id=1.5), lambda m: m[0].update(id=1.5), ("data row 1", "id 1.5 is not a whole number")),
        (None, lambda m: m[0].update(id=1.5), ("tracksMeta.csv", "data row 1", "id 1.5 is not a whole number")),
    ],
)  # fmt: skip
def test_highd_values_are_refused_by_name_and_row(tmp_path: pathlib.Path, capsys, change, meta_change,
                                                  words: tuple[str, ...]) -> None:  # fmt: skip
    assert highd(tmp_path, change, meta_change) == 2
    one_line_error(capsys, *words)
    assert not (tmp_path / "out").exists()


def test_a_highd_frame_far_away_is_refused_before_anything_is_sized_by_it(tmp_path: pathlib.Path) -> None:
    """A frame of 1e13 at 25 Hz is 4e11 s: refused as the table is read, by the limits; a wider limit
    refuses it by the steps it would take, still before a step is made."""
    tracks, meta = highd_rows()
    tracks[5]["frame"] = 1e13
    path = write_highd_tables(tmp_path / "data", tracks, meta)
    with pytest.raises(ValueError, match="data row 6: frame 10000000000000"):
        import_highd(path, tmp_path / "out")
    tracks[5]["frame"] = 2e10  # 8e8 s: a time the limits take, with the span raised to match
    path = write_highd_tables(tmp_path / "data", tracks, meta)
    with pytest.raises(ValueError, match="writes at most"):
        import_highd(path, tmp_path / "out", ImportOptions(max_duration_s=1e9))
    assert not (tmp_path / "out").exists()


def test_positions_stay_finite_through_interpolation(tmp_path: pathlib.Path) -> None:
    """The largest positions accepted, far apart, interpolate to finite values (no +-inf from overflow)."""
    import numpy as np

    from lcdata.corpus import load_tracks

    frames = [f'<timestep time="{t}"><vehicle id="a" x="{x}" y="-1e7" angle="90" speed="150"/></timestep>'
              for t, x in ((0, "-1e7"), (1, "1e7"))]  # fmt: skip
    (tmp_path / "far.xml").write_text("<fcd-export>" + "".join(frames) + "</fcd-export>")
    import_sumo_fcd(tmp_path / "far.xml", tmp_path / "out", ImportOptions(min_episode_steps=2))
    [tracks] = load_tracks(tmp_path / "out")
    assert np.isfinite(tracks[["x", "y", "speed", "accel", "length", "width"]].to_numpy()).all()


def test_a_timestep_holds_a_bounded_number_of_vehicles(tmp_path: pathlib.Path, monkeypatch) -> None:
    """Each vehicle of a timestep is kept until the timestep ends: their number is bounded as they are read
    (the limit lowered to 2 here)."""
    import lcdata.importers.sumo

    monkeypatch.setattr(lcdata.importers.sumo, "MAX_VEHICLES_PER_SAMPLE", 2)
    cars = "".join(f'<vehicle id="{i}" x="{5 * i}" y="0" angle="90" speed="1"/>' for i in range(3))
    (tmp_path / "many.xml").write_text(f'<fcd-export>\n<timestep time="0">\n{cars}</timestep></fcd-export>')
    with pytest.raises(ValueError, match="line 3: the timestep of line 2 holds more than 2 vehicles"):
        import_sumo_fcd(tmp_path / "many.xml", tmp_path / "out")
