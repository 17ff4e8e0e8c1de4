"""``lc-train-predictor``: build the trajectory corpus from recordings, train the transformer, report
ADE/FDE next to the constant-velocity and constant-acceleration baselines."""

from __future__ import annotations

import argparse
import functools
import json
import logging
from pathlib import Path

from lccli.common import fail, positive_int, setup_logging

TRAIN_PREDICTOR_EPILOG = """examples:
  lc-record --scenario corpus --episodes 24 --seed 100 --out runs/corpus --workers 2
  lc-train-predictor --data runs/corpus --out runs/predictor-10-10
  lc-train-predictor --data runs/corpus --history 20 --future 60 --stride 5 --out runs/predictor-20-60

outputs (in --out): predictor.pt (weights, normalisation statistics, config; loads with
torch.load(weights_only=True)), metrics.json (test-split ADE/FDE/curve/miss rate of the model,
constant velocity and constant acceleration on the same windows, and ADE/FDE/RMSE at 0.5 s, 1 s and
3 s where the future reaches; corpus statistics), tensorboard/.
"""


def train_predictor_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lc-train-predictor",
        description="Build the trajectory corpus from recorded MCAP episodes (split by episode), train the "
        "transformer predictor with early stopping, and report test ADE/FDE next to the "
        "constant-velocity and constant-acceleration baselines.",
        epilog=TRAIN_PREDICTOR_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--data", type=Path, required=True, help="directory of recorded .mcap episodes (at least 3)"
    )
    p.add_argument(
        "--out", type=Path, default=Path("runs/predictor"), help="output directory (default runs/predictor)"
    )
    p.add_argument("--history", type=positive_int, default=10, help="history steps H at 20 Hz (default 10)")
    p.add_argument("--future", type=positive_int, default=10, help="future steps F at 20 Hz (default 10)")
    p.add_argument("--epochs", type=positive_int, default=20, help="maximum epochs (default 20)")
    p.add_argument(
        "--patience", type=int, default=4, help="epochs without improvement before stopping (default 4)"
    )
    p.add_argument(
        "--stride", type=positive_int, default=1, help="steps between windows of a vehicle (default 1)"
    )
    p.add_argument(
        "--correction",
        choices=("plain", "bounded", "gated", "bounded-gated"),
        default=None,
        help="how the model's correction to constant velocity is shaped: plain (unbounded), bounded "
        "(tanh-bounded to a physically plausible deviation), gated (a learned confidence gate in [0, 1] "
        "scales it, so the model falls back to constant velocity), bounded-gated (default: "
        "PredictorConfig's)",
    )
    p.add_argument(
        "--velocity-window", type=positive_int, default=None,
        help="steps of history the constant-velocity base fits its velocity to (least squares; 1: the last "
        "step's difference; default PredictorConfig's, 10 = 0.5 s, robust to positions measured with noise)",
    )
    p.add_argument(
        "--base", choices=("constant-velocity", "lane-aware"), default=None,
        help="what the correction is a residual over: constant-velocity (the fitted velocity) or lane-aware "
        "(the fitted speed along the road the neighbours give, a lane change ending at the next lane centre, "
        "no drift across otherwise) (default: PredictorConfig's)",
    )
    p.add_argument(
        "--gate-cost", type=float, default=None, metavar="C",
        help="gated models: loss charged for the gate's mean opening, in units of the typical residual; higher "
        "keeps the correction closed unless it gains more (default: TrainConfig's)",
    )
    p.add_argument(
        "--input-noise",
        type=float,
        default=None,
        metavar="M",
        help="std of Gaussian noise added to observed positions in training, metres, for traffic measured "
        "with noise (default: TrainConfig's)",
    )
    p.add_argument("--batch-size", type=positive_int, default=512, help="windows per step (default 512)")
    p.add_argument(
        "--max-train-windows",
        type=positive_int,
        default=200_000,
        help="deterministic subsample of training windows (default 200000)",
    )
    p.add_argument(
        "--time-limit", type=float, default=None, help="stop after the epoch that passes this many seconds of compute (CPU seconds over --threads: other busy processes do not move it)"
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed for the split, initialisation and batches (default 0)"
    )
    p.add_argument("--threads", type=positive_int, default=1,
                   help="torch threads (default 1: more collapse when another process shares the cores)")
    p.add_argument(
        "--overwrite", action="store_true", help="replace an existing predictor.pt / metrics.json in --out"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def train_predictor_main(argv: list[str] | None = None) -> int:
    args = train_predictor_parser().parse_args(argv)

    error = functools.partial(fail, "lc-train-predictor")

    if not args.data.is_dir():
        return error(f"--data {args.data} is not a directory")
    from lckit.fileio import check_output_folder
    from lcmodels.predictor.train import METRICS_NAME

    try:  # the predictor is written after the whole training: a folder it cannot go to is refused first
        check_output_folder(args.out)
    except ValueError as exc:
        return error(str(exc))
    existing = [p for p in (args.out / "predictor.pt", args.out / METRICS_NAME) if p.exists()]
    if existing and not args.overwrite:
        return error(f"{existing[0]} already exists; choose another --out or pass --overwrite")
    if args.time_limit is not None and args.time_limit <= 0:
        return error(f"--time-limit must be > 0, got {args.time_limit}")
    setup_logging("lc-train-predictor", verbose=not args.quiet)

    from lcdata.corpus import load_tracks
    from lcmodels.predictor import PredictorConfig, TrainConfig, train_predictor

    try:
        config = TrainConfig(
            model=PredictorConfig(
                history_steps=args.history,
                future_steps=args.future,
                **({"correction": args.correction} if args.correction else {}),
                **({"velocity_window": args.velocity_window} if args.velocity_window else {}),
                **({"base": args.base} if args.base else {}),
            ),
            stride=args.stride,
            batch_size=args.batch_size,
            **({"input_noise_m": args.input_noise} if args.input_noise is not None else {}),
            **({"gate_cost": args.gate_cost} if args.gate_cost is not None else {}),
            max_epochs=args.epochs,
            patience=args.patience,
            max_train_windows=args.max_train_windows,
            seed=args.seed,
            num_threads=args.threads,
            time_limit_s=args.time_limit,
            progress=not args.quiet,
        )
        tracks = load_tracks(args.data)
        metrics = train_predictor(tracks, config, args.out)
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    rows = [
        ("model", metrics["model"]),
        ("constant velocity", metrics["constant_velocity"]),
        ("constant acceleration", metrics["constant_acceleration"]),
    ]
    print(
        f"test split, {args.history}+{args.future} steps ({metrics['corpus'].get('windows', {}).get('test', '?')} windows):"
    )
    for name, m in rows:
        print(f"  {name:22s} ADE {m['ade']:.4f} m   FDE {m['fde']:.4f} m   miss rate {m['miss_rate']:.4f}")
    for label in metrics["model"].get("horizons", {}):
        cells = "   ".join(
            f"{name} {m['horizons'][label]['fde']:.4f}/{m['horizons'][label]['rmse']:.4f}" for name, m in
            (("model", rows[0][1]), ("CV", rows[1][1]), ("CA", rows[2][1]))
        )  # fmt: skip
        print(f"  at {label:4s} FDE/RMSE m: {cells}")
    print(f"wrote {args.out / 'predictor.pt'} and {args.out / METRICS_NAME}")
    if not args.quiet:
        logging.getLogger(__name__).info("training: %s", json.dumps(metrics.get("training", {}))[:300])
    return 0




