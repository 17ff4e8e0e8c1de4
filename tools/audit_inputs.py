"""Feed the command lines bad input and say how each case ends: a clean refusal, a traceback, or a silent
wrong result. A maintenance check, not a test: it runs every command as a user would (a process each).

    python tools/audit_inputs.py                    # the table and the counts on stdout
    python tools/audit_inputs.py --markdown FILE    # the same table as Markdown
    python tools/audit_inputs.py --cases audit_cases_paths   # one module's cases alone

A case is *clean* when the command exits non-zero with one ``prog: error: ...`` line (argparse's usage
line before it allowed) and no traceback, and its extra check holds (nothing written, nothing replaced, a
crafted file's code not run); *traceback* when a Python traceback reaches the user; *silent* when the
command exits 0 where it should refuse, or its extra check fails. Cases that must succeed (the same
recording twice, byte for byte) count as *correct* or *silent*.
"""

from __future__ import annotations

import argparse
import base64
import dataclasses
import hashlib
import importlib
import json
import os
import pickle
import re
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the case modules beside this script

ENTRY = {
    "lc-record": "lccli.record:record_main",
    "lc-train-policy": "lccli.policy:train_policy_main",
    "lc-train-predictor": "lccli.predictor:train_predictor_main",
    "lc-eval": "lccli.evaluate:eval_main",
    "lc-experiment": "lccli.experiment:experiment_main",
    "lc-view": "lccli.view:main",
    "lc-import": "lccli.importer:main",
    "lc-calibrate": "lccli.calibrate:main",
    "lc-bench": "lccli.bench:main",
    "lc-tune": "lccli.tune:main",
    "lc-dagger": "lccli.dagger:main",
}


@dataclasses.dataclass
class Case:
    what: str
    argv: list[str]
    expect: str = "refuse"  # or "ok"
    check: Callable[[], str] | None = None
    """Returns "" when the extra condition holds, else what went wrong."""
    env: dict[str, str] | None = None
    before: Callable[[], None] | None = None


@dataclasses.dataclass
class Outcome:
    case: Case
    verdict: str
    rc: int
    message: str
    seconds: float


def _command(argv: list[str]) -> list[str]:
    prog, rest = argv[0], argv[1:]
    module, main = ENTRY[prog].split(":")
    return [sys.executable, "-c", f"import sys; sys.argv[0] = {prog!r}; from {module} import {main}; "
            f"raise SystemExit({main}())", *rest]


def run_case(case: Case, cwd: Path) -> Outcome:
    if case.before is not None:
        case.before()
    env = {**os.environ, **(case.env or {})}
    for key, value in (case.env or {}).items():
        if value == "":
            env.pop(key, None)
    t0 = time.perf_counter()
    proc = subprocess.run(_command(case.argv), cwd=cwd, capture_output=True, text=True, env=env, timeout=600)
    seconds = time.perf_counter() - t0
    err = [line for line in proc.stderr.splitlines() if line.strip()]
    problem = case.check() if case.check is not None else ""
    last = err[-1] if err else ""
    if "Traceback" in proc.stderr:
        verdict = "traceback"
    elif case.expect == "ok":
        verdict = "correct" if proc.returncode == 0 and not problem else "silent"
        last = problem or (proc.stdout.strip().splitlines() or [""])[-1]
    elif proc.returncode == 0 or problem:
        verdict = "silent"
        last = problem or "exit 0"
    else:
        errors = [line for line in err if ": error:" in line]
        others = [line for line in err if ": error:" not in line and not line.startswith(("usage:", " "))]
        verdict = "clean" if len(errors) == 1 and not others else "unclear"
    return Outcome(case, verdict, proc.returncode, last, seconds)


def build_cases(root: Path) -> list[Case]:
    """The cases, with the small files they need made under ``root`` (a trained tiny policy, a crafted zip)."""
    import torch
    from convert_policy import LEGACY_VERSION  # tools/: the one reader of legacy policies

    from lcdata.record import record_episode
    from lcmodels.policy import PolicyConfig, train_policy
    from lcmodels.policy.checkpoint import META_FORMAT, load_policy, read_meta
    from lcmodels.predictor import Predictor, PredictorConfig, TrajectoryTransformer
    from lcsim.config import paper_scenario

    pure_dir = root / "pure"
    # the configuration `lc-train-policy --obs pure --scenario tiny --timesteps 64 --n-envs 2 --n-steps 32
    # --eval-episodes 0` gives
    train_policy(PolicyConfig(scenario="tiny", obs="pure", timesteps=64, n_envs=2, n_steps=32, eval_episodes=0),
                 pure_dir)
    pure = pure_dir / "policy.safetensors"
    torch.manual_seed(0)
    predictor = root / "predictor.pt"
    Predictor(TrajectoryTransformer(PredictorConfig(d_model=16, ff_dim=32, num_layers=1))).save(predictor)
    marker = root / "marker.txt"
    loaded = load_policy(pure)
    model = loaded.model
    model.lc_meta = {**{k: v for k, v in read_meta(pure).items() if k not in ("format", "version")},
                     "format": META_FORMAT, "version": LEGACY_VERSION}
    clean_zip = root / "clean.zip"
    model.save(clean_zip, include=["lc_meta"])
    evil = root / "evil_policy.zip"

    class WritesMarker:
        def __reduce__(self):
            return (Path.write_text, (marker, "code ran"))

    with zipfile.ZipFile(clean_zip) as zin, zipfile.ZipFile(evil, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "data":
                record = json.loads(data)
                record["policy_class"] = {":type:": "<class 'type'>",
                                          ":serialized:": base64.b64encode(pickle.dumps(WritesMarker())).decode()}
                data = json.dumps(record).encode()
            zout.writestr(item, data)
    (root / "six_neighbours.toml").write_text("num_neighbours = 6\n")
    random_bytes = os.urandom(4096)
    (root / "random.safetensors").write_bytes(random_bytes)
    (root / "random.pt").write_bytes(random_bytes)
    (root / "random.mcap").write_bytes(random_bytes)
    (root / "short.safetensors").write_bytes(pure.read_bytes()[:10])
    config = dataclasses.replace(paper_scenario(), traffic=dataclasses.replace(paper_scenario().traffic, num_vehicles=8),
                                 time_limit_s=3.0)
    episode = record_episode(config, 0, "rule", root / "ep" / "paper_rule_s0000000.mcap", writer="inline").path
    (root / "ten_bytes.mcap").write_bytes(episode.read_bytes()[:10])
    (root / "empty").mkdir()
    (root / "a_file").write_text("not a directory")
    (root / "existing.json").write_text("{}")
    (root / "bad_config.toml").write_text("[policy]\ngama = 0.9\n")
    (root / "wide_wander.toml").write_text("[traffic]\nnum_vehicles = 8\nlane_wander_m = 0.6\n")
    (root / "bad_recipe.toml").write_text('name = "bad_recipe"\nrow = "ppo-pure"\n[train]\ntimestep = 5\n')
    (root / "x_tracks.csv").write_text("frame,id,x\n1,1,0.5\n")
    (root / "fcd.xml").write_text("<fcd-export><timestep time='0.00'><vehicle id='a' x='1'")
    (root / "existing.rrd").write_text("a viewer file somebody made")
    foreign = root / "foreign"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("years of work")
    other_run = root / "other_run"
    shutil.copytree(pure_dir, other_run)
    corrupt = root / "corrupt_run"
    shutil.copytree(pure_dir, corrupt)
    (corrupt / "checkpoints" / "latest.json").write_text('{"timesteps": 64,')

    def not_written(*paths: Path) -> Callable[[], str]:
        return lambda: "; ".join(f"{p.name} was written" for p in paths if p.exists())

    def no_marker() -> str:
        return "the crafted file's code ran" if marker.exists() else ""

    def unchanged(path: Path) -> dict[str, Callable]:
        """A case's ``before`` and ``check``: the file's SHA-256 taken just before the case runs, compared after."""
        seen: dict[str, str] = {}

        def before() -> None:
            seen["sha"] = hashlib.sha256(path.read_bytes()).hexdigest()

        def check() -> str:
            return "" if hashlib.sha256(path.read_bytes()).hexdigest() == seen["sha"] else f"{path.name} was replaced"

        return {"before": before, "check": check}

    def same_bytes(a: Path, b: Path) -> Callable[[], str]:
        def check() -> str:
            fa, fb = sorted(a.glob("*.mcap")), sorted(b.glob("*.mcap"))
            same = [x.read_bytes() == y.read_bytes() for x, y in zip(fa, fb, strict=False)]
            return "" if fa and len(fa) == len(fb) and all(same) else "the two recordings differ"
        return check

    foreign_kept = lambda: "" if [p.name for p in foreign.iterdir()] == ["thesis.tex"] else "files in --out changed"  # noqa: E731
    rec = ["lc-record", "--vehicles", "8", "--steps", "40"]
    tiny_train = ["lc-train-policy", "--scenario", "tiny", "--timesteps", "64", "--set", "n_envs=2", "--set",
                  "eval_episodes=0", "-q"]
    r = str(root)
    return [
        # lc-record
        Case("lc-record: zero episodes", [*rec, "--episodes", "0", "--out", f"{r}/r1"], check=not_written(root / "r1")),
        Case("lc-record: negative seed", [*rec, "--seed", "-1", "--out", f"{r}/r1"], check=not_written(root / "r1")),
        Case("lc-record: unknown scenario", [*rec, "--scenario", "town06", "--out", f"{r}/r1"]),
        Case("lc-record: impossible traffic", ["lc-record", "--vehicles", "100000", "--out", f"{r}/r1"]),
        Case("lc-record: --out is a file", [*rec, "--out", f"{r}/a_file"]),
        Case("lc-record: --out cannot be made", [*rec, "--out", f"{r}/a_file/sub"]),
        Case("lc-record: zero workers", [*rec, "--workers", "0", "--out", f"{r}/r1"]),
        Case("lc-record: missing policy", ["lc-record", "--driver", f"policy:{r}/missing.safetensors", "--out",
                                           f"{r}/r1"]),
        Case("lc-record: crafted pickle policy", ["lc-record", "--driver", f"policy:{evil}", "--out", f"{r}/r1"],
             check=no_marker),
        Case("lc-record: random-bytes policy", ["lc-record", "--driver", f"policy:{r}/random.safetensors",
                                                "--out", f"{r}/r1"]),
        Case("lc-record: policy with traffic override", ["lc-record", "--driver", f"policy:{pure}", "--vehicles", "5",
                                                         "--out", f"{r}/r1"]),
        Case("lc-record: zero lookahead horizon", ["lc-record", "--driver", f"lookahead:{pure}",
                                                   "--lookahead-horizon", "0", "--out", f"{r}/r1"]),
        Case("lc-record: planner option without planner", [*rec, "--lookahead-perceived", "--out", f"{r}/r1"]),
        Case("lc-record: bad --start-time", [*rec, "--start-time", "yesterday", "--out", f"{r}/r1"]),
        Case("lc-record: same command twice gives the same bytes", [*rec, "--episodes", "2", "--out", f"{r}/same2"],
             expect="ok", check=same_bytes(root / "same1", root / "same2"),
             before=lambda: subprocess.run(_command([*rec, "--episodes", "2", "--out", f"{r}/same1"]),
                                           capture_output=True, check=True)),
        Case("lc-record: other flags into a recorded --out", [*rec, "--steps", "41", "--episodes", "2",
                                                              "--out", f"{r}/same1"],
             **unchanged(root / "same1" / "paper_rule_s0000000.mcap")),
        # lc-train-policy
        Case("lc-train-policy: hybrid without predictor", [*tiny_train, "--obs", "hybrid", "--out", f"{r}/t1"],
             check=not_written(root / "t1")),
        Case("lc-train-policy: predictor for pure", [*tiny_train, "--obs", "pure", "--predictor", str(predictor),
                                                     "--out", f"{r}/t1"], check=not_written(root / "t1")),
        Case("lc-train-policy: random-bytes predictor", [*tiny_train, "--obs", "hybrid", "--predictor",
                                                         f"{r}/random.pt", "--out", f"{r}/t1"],
             check=not_written(root / "t1")),
        Case("lc-train-policy: missing --init-policy", [*tiny_train, "--obs", "pure", "--init-policy",
                                                        f"{r}/missing.safetensors", "--out", f"{r}/t1"],
             check=not_written(root / "t1")),
        Case("lc-train-policy: crafted pickle --init-policy", [*tiny_train, "--obs", "pure", "--init-policy",
                                                               str(evil), "--out", f"{r}/t1"],
             check=lambda: no_marker() or not_written(root / "t1")()),
        Case("lc-train-policy: empty --warm-start", [*tiny_train, "--obs", "pure", "--warm-start", f"{r}/empty",
                                                     "--out", f"{r}/t1"], check=not_written(root / "t1")),
        Case("lc-train-policy: zero timesteps without warm start", ["lc-train-policy", "--obs", "pure", "--timesteps",
                                                                    "0", "--out", f"{r}/t1"]),
        Case("lc-train-policy: negative learning rate", [*tiny_train, "--obs", "pure", "--set", "learning_rate=-1",
                                                         "--out", f"{r}/t1"]),
        Case("lc-train-policy: gamma 2", [*tiny_train, "--obs", "pure", "--set", "gamma=2", "--out", f"{r}/t1"]),
        Case("lc-train-policy: seed too large", [*tiny_train, "--obs", "pure", "--seed", "2000000", "--out", f"{r}/t1"]),
        Case("lc-train-policy: --freeze-image without --init-policy", [*tiny_train, "--obs", "image",
                                                                       "--set", "freeze_image=true", "--out", f"{r}/t1"]),
        Case("lc-train-policy: --overwrite on a directory it did not write", [*tiny_train, "--obs", "pure", "--out",
                                                                              str(foreign), "--overwrite"],
             check=foreign_kept),
        Case("lc-train-policy: another run's --out", [*tiny_train, "--obs", "pure", "--seed", "3", "--out",
                                                      str(other_run)],
             **unchanged(other_run / "policy.safetensors")),
        Case("lc-train-policy: unknown --set key", [*tiny_train, "--obs", "pure", "--set", "gama=0.9", "--out", f"{r}/t1"],
             check=not_written(root / "t1")),
        Case("lc-train-policy: --set value of the wrong type", [*tiny_train, "--obs", "pure", "--set", "n_envs=many",
                                                                "--out", f"{r}/t1"], check=not_written(root / "t1")),
        Case("lc-train-policy: --config file with an unknown field", [*tiny_train, "--obs", "pure", "--config",
                                                                      f"{r}/bad_config.toml", "--out", f"{r}/t1"],
             check=not_written(root / "t1")),
        Case("lc-train-policy: corrupt checkpoints/latest.json", [*tiny_train, "--obs", "pure", "--timesteps", "128",
                                                                  "--set", "n_steps=32", "--out", str(corrupt)]),
        # lc-eval
        Case("lc-eval: missing policy", ["lc-eval", f"{r}/missing.safetensors", "--no-record"]),
        Case("lc-eval: a directory", ["lc-eval", r, "--no-record"]),
        Case("lc-eval: crafted pickle policy", ["lc-eval", str(evil), "--episodes", "1", "--no-record"],
             check=no_marker),
        Case("lc-eval: random-bytes policy", ["lc-eval", f"{r}/random.safetensors", "--no-record"]),
        Case("lc-eval: truncated policy (10 bytes)", ["lc-eval", f"{r}/short.safetensors", "--no-record"]),
        Case("lc-eval: predictor for a pure policy", ["lc-eval", str(pure), "--predictor", str(predictor),
                                                      "--episodes", "1", "--no-record"]),
        Case("lc-eval: zero episodes", ["lc-eval", "rule", "--episodes", "0", "--no-record"]),
        Case("lc-eval: --json-out exists", ["lc-eval", "rule", "--episodes", "1", "--no-record", "--json-out",
                                            f"{r}/existing.json"], **unchanged(root / "existing.json")),
        Case("lc-eval: a policy on another road", ["lc-eval", str(pure), "--scenario", "light", "--episodes", "2",
                                                   "--no-record"], expect="ok"),
        Case("lc-eval: a road whose observation does not fit the policy", ["lc-eval", str(pure), "--scenario",
                                                                           f"{r}/six_neighbours.toml", "--no-record"]),
        Case("lc-eval: a sealed test seed", ["lc-eval", "rule", "--seed", "20000", "--episodes", "2", "--no-record"]),
        Case("lc-record: a sealed test seed", [*rec, "--seed", "3000000000", "--out", f"{r}/r9"],
             check=not_written(root / "r9")),
        Case("lc-eval: follow option without planner", ["lc-eval", str(pure), "--lookahead-follow", "rule",
                                                        "--no-record"]),
        # lc-view
        Case("lc-view: no display", ["lc-view", str(episode)], env={"DISPLAY": "", "WAYLAND_DISPLAY": ""}),
        Case("lc-view: web port out of range", ["lc-view", str(episode), "--web", "--headless", "--web-port", "99999"]),
        Case("lc-view: --save over an existing .rrd", ["lc-view", str(episode), "--save", f"{r}/existing.rrd"],
             **unchanged(root / "existing.rrd")),
        Case("lc-view: --save without .rrd", ["lc-view", str(episode), "--save", f"{r}/view.txt"]),
        Case("lc-view: truncated recording (10 bytes)", ["lc-view", f"{r}/ten_bytes.mcap", "--headless"]),
        Case("lc-view: random bytes", ["lc-view", f"{r}/random.mcap", "--headless"]),
        Case("lc-view: missing file", ["lc-view", f"{r}/missing.mcap", "--headless"]),
        # lc-train-predictor
        Case("lc-train-predictor: missing --data", ["lc-train-predictor", "--data", f"{r}/missing", "--out", f"{r}/p1"],
             check=not_written(root / "p1")),
        Case("lc-train-predictor: empty --data", ["lc-train-predictor", "--data", f"{r}/empty", "--out", f"{r}/p1"]),
        Case("lc-train-predictor: zero history", ["lc-train-predictor", "--data", f"{r}/ep", "--history", "0",
                                                  "--out", f"{r}/p1"]),
        Case("lc-train-predictor: negative time limit", ["lc-train-predictor", "--data", f"{r}/ep", "--time-limit",
                                                         "-1", "--out", f"{r}/p1"]),
        Case("lc-train-predictor: zero velocity window", ["lc-train-predictor", "--data", f"{r}/ep",
                                                          "--velocity-window", "0", "--out", f"{r}/p1"]),
        Case("lc-record: traffic whose wander leaves the lane", [*rec, "--scenario", f"{r}/wide_wander.toml",
                                                                  "--out", f"{r}/r1"], check=not_written(root / "r1")),
        # lc-experiment
        Case("lc-experiment: zero seeds", ["lc-experiment", "--seeds", "0", "--out", f"{r}/x1"]),
        Case("lc-experiment: unknown preset", ["lc-experiment", "--preset", "bogus", "--out", f"{r}/x1"]),
        Case("lc-experiment: --out is a file", ["lc-experiment", "--preset", "tiny", "--out", f"{r}/a_file"]),
        Case("lc-experiment: unknown recipe", ["lc-experiment", "--recipe", "bogus", "--out", f"{r}/x2"],
             check=not_written(root / "x2")),
        Case("lc-experiment: recipe with an unknown field", ["lc-experiment", "--recipe", f"{r}/bad_recipe.toml",
                                                             "--out", f"{r}/x2"], check=not_written(root / "x2")),
        # the zoo
        Case("lc-eval: unknown zoo policy", ["lc-eval", "zoo:bogus", "--episodes", "2", "--no-record"]),
        Case("lc-record: unknown zoo policy", ["lc-record", "--driver", "zoo:bogus", "--out", f"{r}/z1"],
             check=not_written(root / "z1")),
        Case("lc-view: unknown zoo policy", ["lc-view", "zoo:bogus", "--headless"]),
        # lc-import
        Case("lc-import: highD tracks without columns or meta", ["lc-import", "highd", f"{r}/x_tracks.csv",
                                                                 "--out", f"{r}/i1"], check=not_written(root / "i1")),
        Case("lc-import: truncated SUMO FCD", ["lc-import", "sumo-fcd", f"{r}/fcd.xml", "--out", f"{r}/i2"],
             check=not_written(root / "i2")),
        Case("lc-import: missing file", ["lc-import", "sumo-fcd", f"{r}/missing.xml", "--out", f"{r}/i3"]),
    ]


CASE_MODULES = ("audit_cases_files", "audit_cases_mcap", "audit_cases_imports", "audit_cases_paths")
"""The modules beside this script that add cases (``build(root, Case)``)."""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="audit_inputs.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--markdown", type=Path, default=None, help="also write the table as Markdown here")
    p.add_argument("-k", default="", help="only the cases whose description contains this")
    p.add_argument("--cases", choices=("inputs", *CASE_MODULES), default=None,
                   help="only the cases of this module (inputs: this file's own); the others are not even built")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="lc-audit-") as tmp:
        root = Path(tmp)
        cases = [c for c in build_cases(root) if args.k in c.what] if args.cases in (None, "inputs") else []
        for extra in CASE_MODULES:  # the later rounds' cases, by class of input
            if args.cases not in (None, extra):
                continue
            module = importlib.import_module(extra)
            (root / extra).mkdir()
            cases += [c for c in module.build(root / extra, Case) if args.k in c.what]
        outcomes = []
        for i, case in enumerate(cases, 1):
            out = run_case(case, root)
            outcomes.append(out)
            print(f"[{i}/{len(cases)}] {out.verdict:9s} {case.what}: {out.message[:150]}", flush=True)
    counts = {v: sum(o.verdict == v for o in outcomes) for v in ("clean", "correct", "unclear", "traceback", "silent")}
    print(f"\n{len(outcomes)} cases: " + ", ".join(f"{v} {n}" for v, n in counts.items()))
    if args.markdown is not None:
        lines = ["| case | command | exit | result | verdict |", "|---|---|---|---|---|"]
        for o in outcomes:
            scratch = re.compile(re.escape(tempfile.gettempdir()) + r"/lc-audit-[^/ :]+")
            shown = scratch.sub("…", " ".join(o.case.argv))
            msg = scratch.sub("…", o.message).replace("|", "\\|")
            lines.append(f"| {o.case.what} | `{shown}` | {o.rc} | {msg[:160]} | {o.verdict} |")
        lines.append("")
        lines.append(f"{len(outcomes)} cases: " + ", ".join(f"{v} {n}" for v, n in counts.items()) + ".")
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text("\n".join(lines) + "\n")
    return 0 if counts["traceback"] == counts["silent"] == counts["unclear"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
