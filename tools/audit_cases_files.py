"""Audit cases for the files a user is handed and the machine a command runs on: crafted policy cards and
predictor files, absurd values, refusals that must come before any write, a policy moved away from the
folder it was trained in, and the environment's errors (a full disk, a folder that cannot be written, two
recordings into one folder, the filesystem root or the home directory as ``--out``).

:func:`build` makes the small files the cases need under ``root`` and returns the cases, in the format of
``tools/audit_inputs.py`` (whose ``Case`` class the caller passes in; its ``run_case`` runs them)::

    from audit_inputs import Case, run_case
    from audit_cases_files import build
    for case in build(root, Case):
        print(run_case(case, root).verdict, case.what)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

_ENTRY = {"lc-record": ("lccli.record", "record_main")}
DEEP = 5000
"""Nesting depth of the crafted TOML / JSON arrays (Python's parsers recurse once per level)."""


def _command(argv: list[str]) -> list[str]:
    """A command line as a user runs it (the entry point's module in a fresh interpreter)."""
    module, main = _ENTRY[argv[0]]
    return [sys.executable, "-c", f"import sys; sys.argv[0] = {argv[0]!r}; from {module} import {main}; "
            f"raise SystemExit({main}())", *argv[1:]]


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _recard(src: Path, dest: Path, change: Callable[[dict[str, Any]], None] | None = None,
            append: str = "") -> Path:
    """A copy of the policy file ``src`` at ``dest`` whose card ``change`` edited (``append``: raw JSON text
    put in front of the card's closing brace, for what ``json.dumps`` cannot write)."""
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    with safe_open(str(src), framework="pt") as f:
        header = dict(f.metadata() or {})
    card = json.loads(header["lc_card"])
    if change is not None:
        change(card)
    text = json.dumps(card, sort_keys=True)
    if append:
        text = text[:-1] + ", " + append + "}"
    dest.parent.mkdir(parents=True, exist_ok=True)
    save_file(load_file(str(src)), str(dest), metadata={**header, "lc_card": text})
    return dest


def _repredictor(src: Path, dest: Path, **config: Any) -> Path:
    """A copy of the predictor file ``src`` at ``dest`` whose stored config has the fields ``config``."""
    import torch

    payload = torch.load(src, map_location="cpu", weights_only=True)
    stored = json.loads(payload["config"])
    stored.update(config)
    payload["config"] = json.dumps(stored)
    dest.parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, dest)
    return dest


def _fcd(path: Path, steps: int = 80) -> Path:
    """A small, valid SUMO FCD file: two vehicles on a straight two-lane edge, 0.1 s steps."""
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<fcd-export>"]
    for i in range(steps):
        t = i * 0.1
        lines.append(f'  <timestep time="{t:.2f}">')
        for vid, lane, x0, v in (("a", 0, 10.0, 20.0), ("b", 1, 30.0, 22.0)):
            lines.append(f'    <vehicle id="{vid}" x="{x0 + v * t:.2f}" y="{-1.6 - 3.2 * lane:.2f}" angle="90.00" '
                         f'type="DEFAULT_VEHTYPE" speed="{v:.2f}" pos="0.00" lane="e0_{lane}" slope="0.00"/>')
        lines.append("  </timestep>")
    lines.append("</fcd-export>")
    path.write_text("\n".join(lines) + "\n")
    return path


def build(root: Path, Case: Any) -> list[Any]:
    """The cases, with the small files they need made under ``root``: tiny policies (one trained with a
    scenario file given by a relative path, one reading predictions), crafted cards and predictor files,
    scenario, config and recipe files with absurd or deeply nested values."""
    import torch

    from lcmodels.policy import PolicyConfig, train_policy
    from lcmodels.predictor import Predictor, PredictorConfig, TrajectoryTransformer

    root = Path(root)
    r = str(root)
    torch.manual_seed(0)
    predictor = root / "predictor.pt"
    Predictor(TrajectoryTransformer(PredictorConfig(d_model=16, ff_dim=32, num_layers=1))).save(predictor)

    # A pure policy trained in proj/ with a scenario file named by a relative path.
    proj = root / "proj"
    proj.mkdir()
    (proj / "my.toml").write_text("route_length_m = 150.0\ntime_limit_s = 25.0\n[traffic]\nnum_vehicles = 8\n"
                                  "spawn_behind_m = 40.0\nspawn_ahead_m = 100.0\n")
    here = os.getcwd()
    os.chdir(proj)
    try:
        train_policy(PolicyConfig(scenario="my.toml", obs="pure", timesteps=64, n_envs=2, n_steps=32,
                                  eval_episodes=0), "run")
    finally:
        os.chdir(here)
    mine = proj / "run" / "policy.safetensors"
    train_policy(PolicyConfig(scenario="tiny", obs="pure", timesteps=64, n_envs=2, n_steps=32, eval_episodes=0),
                 root / "pure_run")
    pure = root / "pure_run" / "policy.safetensors"

    # A prediction policy trained with a predictor in pp/, then moved with its predictor beside it.
    torch.manual_seed(1)
    (root / "pp").mkdir()
    own_pred = root / "pp" / "predictor.pt"
    Predictor(TrajectoryTransformer(PredictorConfig(d_model=16, ff_dim=32, num_layers=1))).save(own_pred)
    train_policy(PolicyConfig(scenario="tiny", obs="prediction", timesteps=64, n_envs=2, n_steps=32,
                              eval_episodes=0), root / "pred_run", predictor=own_pred)
    moved = root / "moved"
    moved.mkdir()
    shutil.copyfile(root / "pred_run" / "policy.safetensors", moved / "policy.safetensors")
    shutil.copyfile(own_pred, moved / "predictor.pt")
    own_pred.unlink()
    pred_policy = root / "pred_run" / "policy.safetensors"

    # Crafted cards: absurd sizes, values of the wrong type, deep nesting, a predictor that is no predictor.
    crafted = root / "cards"

    def scenario_field(section: str | None, name: str, value: Any) -> Callable[[dict[str, Any]], None]:
        def change(card: dict[str, Any]) -> None:
            (card["scenario"][section] if section else card["scenario"])[name] = value
        return change

    def train_field(name: str, value: Any) -> Callable[[dict[str, Any]], None]:
        return lambda card: card["train_config"].__setitem__(name, value)

    long_history = _recard(pure, crafted / "history.safetensors", scenario_field(None, "history_steps", 10**9))
    list_steps = _recard(pure, crafted / "list_steps.safetensors", train_field("n_steps", [128, 128]))
    wide_image = _recard(pure, crafted / "features.safetensors", train_field("image_features", 10**9))
    text_speed = _recard(pure, crafted / "speed.safetensors", scenario_field("traffic", "speed_kmh", "fast"))
    list_count = _recard(pure, crafted / "timesteps.safetensors", lambda c: c.__setitem__("timesteps", [64]))
    deep_card = _recard(pure, crafted / "deep.safetensors", append='"notes": ' + "[" * DEEP + "]" * DEEP)
    list_pred = _recard(pred_policy, crafted / "list_pred.safetensors", lambda c: c.__setitem__("predictor", [1]))
    secret = root / "secret.txt"
    secret.write_text("password=hunter2\n")
    not_pred = _recard(pred_policy, crafted / "not_pred.safetensors", lambda c: c.__setitem__(
        "predictor", {"file": "secret.txt", "path": str(secret), "sha256": _sha256(secret)}))
    huge_ff = _repredictor(predictor, root / "huge_ff.pt", ff_dim=10**10)
    list_layers = _repredictor(predictor, root / "list_layers.pt", num_layers=[2])
    huge_ff_card = _recard(pred_policy, crafted / "huge_ff_card.safetensors", lambda c: c.__setitem__(
        "predictor", {"file": huge_ff.name, "path": str(huge_ff), "sha256": _sha256(huge_ff)}))

    # Scenario, config and recipe files with absurd values or deep nesting.
    (root / "fast.toml").write_text("[traffic]\nnum_vehicles = 8\nspeed_kmh = 1e308\n")
    (root / "history.toml").write_text("history_steps = 100000000000000000000\n")
    (root / "long.toml").write_text("time_limit_s = 1e9\n")
    (root / "tiny_dt.toml").write_text("dt_s = 1e-12\ndecision_period_s = 5e-12\n")
    (root / "deep.toml").write_text("x = " + "[" * DEEP + "]" * DEEP + "\n")
    (root / "deep.json").write_text('{"x": ' + "[" * DEEP + "]" * DEEP + "}\n")
    (root / "many-demos.toml").write_text('name = "many-demos"\nrow = "ppo-pure"\nstages = ["clone", "train"]\n'
                                          '[policy]\nobs = "pure"\n[demos]\nepisodes = 1000000000000\n')
    (root / "long-train.toml").write_text('name = "long-train"\nrow = "ppo-pure"\n[policy]\nobs = "pure"\n'
                                          "[train]\ntimesteps = 1000000000000000\n")
    _fcd(root / "fcd.xml")
    from lcdata.record import record_episode
    from lcsim.config import paper_scenario

    base = paper_scenario()
    corpus = dataclasses.replace(base, traffic=dataclasses.replace(base.traffic, num_vehicles=8), time_limit_s=20.0,
                                 render_image=False)
    for seed in range(3):  # the fewest a predictor's train / validation / test split takes
        record_episode(corpus, seed, "rule", root / "ep" / f"paper_rule_s{seed:07d}.mcap", writer="inline")
    home = root / "home"
    home.mkdir()
    (home / ".profile").write_text("# a user's own file\n")
    (root / "a_file").write_text("not a directory")

    def not_written(*paths: Path) -> Callable[[], str]:
        return lambda: "; ".join(f"{p.name} was written" for p in paths if p.exists())

    written_names = ("record.json", ".lc-record.lock", "predictor.pt", "metrics.json", "run.json", "tb",
                     "progress.csv", "experiment.json", ".lock")

    def nothing_new_in(folder: Path) -> dict[str, Callable[..., Any]]:
        """A case's ``before`` and ``check``: no entry appears in ``folder``. What the commands write that did
        appear is removed again (only such names: ``folder`` may be the filesystem root)."""
        seen: dict[str, set[str]] = {}

        def before() -> None:
            seen["names"] = {p.name for p in folder.iterdir()}

        def check() -> str:
            new = sorted({p.name for p in folder.iterdir()} - seen["names"])
            for name in new:  # an audit leaves no trace: what the command wrote there goes again
                p = folder / name
                if name in written_names or name.endswith((".mcap", ".mcap.partial")) or folder != Path("/"):
                    shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
            return f"wrote {', '.join(new[:3])} into {folder}" if new else ""

        return {"before": before, "check": check}

    def recorded(folder: Path, n: int) -> Callable[[], str]:
        def check() -> str:
            files = sorted(folder.glob("*.mcap"))
            return "" if len(files) == n else f"{len(files)} of {n} episodes recorded in {folder.name}"
        return check

    def no_absolute_predictor_path(policy: Path) -> Callable[[], str]:
        def check() -> str:
            from safetensors import safe_open

            with safe_open(str(policy), framework="pt") as f:
                card = json.loads((f.metadata() or {})["lc_card"])
            path = (card.get("predictor") or {}).get("path")
            return f"the card keeps the predictor's absolute path {path}" if path and Path(path).is_absolute() else ""
        return check

    # Two lc-record processes on one --out: the first holds it while the case starts the second.
    rival: dict[str, subprocess.Popen[bytes]] = {}
    rival_out = root / "shared_out"
    rival_argv = ["lc-record", "--vehicles", "8", "--steps", "1200", "--episodes", "3", "--no-images", "--out",
                  str(rival_out)]

    def start_rival() -> None:
        rival["proc"] = subprocess.Popen(_command(rival_argv), cwd=root, stdout=subprocess.DEVNULL,
                                         stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 120
        while not (rival_out / "record.json").exists() and rival["proc"].poll() is None:
            if time.monotonic() > deadline:
                break
            time.sleep(0.05)

    def rival_finished_alone() -> str:
        proc = rival["proc"]
        try:
            rc = proc.wait(timeout=600)
        except subprocess.TimeoutExpired:
            proc.kill()
            return "the first recording did not finish"
        partial = sorted(rival_out.glob("*.partial"))
        if rc != 0:
            return f"the first recording failed (exit {rc})"
        return f"{partial[0].name} left behind" if partial else recorded(rival_out, 3)()

    # A full disk, as a file-size limit the command inherits (writes past it fail with EFBIG).
    saved_fsize = resource.getrlimit(resource.RLIMIT_FSIZE)

    def small_disk(limit: int) -> Callable[[], None]:
        return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, saved_fsize[1]))

    def disk_back(then: Callable[[], str] = lambda: "") -> Callable[[], str]:
        def check() -> str:
            resource.setrlimit(resource.RLIMIT_FSIZE, saved_fsize)
            return then()
        return check

    rec = ["lc-record", "--vehicles", "8", "--steps", "40"]
    tiny_train = ["lc-train-policy", "--scenario", "tiny", "--timesteps", "64", "--set", "n_envs=2", "--set",
                  "n_steps=32", "--set", "eval_episodes=0", "-q", "--obs", "pure"]
    ev = ["lc-eval", "--episodes", "1", "--no-record"]
    fake_home = {"HOME": str(home)}
    cases = [
        # 4. crafted policy cards and predictor files
        Case("lc-eval: card with a history of 1e9 steps", [*ev, str(long_history)]),
        Case("lc-eval: card whose n_steps is a list", [*ev, str(list_steps)]),
        Case("lc-eval: card with 1e9 image features", [*ev, str(wide_image)]),
        Case("lc-eval: card whose traffic speed is text", [*ev, str(text_speed)]),
        Case("lc-eval: card whose step count is a list", [*ev, str(list_count)]),
        Case(f"lc-eval: card nested {DEEP} deep", [*ev, str(deep_card)]),
        Case("lc-eval: card whose predictor entry is a list", [*ev, str(list_pred)]),
        Case("lc-eval: card naming a text file as its predictor", [*ev, str(not_pred)]),
        Case("lc-eval: card naming a predictor with a 1e10 feed-forward width", [*ev, str(huge_ff_card)]),
        Case("lc-train-policy: --predictor with a 1e10 feed-forward width",
             [*tiny_train[:-2], "--obs", "prediction", "--predictor", str(huge_ff), "--out", f"{r}/t8"],
             check=not_written(root / "t8")),
        Case("lc-record: card with a history of 1e9 steps", ["lc-record", "--driver", f"policy:{long_history}",
                                                             "--out", f"{r}/c1"], check=not_written(root / "c1")),
        Case("lc-train-policy: --predictor whose layer count is a list",
             [*tiny_train[:-2], "--obs", "prediction", "--predictor", str(list_layers), "--out", f"{r}/t4"],
             check=not_written(root / "t4")),
        Case("lc-train-policy: --init-policy card whose n_steps is a list",
             [*tiny_train, "--init-policy", str(list_steps), "--out", f"{r}/t5"], check=not_written(root / "t5")),
        # 5. large or odd values
        Case("lc-record: --start-time in the year 9999", [*rec, "--start-time", "9999-12-31T23:59:59Z", "--out",
                                                          f"{r}/s1"], check=not_written(root / "s1")),
        Case("lc-record: --start-time in the year 2300", [*rec, "--start-time", "2300-01-01T00:00:00Z", "--out",
                                                          f"{r}/s2"], check=not_written(root / "s2")),
        Case("lc-train-policy: --timesteps 1e23", [*tiny_train, "--timesteps", str(10**23), "--out", f"{r}/t1"],
             check=not_written(root / "t1")),
        Case("lc-experiment: recipe with 1e12 demonstration episodes",
             ["lc-experiment", "--preset", "tiny", "--recipe", f"{r}/many-demos.toml", "--out", f"{r}/x1"],
             check=not_written(root / "x1")),
        Case("lc-experiment: recipe with 1e15 training steps",
             ["lc-experiment", "--preset", "tiny", "--recipe", f"{r}/long-train.toml", "--out", f"{r}/x2"],
             check=not_written(root / "x2")),
        Case("lc-record: scenario with speed_kmh = 1e308", [*rec, "--scenario", f"{r}/fast.toml", "--out",
                                                            f"{r}/s3"], check=not_written(root / "s3")),
        Case("lc-record: scenario with a 1e9 s time limit", ["lc-record", "--scenario", f"{r}/long.toml", "--out",
                                                              f"{r}/s4"], check=not_written(root / "s4")),
        Case("lc-record: scenario with a 1e-12 s step", ["lc-record", "--scenario", f"{r}/tiny_dt.toml", "--out",
                                                          f"{r}/s5"], check=not_written(root / "s5")),
        Case(f"lc-record: scenario TOML nested {DEEP} deep", [*rec, "--scenario", f"{r}/deep.toml", "--out",
                                                             f"{r}/s6"], check=not_written(root / "s6")),
        Case(f"lc-train-policy: --config TOML nested {DEEP} deep", [*tiny_train, "--config", f"{r}/deep.toml",
                                                                     "--out", f"{r}/t2"], check=not_written(root / "t2")),
        Case(f"lc-eval: --scenario JSON nested {DEEP} deep", ["lc-eval", "rule", "--episodes", "1", "--no-record",
                                                             "--scenario", f"{r}/deep.json"]),
        Case("lc-train-predictor: a history of 1e9 steps", ["lc-train-predictor", "--data", f"{r}/ep",
                                                            "--history", str(10**9), "--out", f"{r}/p1"],
             check=not_written(root / "p1")),
        # 6. bad input that wrote before it refused
        Case("lc-record: scenario with history_steps = 1e20", [*rec, "--scenario", f"{r}/history.toml", "--out",
                                                               f"{r}/s7"], check=not_written(root / "s7")),
        Case("lc-train-policy: --set n_envs=999999", [*tiny_train, "--set", "n_envs=999999", "--out", f"{r}/t3"],
             check=not_written(root / "t3")),
        Case("lc-train-policy: --set eval_seed beyond the validation seeds",
             [*tiny_train, "--set", "eval_seed=99999999", "--set", "eval_episodes=1", "--out", f"{r}/t6"],
             check=not_written(root / "t6")),
        Case("lc-train-policy: dqn with a 1e12 replay buffer", [*tiny_train, "--algo", "dqn", "--set",
                                                                "buffer_size=1000000000000", "--out", f"{r}/t7"],
             check=not_written(root / "t7")),
        # 7. a policy is not tied to the folder it was trained from
        Case("lc-eval: policy trained with --scenario my.toml, from another folder", [*ev, str(mine)], expect="ok"),
        Case("lc-record: policy trained with --scenario my.toml, from another folder",
             ["lc-record", "--driver", f"policy:{mine}", "--no-images", "--out", f"{r}/m1"], expect="ok",
             check=recorded(root / "m1", 1)),
        Case("lc-eval: a prediction policy moved with its predictor beside it", [*ev, str(moved / "policy.safetensors")],
             expect="ok", check=no_absolute_predictor_path(pred_policy)),
        # 8. the environment's errors
        Case("lc-eval: --json-out in a folder nobody can write", [*ev, "rule", "--json-out", "/proc/lc-audit.json"]),
        Case("lc-eval: --json-out under a file", [*ev, "rule", "--json-out", f"{r}/a_file/summary.json"]),
        Case("lc-eval: --json-out is a directory", [*ev, "rule", "--overwrite", "--json-out", f"{r}/proj"]),
        Case("lc-record: a second recording into the same --out", rival_argv, before=start_rival,
             check=rival_finished_alone),
        Case("lc-record: --out /", [*rec, "--out", "/"], **nothing_new_in(Path("/"))),
        Case("lc-record: --out is the home directory", [*rec, "--out", str(home)], env=fake_home,
             **nothing_new_in(home)),
        Case("lc-train-policy: --out is the home directory", [*tiny_train, "--out", str(home), "--overwrite"],
             env=fake_home, **nothing_new_in(home)),
        Case("lc-experiment: --out is the home directory", ["lc-experiment", "--preset", "tiny", "--out", str(home)],
             env=fake_home, **nothing_new_in(home)),
        Case("lc-import: --out is the home directory", ["lc-import", "sumo-fcd", f"{r}/fcd.xml", "--out", str(home)],
             env=fake_home, **nothing_new_in(home)),
        Case("lc-train-predictor: --out /", ["lc-train-predictor", "--data", f"{r}/ep", "--epochs", "1", "--out", "/"],
             **nothing_new_in(Path("/"))),
        Case("lc-record: the disk fills up", [*rec, "--out", f"{r}/full1"], before=small_disk(16 << 10),
             check=disk_back()),
        Case("lc-eval: the disk fills up under --out", ["lc-eval", "rule", "--episodes", "2", "--out", f"{r}/full2"],
             before=small_disk(16 << 10), check=disk_back()),
        Case("lc-train-policy: the disk fills up", [*tiny_train, "--set", "batch_size=64", "--out", f"{r}/full3"],
             before=small_disk(16 << 10),
             check=disk_back()),
    ]
    return cases


if __name__ == "__main__":
    sys.exit("run these cases with run_case from tools/audit_inputs.py (see the module docstring)")
