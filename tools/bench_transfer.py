#!/usr/bin/env python
"""Does the trajectory predictor transfer to traffic it was not trained on?

One command does it all, each stage skipped when its output is already in --out (so a rerun resumes):

1. record an lcsim training corpus and a separate lcsim test corpus (``lc-record --scenario corpus``,
   other seeds);
2. train one predictor per configuration and variant (``--configs``, ``--variants``: a correction and the
   input noise of training) on the training corpus, or take the given ``--checkpoint`` files instead;
3. simulate SUMO highway episodes and import them into the corpus layout (``tools/sumo_highway.py``);
4. evaluate every predictor on (a) the lcsim test corpus and (b) the SUMO episodes, next to constant
   velocity (CV) and constant acceleration (CA) on the very same windows: ADE, FDE and RMSE at 0.5 s,
   1 s and 3 s where the future reaches, and the model's FDE at the last horizon relative to CV's.

    python tools/bench_transfer.py --out runs/transfer                      # about 10 minutes on 2 cores
    python tools/bench_transfer.py --out runs/transfer --json > transfer.json
    python tools/bench_transfer.py --out runs/t2 --checkpoint runs/predictor/predictor.pt   # evaluate only

The figures go to OUT/transfer.json; the table to stdout (or the JSON with --json). Needs
``pip install -e ".[sumo]"`` for the SUMO part.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import math
import pathlib
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

PROG = "bench_transfer.py"
TOOLS = pathlib.Path(__file__).resolve().parent
if str(TOOLS) not in sys.path:  # sumo_highway.py beside this file, also when imported by the tests
    sys.path.insert(0, str(TOOLS))

import sumo_highway  # noqa: E402

from lccli.common import non_negative_int, positive_float, positive_int  # noqa: E402

__all__ = ["Setup", "evaluate_checkpoint", "format_table", "main", "parse_config", "parse_variant", "run", "source_state"]

log = logging.getLogger("bench_transfer")

CORRECTIONS = ("plain", "bounded", "gated", "bounded-gated")
BASES = ("constant-velocity", "lane-aware")  # PredictorConfig.base (lcmodels is imported lazily)


def parse_variant(text: str) -> tuple[str, float, int | None, str | None]:
    """``"gated"`` -> ``("gated", 0.0, None, None)``; ``"gated:0.003"`` -> trained with 3 mm of input noise;
    ``"gated:0:1"`` -> no noise, the constant-velocity base from the last step's difference (``velocity_window``
    1; None: PredictorConfig's default); ``"gated:0.003::lane-aware"`` -> the lane-aware base
    (``PredictorConfig.base``; None: the default)."""
    correction, _, rest = text.partition(":")
    noise_text, _, rest = rest.partition(":")
    window_text, _, base_text = rest.partition(":")
    base: str | None = base_text or None
    if base is not None and base not in BASES:
        raise ValueError(f"unknown base {base!r} in variant {text!r} (choose from {', '.join(BASES)})")
    window: int | None = None
    if window_text:
        if not window_text.isdigit() or int(window_text) < 1:
            raise ValueError(f"variant {text!r}: the velocity window after the second ':' must be an integer >= 1")
        window = int(window_text)
    if correction not in CORRECTIONS:
        raise ValueError(f"unknown correction {correction!r} in variant {text!r} (choose from {', '.join(CORRECTIONS)})")
    try:
        noise = float(noise_text) if noise_text else 0.0
    except ValueError:
        noise = -1.0
    if not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"variant {text!r}: the input noise after ':' must be a number of metres >= 0")
    return correction, noise, window, base


def parse_config(text: str) -> tuple[int, int, int]:
    """``"20+60"`` -> ``(20, 60, stride)``, ``"20+60/5"`` -> stride 5; stride 1 for 10 future steps or fewer,
    else 5 (the strides ``lc-train-predictor``'s examples use)."""
    head, _, stride_text = text.partition("/")
    h_text, plus, f_text = head.partition("+")
    try:
        if not plus:
            raise ValueError
        h, f = int(h_text), int(f_text)
        stride = int(stride_text) if stride_text else (1 if f <= 10 else 5)
    except ValueError:
        raise ValueError(f"a configuration is HISTORY+FUTURE[/STRIDE] in steps, such as 20+60/5; got {text!r}") from None
    if h < 3 or f < 1 or stride < 1:
        raise ValueError(f"configuration {text!r}: history must be >= 3 steps, future and stride >= 1")
    return h, f, stride


@dataclass(frozen=True, slots=True, kw_only=True)
class Setup:
    """Sizes of one run (the command's flags)."""

    configs: tuple[str, ...] = ("10+10", "20+60/5")
    variants: tuple[str, ...] = ("gated:0:1", "gated", "gated:0.003")
    lcsim_episodes: int = 16
    lcsim_exact_episodes: int = 16
    lcsim_test_episodes: int = 4
    lcsim_seed: int = 100
    lcsim_test_seed: int = 50_000
    sumo_episodes: int = 4
    sumo_seed: int = 1000
    max_train_windows: int = 60_000
    max_epochs: int = 20
    train_time_limit_s: float = 75.0
    max_eval_windows: int = 20_000
    threads: int = 1
    seed: int = 0
    progress: bool = True


def _stage(msg: str, quiet: bool) -> None:
    if not quiet:
        print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def record_lcsim(out: pathlib.Path, episodes: int, seed: int, quiet: bool, exact_episodes: int = 0) -> pathlib.Path:
    """``lc-record --scenario corpus`` into ``out`` unless it holds that many episodes already; with
    ``exact_episodes``, that many more of the same scenario with exact-IDM traffic (``traffic.human_like =
    false``, seeds from ``seed + 100000``), so that the corpus mixes two driving styles."""
    if len(list(out.glob("*.mcap"))) >= episodes + exact_episodes:
        return out
    from lccli.record import record_main
    from lcsim.config import corpus_scenario

    runs = [("corpus", episodes, seed)]
    if exact_episodes:
        exact = corpus_scenario()
        exact = dataclasses.replace(exact, traffic=dataclasses.replace(exact.traffic, human_like=False))
        out.parent.mkdir(parents=True, exist_ok=True)
        path = out.parent / "corpus-exact-idm.toml"
        path.write_text(exact.to_toml())
        runs.append((str(path), exact_episodes, seed + 100_000))
    for scenario, count, first in runs:
        with contextlib.redirect_stdout(sys.stderr):  # stdout carries only the table or the JSON
            rc = record_main(["--scenario", scenario, "--driver", "autopilot", "--episodes", str(count), "--seed",
                              str(first), "--out", str(out), "--overwrite"])  # fmt: skip
        if rc != 0:
            raise RuntimeError(f"lc-record failed (exit {rc}) writing {out}")
    return out


def make_sumo(out: pathlib.Path, episodes: int, seed: int, quiet: bool) -> pathlib.Path:
    """SUMO episodes imported into ``out/corpus`` unless there already."""
    corpus = out / "corpus"
    if corpus.is_dir() and len(list(corpus.glob("*.mcap"))) >= episodes:
        return corpus
    files = sumo_highway.generate(out / "sumo", episodes, seed,
                                  progress=None if quiet else lambda d, n: _stage(f"  sumo episode {d}/{n}", quiet))  # fmt: skip
    sumo_highway.import_fcd(files, corpus, overwrite=True)
    return corpus


def train_one(data: pathlib.Path, out: pathlib.Path, config: str, variant: str, setup: Setup) -> pathlib.Path:
    """Train one predictor (unless ``out/predictor.pt`` exists); its checkpoint."""
    ckpt = out / "predictor.pt"
    if ckpt.is_file():
        return ckpt
    from lcdata.corpus import load_tracks
    from lcmodels.predictor import PredictorConfig, TrainConfig, train_predictor

    h, f, stride = parse_config(config)
    correction, noise, window, base = parse_variant(variant)
    extra: dict[str, Any] = {} if window is None else {"velocity_window": window}
    if base is not None:
        extra["base"] = base
    cfg = TrainConfig(model=PredictorConfig(history_steps=h, future_steps=f, correction=correction, **extra), stride=stride,
                      max_train_windows=setup.max_train_windows, max_epochs=setup.max_epochs,
                      time_limit_s=setup.train_time_limit_s, input_noise_m=noise,
                      num_threads=setup.threads, seed=setup.seed, progress=setup.progress, tensorboard=False)  # fmt: skip
    train_predictor(load_tracks(data), cfg, out)
    return ckpt


def evaluate_checkpoint(checkpoint: pathlib.Path, data: pathlib.Path, *, stride: int | None = None,
                        max_windows: int | None = 20_000, seed: int = 0) -> dict[str, Any]:  # fmt: skip
    """A predictor and the CV/CA baselines on the windows of a corpus folder.

    Windows have the checkpoint's horizons and ``stride`` (default: the stride it was trained with); at
    most ``max_windows`` of them, a deterministic subsample. Returns ``{"windows": n, "stride": s,
    "model" | "constant_velocity" | "constant_acceleration": summary}`` (summaries as
    :func:`lcmodels.predictor.metrics.summary`, horizons included), ``ValueError`` on bad input.
    """
    import torch

    from lcdata.corpus import Corpus, WindowOptions, load_tracks
    from lcmodels.predictor import load_model
    from lcmodels.predictor.train import evaluate

    model, extra = load_model(checkpoint)
    c = model.config
    if stride is None:
        stride = int(extra.get("train_config", {}).get("stride", 1))
    corpus = Corpus.from_tracks(load_tracks(data), WindowOptions(
        history_steps=c.history_steps, future_steps=c.future_steps, num_neighbours=c.num_neighbours, stride=stride))  # fmt: skip
    if len(corpus) == 0:
        raise ValueError(f"{data}: no window of {c.history_steps}+{c.future_steps} steps (episodes too short?)")
    rows = np.arange(len(corpus))
    if max_windows is not None and len(rows) > max_windows:
        rows = np.sort(np.random.default_rng(seed).choice(rows, size=max_windows, replace=False))
    batch = corpus.gather(rows)
    with torch.no_grad():
        result = evaluate(model, batch, miss_threshold_m=0.5)
    result.pop("lane_change", None)
    return {"windows": len(rows), "stride": stride, "history_steps": c.history_steps,
            "future_steps": c.future_steps, "correction": c.correction, **result}  # fmt: skip


def source_state() -> dict[str, Any]:
    """The commit of the code and whether the simulator (``lcsim/``) differs from it: traffic recorded
    from a working tree with changes to the simulator is not the committed simulator's."""
    import subprocess

    root = TOOLS.parent

    def git(*args: str) -> str:
        done = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=False)
        return done.stdout.strip() if done.returncode == 0 else ""

    return {"commit": git("rev-parse", "HEAD") or None, "lcsim_changed": bool(git("status", "--porcelain", "--", "lcsim"))}


def run(out: pathlib.Path, setup: Setup, checkpoints: Sequence[pathlib.Path] = (), *,
        quiet: bool = False, lcsim_train: pathlib.Path | None = None, lcsim_test: pathlib.Path | None = None,
        sumo: pathlib.Path | None = None) -> dict[str, Any]:  # fmt: skip
    """Everything the command does; returns (and writes to ``out/transfer.json``) the figures."""
    import torch

    torch.set_num_threads(setup.threads)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    models: dict[str, pathlib.Path] = {}
    recorded = (not checkpoints and lcsim_train is None) or lcsim_test is None  # lcsim traffic from this tree
    if checkpoints:
        for ckpt in checkpoints:
            models[ckpt.parent.name or ckpt.stem] = ckpt
    else:
        train_data = lcsim_train
        if train_data is None:
            _stage(f"recording the lcsim training corpus ({setup.lcsim_episodes} episodes of the default traffic, "
                   f"{setup.lcsim_exact_episodes} of exact IDM)", quiet)
            train_data = record_lcsim(out / "lcsim-train", setup.lcsim_episodes, setup.lcsim_seed, quiet,
                                      setup.lcsim_exact_episodes)
        for config in setup.configs:
            for variant in setup.variants:
                h, f, _ = parse_config(config)
                correction, noise, window, base = parse_variant(variant)
                name = f"{h}+{f}-{correction}" + (f"-noise{noise * 1000:g}mm" if noise else "") + (
                    f"-window{window}" if window is not None else "") + (f"-{base}" if base is not None else "")
                _stage(f"training {name}", quiet)
                models[name] = train_one(train_data, out / "models" / name, config, variant, setup)
    if lcsim_test is None:
        _stage(f"recording the lcsim test corpus ({setup.lcsim_test_episodes} episodes)", quiet)
        lcsim_test = record_lcsim(out / "lcsim-test", setup.lcsim_test_episodes, setup.lcsim_test_seed, quiet)
    if sumo is None:
        _stage(f"simulating and importing {setup.sumo_episodes} SUMO episodes", quiet)
        sumo = make_sumo(out / "sumo", setup.sumo_episodes, setup.sumo_seed, quiet)
    result: dict[str, Any] = {"setup": {k: getattr(setup, k) for k in Setup.__slots__},  # type: ignore[attr-defined]
                              "data": {"lcsim": str(lcsim_test), "sumo": str(sumo)}, "source": source_state() if recorded else "corpora given",
                              "models": {}}  # fmt: skip
    for name, ckpt in models.items():
        result["models"][name] = {"checkpoint": str(ckpt)}
        for data_name, data in (("lcsim", lcsim_test), ("sumo", sumo)):
            _stage(f"evaluating {name} on {data_name}", quiet)
            result["models"][name][data_name] = evaluate_checkpoint(ckpt, data, max_windows=setup.max_eval_windows,
                                                                    seed=setup.seed)  # fmt: skip
    result["seconds"] = time.perf_counter() - started
    tmp = out / "transfer.json.partial"
    tmp.write_text(json.dumps(result, indent=1, sort_keys=True, default=str))
    tmp.replace(out / "transfer.json")
    return result


def format_table(result: dict[str, Any]) -> str:
    """Markdown table: one row per data set, configuration and predictor (CV and CA once per data set and
    configuration); ADE/FDE/RMSE at each horizon; the FDE at the last horizon relative to CV's."""
    lines = []
    header_done = False
    for data_name in ("lcsim", "sumo"):
        seen: set[tuple[int, int, int]] = set()
        for name, entry in result["models"].items():
            e = entry[data_name]
            key = (e["history_steps"], e["future_steps"], e["stride"])
            labels = list(e["constant_velocity"]["horizons"])
            if not header_done:
                lines.append("| data | H+F | predictor | windows | " + " | ".join(
                    f"ADE/FDE/RMSE {t}" for t in ("0.5s", "1s", "3s")) + " | FDE at last horizon vs CV |")  # fmt: skip
                lines.append("|---" * 8 + "|")
                header_done = True
            rows = [(name, e["model"])]
            if key not in seen:
                seen.add(key)
                fit = [("CV, velocity fitted to 0.5 s", e["constant_velocity_fit"])] if "constant_velocity_fit" in e else []
                if "lane_aware" in e:
                    fit.append(("lane-aware base (analytic)", e["lane_aware"]))
                rows = [("CV", e["constant_velocity"]), *fit, ("CA", e["constant_acceleration"]), *rows]
            last = labels[-1]
            cv_fde = e["constant_velocity"]["horizons"][last]["fde"]
            for label, m in rows:
                cells = []
                for t in ("0.5s", "1s", "3s"):
                    h = m["horizons"].get(t)
                    cells.append(f"{h['ade']:.3f}/{h['fde']:.3f}/{h['rmse']:.3f}" if h else "-")
                rel = m["horizons"][last]["fde"] / cv_fde - 1 if cv_fde > 0 else float("nan")
                lines.append(f"| {data_name} | {key[0]}+{key[1]} | {label} | {e['windows']} | " + " | ".join(cells)
                             + f" | {rel:+.1%} at {last} |")  # fmt: skip
    return "\n".join(lines)


def _csv(kind: str, check: Callable[[str], Any]) -> Callable[[str], tuple[str, ...]]:
    def parse(text: str) -> tuple[str, ...]:
        items = tuple(t.strip() for t in text.split(",") if t.strip())
        if not items:
            raise argparse.ArgumentTypeError(f"expected a comma-separated list of {kind}")
        for item in items:
            try:
                check(item)
            except ValueError as exc:
                raise argparse.ArgumentTypeError(str(exc)) from None
        return items

    return parse


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        print(f"{PROG}: error: {message} (see --help)", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    d = Setup()
    p = _Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=pathlib.Path, required=True, help="working and output folder (rerun to resume)")
    p.add_argument("--checkpoint", type=pathlib.Path, action="append", default=[],
                   help="evaluate this predictor.pt (repeatable) instead of recording a corpus and training")
    p.add_argument("--configs", type=_csv("configurations", parse_config), default=d.configs,
                   help=f"HISTORY+FUTURE[/STRIDE] steps to train, comma-separated (default {','.join(d.configs)})")
    p.add_argument("--variants", type=_csv("variants", parse_variant), default=d.variants,
                   help="predictors to train for each configuration, comma-separated: CORRECTION[:NOISE_M[:WINDOW[:BASE]]], "
                   f"the correction one of {', '.join(CORRECTIONS)}, NOISE_M the std of the noise added to observed "
                   "positions in training, metres, WINDOW the steps the constant-velocity base fits its velocity "
                   "to (1: the last step's difference; empty or absent: PredictorConfig's default), BASE the "
                   f"extrapolation the correction is a residual over, one of {', '.join(BASES)} (absent: the "
                   f"default) (default {','.join(d.variants)})")
    p.add_argument("--lcsim-episodes", type=positive_int, default=d.lcsim_episodes,
                   help=f"lcsim training episodes, 100 s each (default {d.lcsim_episodes})")
    p.add_argument("--lcsim-exact-episodes", type=non_negative_int, default=d.lcsim_exact_episodes,
                   help="more training episodes with exact-IDM traffic, so that the corpus mixes two driving "
                   f"styles (0: the default traffic only; default {d.lcsim_exact_episodes})")
    p.add_argument("--lcsim-test-episodes", type=positive_int, default=d.lcsim_test_episodes,
                   help=f"lcsim test episodes, seeds of their own (default {d.lcsim_test_episodes})")
    p.add_argument("--lcsim-train", type=pathlib.Path, default=None,
                   help="an existing lcsim training corpus folder (instead of recording one)")
    p.add_argument("--lcsim-test", type=pathlib.Path, default=None, help="an existing lcsim test corpus folder")
    p.add_argument("--sumo-episodes", type=positive_int, default=d.sumo_episodes,
                   help=f"SUMO episodes, 100 s each (default {d.sumo_episodes})")
    p.add_argument("--sumo", type=pathlib.Path, default=None, help="an existing imported SUMO corpus folder")
    p.add_argument("--max-train-windows", type=positive_int, default=d.max_train_windows,
                   help=f"training windows per model (default {d.max_train_windows})")
    p.add_argument("--epochs", type=positive_int, default=d.max_epochs, help=f"maximum epochs (default {d.max_epochs})")
    p.add_argument("--train-time-limit", type=positive_float, default=d.train_time_limit_s, metavar="S",
                   help=f"stop a model's training after the epoch past this (default {d.train_time_limit_s:g} s)")
    p.add_argument("--max-eval-windows", type=positive_int, default=d.max_eval_windows,
                   help=f"windows per evaluation, a deterministic subsample (default {d.max_eval_windows})")
    p.add_argument("--threads", type=positive_int, default=d.threads, help=f"torch threads (default {d.threads})")
    p.add_argument("--seed", type=int, default=d.seed, help="training and subsampling seed (default 0)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON instead of the table")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)

    def error(msg: str) -> int:
        print(f"{PROG}: error: {' '.join(str(msg).split())}", file=sys.stderr)
        return 2

    for ckpt in args.checkpoint:
        if not ckpt.is_file():
            return error(f"--checkpoint {ckpt} does not exist")
    for name in ("lcsim_train", "lcsim_test", "sumo"):
        folder = getattr(args, name)
        if folder is not None and not (folder.is_dir() and any(folder.glob("*.mcap"))):
            return error(f"--{name.replace('_', '-')} {folder} is not a folder of .mcap episodes")
    if args.sumo is None and not sumo_highway.sumo_available():
        return error('eclipse-sumo is not installed (pip install -e ".[sumo]"), or pass --sumo FOLDER')
    if args.lcsim_episodes < 3 and not args.checkpoint:
        return error(f"--lcsim-episodes must be >= 3 (train/validation/test split by episode), got {args.lcsim_episodes}")
    logging.basicConfig(level=logging.WARNING, format=f"{PROG}: %(message)s")
    setup = Setup(configs=args.configs, variants=args.variants, lcsim_episodes=args.lcsim_episodes,
                  lcsim_exact_episodes=args.lcsim_exact_episodes,
                  lcsim_test_episodes=args.lcsim_test_episodes, sumo_episodes=args.sumo_episodes,
                  max_train_windows=args.max_train_windows, max_epochs=args.epochs,
                  train_time_limit_s=args.train_time_limit,
                  max_eval_windows=args.max_eval_windows, threads=args.threads, seed=args.seed,
                  progress=not args.quiet)  # fmt: skip
    try:
        result = run(args.out, setup, args.checkpoint, quiet=args.quiet, lcsim_train=args.lcsim_train,
                     lcsim_test=args.lcsim_test, sumo=args.sumo)
    except (ValueError, RuntimeError, OSError) as exc:
        return error(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
    if args.json:
        print(json.dumps(result, indent=1, sort_keys=True, default=str))
    else:
        print(format_table(result))
        print(f"\n{len(result['models'])} predictors, {result['seconds']:.0f} s; figures in {args.out / 'transfer.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
