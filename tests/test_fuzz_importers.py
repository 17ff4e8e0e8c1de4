"""Fuzzing the importers' parsers: SUMO FCD documents and highD tables built from random and hostile values
(non-finite, huge, negative, fractional, not numbers, missing), random bytes, and truncated valid files. Every
input ends in a clean import or a ``ValueError`` refusal (one line, naming the file), never another exception,
a hang, or an allocation sized by a value.

The imports run in a child process whose address space is capped (``RLIMIT_AS``) and which is given a minute
per input; a blow-up or a hang fails the test instead of taking the machine down.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import pathlib
import resource
from collections.abc import Iterator
from xml.sax.saxutils import quoteattr

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.test_importers import write_fcd, write_highd

MEMORY_LIMIT = 1_500_000_000
"""Address space of the importing process: its imports take about 0.6 GB of it, an input may cost the rest."""
TIME_LIMIT_S = 60
FUZZ = settings(max_examples=25, deadline=None, print_blob=True, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])  # fmt: skip


def _import(job: tuple[str, str, str, float]) -> tuple[str, str]:
    from lcdata.importers import ImportOptions, import_highd, import_sumo_fcd

    kind, path, out, dt = job
    options = ImportOptions(dt_s=dt, episode_steps=50, min_episode_steps=2)
    try:
        if kind == "sumo":
            written = import_sumo_fcd(path, out, options)
        else:
            written = import_highd(path, out, options)
        return "ok", f"{len(written)} episodes"
    except ValueError as exc:
        return "refused", str(exc)
    except MemoryError:
        return "memory", "MemoryError"
    except Exception as exc:  # what the test is after: anything but a clean refusal
        return "error", f"{type(exc).__name__}: {exc}"[:600]


def _serve(conn: multiprocessing.connection.Connection, limit: int) -> None:
    resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
    import lcdata.importers  # noqa: F401  (imported once, under the limit)

    while (job := conn.recv()) is not None:
        conn.send(_import(job))


class LimitedImporter:
    """The capped child, restarted after a hang or a death."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._context = multiprocessing.get_context("spawn")
        self._start()

    def _start(self) -> None:
        self._conn, child = self._context.Pipe()
        self._proc = self._context.Process(target=_serve, args=(child, self.limit), daemon=True)
        self._proc.start()
        child.close()

    def run(self, kind: str, path: pathlib.Path, out: pathlib.Path, dt: float = 0.05) -> tuple[str, str]:
        self._conn.send((kind, str(path), str(out), dt))
        try:
            if self._conn.poll(TIME_LIMIT_S):
                return self._conn.recv()
            outcome = ("hang", f"no answer after {TIME_LIMIT_S} s")
        except EOFError:
            outcome = ("died", "")
        self._proc.kill()
        self._proc.join()
        self._start()
        return outcome[0], outcome[1] or f"exit code {self._proc.exitcode}"

    def close(self) -> None:
        self._conn.send(None)
        self._proc.join(10)
        if self._proc.is_alive():
            self._proc.kill()


@pytest.fixture(scope="module")
def importer() -> Iterator[LimitedImporter]:
    child = LimitedImporter(MEMORY_LIMIT)
    yield child
    child.close()


def check(importer: LimitedImporter, kind: str, path: pathlib.Path, dt: float = 0.05) -> None:
    outcome, message = importer.run(kind, path, path.parent / f"out-{path.stem}", dt)
    assert outcome in ("ok", "refused"), f"{outcome}: {message}"
    if outcome == "refused":
        assert str(path.parent) in message and "\n" not in message.strip(), message


# -- values a hostile file puts where a number belongs ------------------------------------------------------
hostile = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**30), 10**30).map(str),
    st.sampled_from(["", "abc", "1e400", "-1e400", "1e13", "1e-300", "0x10", "1_000", " 5 ", "\u0661\u0662", "nan"]),
)
lanes = st.sampled_from(["e0_0", "e0_1", ":J0_0_0", "e0_", "e0_x", "e0_\u00b2", "e0_999999999", "e0_" + "9" * 30, ""])


def _value(draw: st.DrawFn, low: float, high: float, spoil: int = 10) -> str:
    """A plausible number in ``[low, high]``, or (one time in ``spoil``) a hostile one."""
    if draw(st.integers(0, spoil - 1)) == 0:
        return draw(hostile)
    return f"{draw(st.floats(low, high)):.3f}"


@st.composite
def sumo_document(draw: st.DrawFn) -> str:
    step = draw(st.sampled_from([0.04, 0.1, 1.0, 7.0]))
    spoil = draw(st.sampled_from([10**9, 40, 10]))  # a clean document one time in three
    ranges = {"x": (-1000, 1000), "y": (-1000, 1000), "angle": (0, 360), "speed": (0, 40), "length": (3, 20),
              "width": (1.5, 3), "acceleration": (-5, 5)}  # fmt: skip
    body = []
    for k in range(draw(st.integers(0, 8))):
        time = f"{k * step:.2f}" if draw(st.integers(0, spoil - 1)) else draw(st.none() | hostile)
        head = "<timestep" + ("" if time is None else f" time={quoteattr(time)}") + ">"
        vehicles = []
        for vid in draw(st.lists(st.sampled_from(["a", "b", "c"]), max_size=3)):
            attrs = {"id": vid, **{f: _value(draw, *r, spoil) for f, r in ranges.items()
                                   if f in ("x", "y", "angle", "speed") or draw(st.booleans())}}  # fmt: skip
            if draw(st.booleans()):
                attrs["lane"] = draw(lanes) if draw(st.integers(0, spoil - 1)) == 0 else "e0_1"
            if draw(st.integers(0, spoil - 1)) == 0:  # now and then a required attribute missing
                attrs.pop(draw(st.sampled_from(["x", "y", "angle", "speed", "id"])), None)
            vehicles.append("<vehicle " + " ".join(f"{k}={quoteattr(v)}" for k, v in attrs.items()) + "/>")
        body.append(head + "".join(vehicles) + "</timestep>")
    return "<fcd-export>" + "\n".join(body) + "</fcd-export>"


@FUZZ
@given(document=sumo_document(), dt=st.sampled_from([0.001, 0.05, 1.0]))
def test_fuzzed_sumo_documents_import_or_are_refused(importer, tmp_path_factory, document: str, dt: float) -> None:
    path = tmp_path_factory.mktemp("sumo") / "fcd.xml"
    path.write_text(document)
    check(importer, "sumo", path, dt)


COLUMNS = ("frame", "id", "x", "y", "width", "height", "xVelocity", "yVelocity", "xAcceleration", "yAcceleration",
           "laneId")  # fmt: skip


@st.composite
def highd_tables(draw: st.DrawFn) -> tuple[str, str]:
    """Two or three vehicles over a few frames, some cells hostile (none, now and then)."""
    frames = draw(st.integers(2, 40))
    vehicles = draw(st.integers(1, 3))
    rows = []
    for vid in range(1, vehicles + 1):
        lane = draw(st.integers(1, 7))
        for f in range(1, frames + 1):
            rows.append([str(f), str(vid), f"{10 + 30 * f / 25:.2f}", f"{3.75 * lane:.2f}", "4.5", "1.9", "30", "0",
                         "0", "0", str(lane)])  # fmt: skip
    for _ in range(draw(st.integers(0, 3))):
        row, col = draw(st.integers(0, len(rows) - 1)), draw(st.integers(0, len(COLUMNS) - 1))
        rows[row][col] = draw(hostile | st.integers(-5, 50).map(str))
    directions = st.sampled_from(["1", "2"]) if draw(st.integers(0, 4)) else st.sampled_from(["3", "1.5", "-1", ""])
    meta = [f"{vid},{draw(st.sampled_from(['Car', 'Truck']))},{draw(directions)}" for vid in range(1, vehicles + 1)]
    if draw(st.integers(0, 4)) == 0:
        meta[0] = f"{draw(hostile)},Car,2"
    tracks = ",".join(COLUMNS) + "\n" + "\n".join(",".join(r) for r in rows) + "\n"
    return tracks, "id,class,drivingDirection\n" + "\n".join(meta) + "\n"


@FUZZ
@given(tables=highd_tables())
def test_fuzzed_highd_tables_import_or_are_refused(importer, tmp_path_factory, tables: tuple[str, str]) -> None:
    folder = tmp_path_factory.mktemp("highd")
    (folder / "01_tracks.csv").write_text(tables[0])
    (folder / "01_tracksMeta.csv").write_text(tables[1])
    check(importer, "highd", folder / "01_tracks.csv")


@FUZZ
@given(kind=st.sampled_from(["sumo", "highd"]), data=st.data())
def test_random_bytes_and_truncated_files_are_refused(importer, tmp_path_factory, kind: str,
                                                      data: st.DataObject) -> None:  # fmt: skip
    folder = tmp_path_factory.mktemp("raw")
    good = write_fcd(folder / "fcd.xml") if kind == "sumo" else write_highd(folder)
    content = good.read_bytes()
    if data.draw(st.booleans()):
        content = content[: data.draw(st.integers(0, len(content) - 1))]
    else:
        at = data.draw(st.integers(0, len(content) - 1))
        content = content[:at] + data.draw(st.binary(max_size=64)) + content[at + 1 :]
    good.write_bytes(content)
    check(importer, kind, good)


def test_the_harness_reports_what_is_not_a_refusal(importer: LimitedImporter, tmp_path: pathlib.Path) -> None:
    outcome, message = importer.run("sumo", tmp_path / "missing.xml", tmp_path / "out")
    assert outcome == "error" and message.startswith("FileNotFoundError")
