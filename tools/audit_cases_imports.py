"""Audit cases for traffic imported from elsewhere and the sizes a user may ask for: SUMO FCD and highD files
holding values no recording holds (non-finite, huge, negative, fractional), gaps and steps that would write
without end, the staging folder an import leaves or holds, lc-calibrate's bootstrap and episodes, a seed
beyond the last start time a file holds, and files read back beside a policy (a tensor relabelled to another
dtype, a seeds file that holds no seeds).

:func:`build` makes the small files the cases need under ``root`` and returns the cases, in the format of
``tools/audit_inputs.py`` (whose ``Case`` class the caller passes in; its ``run_case`` runs them). Run alone,
this module runs its own cases only and prints the table and the counts::

    python tools/audit_cases_imports.py
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

STAGING = ".sumo_fcd.import-staging"
"""The staging folder of an import of ``fcd.xml`` (``lcdata.importers.episodes.EpisodeFiles``)."""
CAR = 'x="{x:.2f}" y="-1.60" angle="90.00" type="DEFAULT_VEHTYPE" speed="{speed}" lane="e0_0"'


def _fcd(path: Path, steps: int = 80, car: str = CAR, times: dict[int, str] | None = None,
         speeds: dict[int, str] | None = None) -> Path:  # fmt: skip
    """A SUMO FCD file: vehicle ``a`` (``car``, formatted with its x and speed) and ``b`` on two lanes, 0.1 s
    steps; ``times`` and ``speeds`` replace the time and ``a``'s speed of the given timesteps."""
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<fcd-export>"]
    for i in range(steps):
        t = i * 0.1
        lines.append(f'  <timestep time="{(times or {}).get(i, f"{t:.2f}")}">')
        lines.append(f'    <vehicle id="a" {car.format(x=10 + 20 * t, speed=(speeds or {}).get(i, "20.00"))}/>')
        lines.append(f'    <vehicle id="b" x="{30 + 22 * t:.2f}" y="-4.80" angle="90.00" speed="22.00" lane="e0_1"/>')
        lines.append("  </timestep>")
    lines.append("</fcd-export>")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


HIGHD_COLUMNS = ("frame", "id", "x", "y", "width", "height", "xVelocity", "yVelocity", "xAcceleration",
                 "yAcceleration", "laneId")  # fmt: skip


def _highd(folder: Path, change: Callable[[list[dict[str, Any]]], None] | None = None,
           meta_change: Callable[[list[dict[str, Any]]], None] | None = None) -> Path:
    """``01_tracks.csv`` and ``01_tracksMeta.csv`` in ``folder``: two cars on the lower carriageway (lanes 5 and 6,
    25 Hz, 2 s; car 2 changes lane at frame 25) and one on the upper, each row edited by ``change``."""
    rows: list[dict[str, Any]] = []
    for vid, lane, x0, vx in ((1, 6, 20.0, 30.0), (2, 6, 60.0, 32.0), (3, 2, 400.0, -25.0)):
        for f in range(1, 51):
            lane_id = 5 if vid == 2 and f >= 25 else lane
            y = {2: 9.875, 5: 21.875, 6: 25.625}[lane_id]
            rows.append({"frame": f, "id": vid, "x": x0 + vx * (f - 1) / 25 - 2.25, "y": y - 0.95, "width": 4.5,
                         "height": 1.9, "xVelocity": vx, "yVelocity": 0.0, "xAcceleration": 0.0, "yAcceleration": 0.0,
                         "laneId": lane_id})  # fmt: skip
    meta = [{"id": vid, "class": "Car", "drivingDirection": d} for vid, d in ((1, 2), (2, 2), (3, 1))]
    if change is not None:
        change(rows)
    if meta_change is not None:
        meta_change(meta)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "01_tracks.csv").write_text(",".join(HIGHD_COLUMNS) + "\n" + "".join(
        ",".join(str(r[c]) for c in HIGHD_COLUMNS) + "\n" for r in rows))  # fmt: skip
    (folder / "01_tracksMeta.csv").write_text("id,class,drivingDirection\n" + "".join(
        f"{m['id']},{m['class']},{m['drivingDirection']}\n" for m in meta))  # fmt: skip
    return folder / "01_tracks.csv"


def _row(index: int, **values: Any) -> Callable[[list[dict[str, Any]]], None]:
    return lambda rows: rows[index].update(values)


def _vehicle(vid: int, new: Any) -> Callable[[list[dict[str, Any]]], None]:
    def change(rows: list[dict[str, Any]]) -> None:
        for row in rows:
            if row["id"] == vid:
                row["id"] = new

    return change


def _relabelled(src: Path, dest: Path) -> Path:
    """A copy of the safetensors file ``src`` whose first float tensor's header says I32 (same bytes)."""
    data = src.read_bytes()
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + n])
    name = next(k for k, v in sorted(header.items()) if k != "__metadata__" and v["dtype"] == "F32")
    header[name]["dtype"] = "I32"
    text = json.dumps(header, separators=(",", ":")).encode()
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_bytes(data[:8] + text + b" " * (n - len(text)) + data[8 + n :])
    return dest


def build(root: Path, Case: Any) -> list[Any]:
    """The cases, with the files they need made under ``root``: SUMO and highD files, an imported recording for
    lc-calibrate, a tiny trained policy and copies of it beside bad seed files."""
    import shutil

    import numpy as np

    from lcdata.record import MAX_USER_SEED
    from lcmodels.fileio import TRAIN_SEEDS_FILE
    from lcmodels.policy import PolicyConfig, train_policy

    root = Path(root)
    r = str(root)
    sumo = root / "sumo"
    fcd = _fcd(sumo / "fcd.xml")

    def not_written(out: Path) -> Callable[[], str]:
        return lambda: f"{out.name} was written" if out.exists() else ""

    def import_refused(what: str, path: Path, name: str, *flags: str) -> Any:
        out = root / "out" / name
        fmt = "sumo-fcd" if path.suffix == ".xml" else "highd"
        return Case(f"lc-import: {what}", ["lc-import", fmt, str(path), "--out", str(out), "-q", *flags],
                    check=not_written(out))

    def sumo_file(name: str, **kw: Any) -> Path:
        return _fcd(sumo / name / "fcd.xml", **kw)

    def car(**attrs: str) -> str:
        base = dict(x="{x:.2f}", y="-1.60", angle="90.00", speed="{speed}", lane="e0_0")
        base.update(attrs)
        return " ".join(f'{k}="{v}"' for k, v in base.items())

    # lc-calibrate reads an imported recording (its lane change and two lanes are all the checks need)
    from lcdata.importers import import_highd

    data = root / "calibrate_data"
    import_highd(_highd(root / "highd_ok"), data)

    # a stale staging folder (its import killed outright) and one held by a running import
    stale_out, held_out = root / "stale_out", root / "held_out"
    for out in (stale_out, held_out):
        (out / STAGING).mkdir(parents=True)
        (out / STAGING / "sumo_fcd_0000.mcap.staged").write_bytes(b"half an episode")
    holder: list[subprocess.Popen[str]] = []

    def hold() -> None:
        code = ("import fcntl, sys, time; f = open(sys.argv[1], 'a+'); fcntl.flock(f, fcntl.LOCK_EX); "
                "print('held', flush=True); time.sleep(600)")  # fmt: skip
        proc = subprocess.Popen([sys.executable, "-c", code, str(held_out / STAGING / ".lock")],
                                stdout=subprocess.PIPE, text=True)  # fmt: skip
        assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
        holder.append(proc)

    def held_kept() -> str:
        for proc in holder:
            proc.kill()
            proc.wait()
        staged = held_out / STAGING / "sumo_fcd_0000.mcap.staged"
        if not staged.exists() or list(held_out.glob("*.mcap")):
            return "the staging folder of a running import was touched"
        return ""

    def stale_removed() -> str:
        if (stale_out / STAGING).exists():
            return "the stale staging folder is still there"
        return "" if sorted(p.name for p in stale_out.glob("*.mcap")) == ["sumo_fcd_0000.mcap"] else "no episode"

    # a tiny policy, a copy with a relabelled tensor, and copies beside bad seed files
    train_policy(PolicyConfig(scenario="tiny", obs="pure", timesteps=64, n_envs=2, n_steps=32, eval_episodes=0),
                 root / "run")
    policy = root / "run" / "policy.safetensors"
    relabelled = _relabelled(policy, root / "relabelled" / "policy.safetensors")
    seeds: dict[str, Path] = {}
    for kind in ("strings", "objects", "random", "two_d"):
        folder = root / f"seeds_{kind}"
        shutil.copytree(root / "run", folder)
        path = folder / TRAIN_SEEDS_FILE
        if kind == "strings":
            np.save(path, np.array(["7", "11"]))
        elif kind == "objects":
            np.save(path, np.array([7, "x"], dtype=object), allow_pickle=True)
        elif kind == "random":
            path.write_bytes(np.random.default_rng(0).bytes(300))
        else:
            np.save(path, np.load(path).reshape(1, -1))
        seeds[kind] = folder / "policy.safetensors"

    cal = ["lc-calibrate", str(data), "--out", f"{r}/cal/s.toml", "-q"]
    rec = ["lc-record", "--vehicles", "8", "--steps", "40"]
    lane_digits = "9" * 5000
    return [
        # SUMO FCD: values by name
        import_refused("SUMO time inf", sumo_file("t_inf", times={40: "inf"}), "t_inf"),
        import_refused("SUMO time nan", sumo_file("t_nan", times={40: "nan"}), "t_nan"),
        import_refused("SUMO time 1e400 (overflows to inf)", sumo_file("t_big", times={40: "1e400"}), "t_big"),
        import_refused("SUMO time 1e-9 after the one before (an infinite acceleration)",
                       sumo_file("t_close", times={1: "0.000000001"}), "t_close"),
        import_refused("SUMO x 1e308", sumo_file("x_big", car=car(x="1e308")), "x_big"),
        import_refused("SUMO x -inf", sumo_file("x_inf", car=car(x="-inf")), "x_inf"),
        import_refused("SUMO speed -5", sumo_file("v_neg", car=car(speed="-5")), "v_neg"),
        import_refused("SUMO acceleration inf", sumo_file("a_inf", car=car(acceleration="inf")), "a_inf"),
        import_refused("SUMO acceleration 1e9", sumo_file("a_big", car=car(acceleration="1e9")), "a_big"),
        import_refused("SUMO speed 20 -> 150 m/s in 0.1 s (no acceleration attribute)",
                       sumo_file("v_jump", speeds={40: "150"}), "v_jump"),
        import_refused("SUMO length -4", sumo_file("len", car=car(length="-4")), "len"),
        import_refused("SUMO width 0", sumo_file("wid", car=car(width="0")), "wid"),
        import_refused("SUMO lane index 999,999,999", sumo_file("lane", car=car(lane="e0_999999999")), "lane"),
        import_refused("SUMO lane index of 5000 digits (int() refuses it)",
                       sumo_file("lane_long", car=car(lane=f"e0_{lane_digits}")), "lane_long"),
        # SUMO FCD: what an import may write
        import_refused("SUMO one timestep 1e9 s on (writes until the disk is full)",
                       sumo_file("gap_1e9", times={79: "1000000000"}), "gap_1e9"),
        import_refused("SUMO one timestep 5000 s on (100,000 steps for 80 samples)",
                       sumo_file("gap_5000", times={79: "5000"}), "gap_5000"),
        import_refused("--dt 1e-6", fcd, "dt", "--dt", "1e-6"),
        import_refused("--max-duration 2 for 8 s of traffic", fcd, "dur", "--max-duration", "2"),
        import_refused("--max-steps 50 for 160 steps", fcd, "steps", "--max-steps", "50"),
        import_refused("--episode-steps 1e12", fcd, "ep_steps", "--episode-steps", "1000000000000"),
        Case("lc-import: a 200 s gap bridged with --max-steps", ["lc-import", "sumo-fcd",
             str(sumo_file("gap_200", times={79: "200"})), "--out", f"{r}/out/gap_200", "--max-steps", "5000", "-q"],
             expect="ok"),
        # highD: values by name, before anything is sized by them
        import_refused("highD frame 1e13 (hung the CPU)", _highd(root / "h_frame", _row(5, frame=10**13)), "h_frame"),
        import_refused("highD fractional frame 5.5 (was truncated)", _highd(root / "h_frac", _row(5, frame=5.5)),
                       "h_frac"),
        import_refused("highD laneId 999,999,999 (a road of a billion lanes)",
                       _highd(root / "h_lane", _row(5, laneId=999_999_999)), "h_lane"),
        import_refused("highD laneIds 6 and 40 on one carriageway", _highd(root / "h_span", _row(5, laneId=40)),
                       "h_span"),
        import_refused("highD vehicle id 0 (the ego's)", _highd(root / "h_id0", _vehicle(1, 0),
                                                                lambda m: m[0].update(id=0)), "h_id0"),
        import_refused("highD vehicle id 1e30 (OverflowError)", _highd(root / "h_id30", _vehicle(1, 1e30),
                                                                       lambda m: m[0].update(id=1e30)), "h_id30"),
        import_refused("highD vehicle id 1.5 (KeyError)", _highd(root / "h_id15", _vehicle(1, 1.5),
                                                                 lambda m: m[0].update(id=1.5)), "h_id15"),
        import_refused("highD negative width (length) -4.5", _highd(root / "h_len", _row(5, width=-4.5)), "h_len"),
        import_refused("highD xAcceleration 1e300", _highd(root / "h_acc", _row(5, xAcceleration=1e300)), "h_acc"),
        import_refused("highD x 1e300 (+-inf once interpolated)", _highd(root / "h_x", _row(5, x=1e300)), "h_x"),
        import_refused("highD xVelocity -1e300", _highd(root / "h_v", _row(5, xVelocity=-1e300)), "h_v"),
        # the staging folder
        Case("lc-import: a stale staging folder left by a killed import", ["lc-import", "sumo-fcd", str(fcd),
             "--out", str(stale_out), "-q"], expect="ok", check=stale_removed),
        Case("lc-import: a staging folder held by a running import", ["lc-import", "sumo-fcd", str(fcd), "--out",
             str(held_out), "-q"], before=hold, check=held_kept),
        # lc-calibrate: sizes
        Case("lc-calibrate: --bootstrap 100000000 (hung)", [*cal, "--bootstrap", "100000000"],
             check=not_written(root / "cal")),
        Case("lc-calibrate: --episodes 1000000 (8 GiB)", [*cal, "--episodes", "1000000"],
             check=not_written(root / "cal")),
        Case("lc-calibrate: --report-episodes 1000000", [*cal, "--report-episodes", "1000000"],
             check=not_written(root / "cal")),
        Case("lc-calibrate: --episodes 1000 --seconds 3000 (tracks past memory)",
             [*cal, "--episodes", "1000", "--seconds", "3000"], check=not_written(root / "cal")),
        Case("lc-calibrate: --seconds 1e9", [*cal, "--seconds", "1e9"], check=not_written(root / "cal")),
        # lc-record: a seed past the last start time, refused before record.json and the lock
        Case("lc-record: --seed 1e10 leaves no record.json and no lock", [*rec, "--seed", "10000000000", "--out",
             f"{r}/rec_seed"], check=not_written(root / "rec_seed")),
        Case("lc-record: the last episode's seed past the last start time", [*rec, "--seed", str(MAX_USER_SEED),
             "--episodes", "2", "--out", f"{r}/rec_last"], check=not_written(root / "rec_last")),
        # files read back beside a policy
        Case("lc-eval: a tensor relabelled I32 (was loaded and cast)", ["lc-eval", str(relabelled), "--episodes",
             "1", "--no-record"]),
        *[Case(f"lc-eval: {TRAIN_SEEDS_FILE} of {kind.replace('_', '-')} beside the policy",
               ["lc-eval", str(path), "--episodes", "1", "--no-record"]) for kind, path in seeds.items()],
    ]


def main() -> int:
    """Run this module's cases alone (``tools/audit_inputs.py`` runs them with every other module's)."""
    import tempfile

    import audit_inputs

    with tempfile.TemporaryDirectory(prefix="lc-audit-") as tmp:
        cases = build(Path(tmp), audit_inputs.Case)
        outcomes = []
        for i, case in enumerate(cases, 1):
            out = audit_inputs.run_case(case, Path(tmp))
            outcomes.append(out)
            print(f"[{i}/{len(cases)}] {out.verdict:9s} {case.what}: {out.message[:150]}", flush=True)
    counts = {v: sum(o.verdict == v for o in outcomes) for v in ("clean", "correct", "unclear", "traceback", "silent")}
    print(f"\n{len(outcomes)} cases: " + ", ".join(f"{v} {n}" for v, n in counts.items()))
    return 0 if counts["traceback"] == counts["silent"] == counts["unclear"] == 0 else 1


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    raise SystemExit(main())
