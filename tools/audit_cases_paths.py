"""Audit cases for the paths a command writes, deletes and reads back: symbolic links planted in its output
folder (a ``.partial``, a lock, a table, a stage or run folder), names made of a user's values (``lc-tune``'s
trials), paths read from its own files (a stage record's outputs, a DAgger round, a zoo name), and a user's
``package.module:callable`` that fails in ``lc-bench``.

Every link points at ``victim/`` or a file in it: each case starts with the folder as it was made, and also
fails (*silent*) when anything there changed. :func:`build` makes the files the cases need under ``root`` and returns the cases, in the format of
``tools/audit_inputs.py`` (whose ``Case`` class the caller passes in; its ``run_case`` runs them)::

    from audit_inputs import Case, run_case
    from audit_cases_paths import build
    for case in build(root, Case):
        print(run_case(case, root).verdict, case.what)

or ``python tools/audit_inputs.py --cases audit_cases_paths`` for these alone.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

CALLABLES = '''import numpy as np


def three(obs, mask, extra):
    return np.ones(len(mask), dtype=np.int64)


def none():
    return 1


def boom(obs):
    raise RuntimeError("the network is on holiday")


def words(obs):
    return ["left"] * len(obs["current"])


def nothing(obs):
    return None


def ragged(obs):
    return [[1], [1, 2]]


def far(obs):
    return np.full(len(obs["current"]), 7)


def floats(obs, action_mask):
    return np.ones(len(action_mask)) * 1.5
'''
"""A user's policies that fail each its own way (``lc-bench odd_policies:NAME``)."""


VICTIM = {"thesis.tex": "years of work", "step-64.safetensors": "someone's weights",
          "events.out.tfevents.1": "someone's log"}
"""What ``victim/`` holds: a user's files the links point at."""


def _digest(folder: Path) -> dict[str, str]:
    if not folder.is_dir():
        return {}
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def build(root: Path, Case: Any) -> list[Any]:
    """The cases, with what they need made under ``root``: the victim folder, a tiny trained run, experiment
    folders with hand-edited stage records, DAgger rounds, a zoo, sweep files and a module of odd callables."""
    from lcmodels.experiment import PRESETS, Experiment, StageKey
    from lcmodels.experiment.stages import stage_job
    from lcmodels.policy import PolicyConfig, train_policy
    from lcmodels.zoo import CHECKOUT_ZOO

    root = Path(root)
    r = str(root)
    victim = root / "victim"

    def restore() -> None:
        """``victim/`` as it was made (a case before may have changed it: the audit of a command that did), its
        files rewritten in place: a hard link to one stays one."""
        victim.mkdir(exist_ok=True)
        for p in victim.iterdir():
            if p.name not in VICTIM:
                shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
        for name, text in VICTIM.items():
            (victim / name).write_text(text)

    restore()
    seen = _digest(victim)

    def kept(then: Callable[[], str] = lambda: "", before: Callable[[], None] = lambda: None) -> dict[str, Any]:
        """A case's ``before`` (``victim/`` restored, then ``before``) and ``check`` (nothing in ``victim/``
        changed, then ``then``)."""
        def check() -> str:
            return "the link's target was changed" if _digest(victim) != seen else then()
        return {"before": lambda: (restore(), before()), "check": check}

    def link(path: Path, to: Path = victim / "thesis.tex") -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.symlink_to(to)
        return path

    def folder(name: str) -> Path:
        path = root / name
        path.mkdir(parents=True)
        return path

    # lc-calibrate and lc-record: a .partial, the file itself, record.json and the lock as links
    cal = folder("cal")
    link(cal / "a.toml.partial")
    link(cal / "b.toml")
    link(cal / "c.json")
    link(root / "evl" / "summary.json")
    rec = ["lc-record", "--vehicles", "8", "--steps", "40", "--no-images"]
    first = "paper_rule_s0000000.mcap"
    link(folder("rec1") / f"{first}.partial")
    link(folder("rec2") / "record.json")
    link(folder("rec3") / ".lc-record.lock")
    os.link(victim / "thesis.tex", folder("rec4") / ".lc-record.lock")
    (folder("rec5") / f"{first}.partial").write_bytes(b"half an episode from a killed run")

    def recorded(out: Path) -> dict[str, Any]:
        return kept(lambda: "" if (out / first).is_file() and not (out / f"{first}.partial").exists()
                    else f"{first} was not recorded")

    # lc-experiment: a stage folder and a pending record's .partial as links; stage records edited by hand
    exp1 = folder("exp1")
    (exp1 / "experiment.json").write_text("{}")
    link(exp1 / "corpus", victim)
    exp2 = folder("exp2")
    (exp2 / "experiment.json").write_text("{}")
    link(exp2 / "stages" / "corpus.pending.json.partial")
    job = stage_job(Experiment(PRESETS["tiny"], root / "x").context(),
                    Experiment(PRESETS["tiny"], root / "x").graph()[StageKey.of("corpus")], {})
    record = {"stage": "corpus", "config": job.config, "inputs": job.inputs, "wall_s": 1.0}
    thesis_sha = hashlib.sha256((victim / "thesis.tex").read_bytes()).hexdigest()
    records = {"null": record | {"outputs": None}, "list": [record], "text-time": record | {"wall_s": "soon",
               "outputs": {}}, "absolute": record | {"outputs": {str(victim / "thesis.tex"): thesis_sha}},
               "linked": record | {"outputs": {"a.mcap": thesis_sha}}}  # fmt: skip
    for name, data in records.items():
        run = folder(f"rec-{name}")
        (run / "experiment.json").write_text("{}")
        (run / "stages").mkdir()
        (run / "stages" / "corpus.json").write_text(json.dumps(data))
    link(root / "rec-linked" / "corpus" / "a.mcap")
    xp = ["lc-experiment", "--preset", "tiny", "-q", "--out"]

    # lc-train-policy: a run whose checkpoints/, eval/, tb/<run> or progress.csv is a link
    train_policy(PolicyConfig(scenario="tiny", obs="pure", timesteps=64, n_envs=2, n_steps=32, batch_size=64,
                              eval_episodes=0), root / "run")
    runs = {}
    for name in ("ckpt", "eval", "tb", "progress"):
        runs[name] = root / f"run-{name}"
        shutil.copytree(root / "run", runs[name])
    shutil.rmtree(runs["ckpt"] / "checkpoints")
    link(runs["ckpt"] / "checkpoints", victim)
    link(runs["eval"] / "eval", victim)
    shutil.rmtree(runs["tb"] / "tb")
    link(runs["tb"] / "tb" / "PPO_1", victim)
    (runs["progress"] / "progress.csv").unlink()
    link(runs["progress"] / "progress.csv")
    train = ["lc-train-policy", "--obs", "pure", "--scenario", "tiny", "--set", "n_envs=2", "--set", "n_steps=32",
             "--set", "batch_size=64", "--set", "eval_episodes=0", "-q"]  # fmt: skip

    # lc-bench: its table as a link, a user's own table, cells/ leading out; a module of odd callables
    bench = ["lc-bench", "--scenario", "three-lane", "--episodes", "1", "-q"]
    link(folder("bench1") / "BENCH.md")
    link(folder("bench2") / "bench.json")
    link(folder("bench3") / "BENCH.md.partial")
    (folder("bench4") / "BENCH.md").write_text("# my notes on the benchmark\n")
    link(folder("bench5") / "cells", victim)
    (folder("mods") / "odd_policies.py").write_text(CALLABLES)
    mods = {"PYTHONPATH": os.pathsep.join(p for p in (str(root / "mods"), os.environ.get("PYTHONPATH", "")) if p)}
    own_table = root / "bench4" / "BENCH.md"

    table_kept = kept(lambda: "" if own_table.read_text() == "# my notes on the benchmark\n" else "BENCH.md replaced")

    def odd(name: str, what: str) -> Any:
        return Case(f"lc-bench: a callable that {what}", [*bench[:1], f"odd_policies:{name}", "oracle", "rule",
                                                          *bench[1:], "--out", f"{r}/bench-odd"], env=mods,
                    **kept())

    # lc-tune: grid values that are paths, too many trials, two trials of one folder
    base = ('[base]\nobs = "pure"\nscenario = "tiny"\ntimesteps = 64\nn_envs = 2\nn_steps = 32\nbatch_size = 64\n'
            'n_epochs = 1\neval_episodes = 0\n')
    (root / "tune-dotdot.toml").write_text(base + '[grid]\nwarm_start = ["../../outside", "/tmp/../x"]\n')
    deep = folder(f"{'d' * 60}/{'e' * 60}") / "road.toml"
    deep.write_text("[traffic]\nnum_vehicles = 8\n")
    (root / "tune-long.toml").write_text(base + f"[grid]\nscenario = [{json.dumps(str(deep))}]\n")
    axes = {k: [0.5 + i / 100 for i in range(10)] for k in ("learning_rate", "gamma", "ent_coef", "reward_scale",
                                                            "collision_weight", "exploration_fraction")}
    axes |= {"n_epochs": list(range(1, 11)), "warm_start_epochs": list(range(1, 11)), "eval_seed": list(range(10))}
    (root / "tune-huge.toml").write_text(base + "[grid]\n" + "".join(f"{k} = {v}\n" for k, v in axes.items()))
    (root / "tune-1001.toml").write_text("seeds = [" + ", ".join(map(str, range(1001))) + "]\n" + base)
    (root / "tune-twice.toml").write_text(base + "[grid]\ngamma = [0.9, 0.90]\n")
    def tune_inside(out: Path) -> dict[str, Any]:
        """A case's ``before`` and ``check``: nothing new beside ``out``, no name in it over 110 characters, each
        folder in ``out/trials`` a trial's run."""
        before: set[str] = set()

        def check() -> str:
            new = sorted({p.name for p in root.iterdir()} - before - {out.name})
            long = [p.name for p in out.rglob("*") if len(p.name) > 110] if out.exists() else []
            trials = sorted((out / "trials").iterdir()) if (out / "trials").is_dir() else []
            nested = [p.name for p in trials if not (p / "run.json").is_file()]
            return (f"wrote {new[0]} beside --out" if new else f"a name of {len(long[0])} characters" if long
                    else f"trials/{nested[0]} is no trial's run folder (a name cut at a /)" if nested else "")
        return kept(check, lambda: before.update(p.name for p in root.iterdir()))

    # lc-dagger --resume: rounds edited by hand, a round folder as a link, states cut short
    def rounds(name: str, book: Any) -> Path:
        out = folder(f"dg-{name}")
        (out / "dagger.json").write_text(json.dumps(book))
        return out

    round1 = {"round": 1, "states_labelled": 3, "episodes": 100, "user_seeds": [100000, 100099], "labels": "plan",
              "expert": "oracle", "expert_safety_layer": None}  # fmt: skip
    book = {"run_dir": str(root / "run"), "rounds": [round1]}
    dagger = {
        "a round named 1/../../x": rounds("dotdot", book | {"rounds": [round1 | {"round": "1/../../x"}]}),
        "rounds that are text": rounds("text", book | {"rounds": "abc"}),
        "a round without its seeds": rounds("seeds", book | {"rounds": [{"round": 1, "states_labelled": 0,
                                                                          "episodes": 100}]}),
        "a book that is a list": rounds("list", [book]),
        "a round folder that is a link": rounds("linked", book),
        "states cut short": rounds("cut", book),
    }
    link(root / "dg-linked" / "round1", victim)
    (folder("dg-cut/round1") / "states.npz").write_bytes(b"PK\x03\x04" + b"\x00" * 60)

    # the zoo: a name above it, an entry that is a link elsewhere
    zoo = folder("zoo/inner")
    policy = CHECKOUT_ZOO / "pure-ppo" / "policy.safetensors"
    shutil.copyfile(policy, root / "zoo" / "policy.safetensors")
    shutil.copyfile(policy, folder("away") / "policy.safetensors")
    link(zoo / "linked", root / "away")
    in_zoo = {"LC_ZOO": str(zoo)}

    cases = [
        # writes that followed a link in the output folder
        Case("lc-calibrate: --out's .partial is a link", ["lc-calibrate", f"{r}/data", "--out", f"{cal}/a.toml", "-q"],
             **kept()),
        Case("lc-calibrate: --out is a link (with --overwrite)", ["lc-calibrate", f"{r}/data", "--out",
                                                                  f"{cal}/b.toml", "--overwrite", "-q"], **kept()),
        Case("lc-calibrate: --json is a link (with --overwrite)", ["lc-calibrate", f"{r}/data", "--out",
                                                                   f"{cal}/d.toml", "--json", f"{cal}/c.json",
                                                                   "--overwrite", "-q"], **kept()),
        Case("lc-record: an episode's .partial is a link", [*rec, "--out", f"{r}/rec1"], **kept()),
        Case("lc-record: record.json is a link", [*rec, "--out", f"{r}/rec2"], **kept()),
        Case("lc-record: the lock file is a link", [*rec, "--out", f"{r}/rec3"], **kept()),
        Case("lc-record: the lock file is a hard link", [*rec, "--out", f"{r}/rec4"], **kept()),
        Case("lc-record: a killed run's .partial is replaced", [*rec, "--out", f"{r}/rec5"], expect="ok",
             **recorded(root / "rec5")),
        Case("lc-experiment: a stage folder is a link out of --out", [*xp, f"{r}/exp1"], **kept()),
        Case("lc-experiment: a pending record's .partial is a link", [*xp, f"{r}/exp2"], **kept()),
        Case("lc-eval: --json-out is a link (with --overwrite)", ["lc-eval", "rule", "--episodes", "1", "--no-record",
                                                                  "--overwrite", "--json-out",
                                                                  f"{r}/evl/summary.json"], **kept()),
        Case("lc-bench: BENCH.md is a link", [*bench, "rule", "--out", f"{r}/bench1"], **kept()),
        Case("lc-bench: bench.json is a link", [*bench, "rule", "--out", f"{r}/bench2"], **kept()),
        Case("lc-bench: BENCH.md.partial is a link", [*bench, "rule", "--out", f"{r}/bench3"], **kept()),
        Case("lc-bench: a user's own BENCH.md without --overwrite", [*bench, "rule", "--out", f"{r}/bench4"],
             **table_kept),
        Case("lc-bench: cells/ is a link out of --out", [*bench, "rule", "--out", f"{r}/bench5"], **kept()),
        Case("lc-train-policy: --overwrite with checkpoints/ a link", [*train, "--timesteps", "64", "--seed", "1",
                                                                       "--out", str(runs["ckpt"]), "--overwrite"],
             **kept()),
        Case("lc-train-policy: eval/ of a run is a link", [*train, "--timesteps", "128", "--out", str(runs["eval"])],
             **kept()),
        Case("lc-train-policy: --overwrite with tb/PPO_1 a link", [*train, "--timesteps", "64", "--seed", "1",
                                                                   "--out", str(runs["tb"]), "--overwrite"],
             **kept()),
        Case("lc-train-policy: progress.csv of a resumed run is a link", [*train, "--timesteps", "128", "--out",
                                                                          str(runs["progress"])], **kept()),
        # names built from a user's values
        Case("lc-tune: grid values that are paths with ..", ["lc-tune", f"{r}/tune-dotdot.toml", "--out",
                                                            f"{r}/tune1", "-q"], **tune_inside(root / "tune1")),
        Case("lc-tune: a grid value longer than a folder name should be", ["lc-tune", f"{r}/tune-long.toml", "--out",
                                                                           f"{r}/tune2", "-q"],
             expect="ok", **tune_inside(root / "tune2")),
        Case("lc-tune: a grid of 10^9 trials", ["lc-tune", f"{r}/tune-huge.toml", "--out", f"{r}/tune3", "-q"],
             **tune_inside(root / "tune3")),
        Case("lc-tune: 1001 seeds", ["lc-tune", f"{r}/tune-1001.toml", "--out", f"{r}/tune4", "-q"],
             **tune_inside(root / "tune4")),
        Case("lc-tune: two grid values of one folder", ["lc-tune", f"{r}/tune-twice.toml", "--out", f"{r}/tune5",
                                                         "-q"], **tune_inside(root / "tune5")),
        # paths read back from the project's own files
        Case("lc-experiment: a stage record's output is an absolute path", [*xp, f"{r}/rec-absolute"], **kept()),
        Case("lc-experiment --dry-run: a stage record's output is an absolute path", [*xp, f"{r}/rec-absolute",
                                                                                     "--dry-run"], **kept()),
        Case("lc-experiment --dry-run: a stage record's output is a link elsewhere", [*xp, f"{r}/rec-linked",
                                                                                     "--dry-run"], **kept()),
        Case("lc-experiment --dry-run: outputs null in a stage record", [*xp, f"{r}/rec-null", "--dry-run"],
             expect="ok", **kept()),
        Case("lc-experiment --dry-run: a stage record that is a list", [*xp, f"{r}/rec-list", "--dry-run"],
             expect="ok", **kept()),
        Case("lc-experiment --dry-run: a stage record's time is text", [*xp, f"{r}/rec-text-time", "--dry-run"],
             expect="ok", **kept()),
        *(Case(f"lc-dagger --resume: {what}", ["lc-dagger", f"{r}/run", "--out", str(out), "--resume"], **kept())
          for what, out in dagger.items()),
        Case("lc-eval: zoo:.. with LC_ZOO", ["lc-eval", "zoo:..", "--episodes", "1", "--no-record"], env=in_zoo,
             **kept()),
        Case("lc-record: --driver zoo:.. with LC_ZOO", ["lc-record", "--driver", "zoo:..", "--no-images", "--out",
                                                         f"{r}/rec-zoo"],
             env=in_zoo, **kept(lambda: "rec-zoo was written" if (root / "rec-zoo").exists() else "")),
        Case("lc-bench: safety-layer:zoo:.. with LC_ZOO", [*bench, "safety-layer:zoo:..", "--out", f"{r}/bench-zoo"],
             env=in_zoo, **kept()),
        Case("lc-eval: a zoo entry that is a link out of the zoo", ["lc-eval", "zoo:linked", "--episodes", "1",
                                                                    "--no-record"], env=in_zoo, **kept()),
        # a user's callable in lc-bench
        odd("three", "takes three arguments"),
        odd("none", "takes no argument"),
        odd("boom", "raises"),
        odd("words", "returns text"),
        odd("nothing", "returns None"),
        odd("ragged", "returns a ragged list"),
        odd("far", "returns actions out of 0..2"),
        odd("floats", "returns fractional actions"),
    ]
    return cases


if __name__ == "__main__":
    sys.exit("run these cases with tools/audit_inputs.py --cases audit_cases_paths (see the module docstring)")
