"""Inference throughput of the trajectory predictor's policy-time API.

Times ``Predictor.predict_neighbours`` on a batch of observations (default 512 x 8 neighbours) and
reports vehicle predictions per second, end to end (frames in numpy + one forward pass). Every
neighbour slot counts as a vehicle; by default all are present (the worst case: absent ones are
skipped).

    python tools/bench_predictor.py                 # untrained default model, 10+10
    python tools/bench_predictor.py --checkpoint runs/predictor/predictor.pt --json
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import sys
import time

import numpy as np
import torch

from lcmodels.predictor import Predictor, PredictorConfig, TrajectoryTransformer


def make_inputs(
    batch: int, k: int, h: int, *, absent_fraction: float = 0.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plausible neighbour histories ``(B, K, H, 2)``, masks ``(B, K, H)`` and ego histories ``(B, H, 2)``."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(-40, 40, (batch, k, 1, 2))
    vel = np.stack((rng.uniform(0.2, 0.4, (batch, k)), rng.normal(0, 0.01, (batch, k))), -1)[:, :, None]
    hist = start + np.arange(h)[None, None, :, None] * vel
    mask = np.broadcast_to(rng.random((batch, k, 1)) >= absent_fraction, hist.shape[:3]).copy()
    ego = np.arange(h)[None, :, None] * np.array([0.33, 0.0]) - (h - 1) * np.array([0.33, 0.0])
    return hist, mask, np.broadcast_to(ego, (batch, h, 2)).copy()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--checkpoint", type=pathlib.Path, help="trained predictor.pt (default: untrained model)"
    )
    parser.add_argument("--history-steps", type=int, default=10)
    parser.add_argument("--future-steps", type=int, default=10)
    parser.add_argument("--d-model", type=int, default=PredictorConfig().d_model, help="untrained model width")
    parser.add_argument("--batch", type=int, default=512, help="observations per call (x 8 neighbours)")
    parser.add_argument(
        "--absent-fraction",
        type=float,
        default=0.0,
        help="share of absent neighbours (skipped; 0 = worst case)",
    )
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    if args.checkpoint:
        predictor = Predictor.load(args.checkpoint)
    else:
        torch.manual_seed(0)
        cfg = PredictorConfig(
            history_steps=args.history_steps, future_steps=args.future_steps, d_model=args.d_model
        )
        predictor = Predictor(TrajectoryTransformer(cfg))
    cfg = predictor.config
    hist, mask, ego = make_inputs(
        args.batch, cfg.num_neighbours, cfg.history_steps, absent_fraction=args.absent_fraction
    )
    for _ in range(3):
        predictor.predict_neighbours(hist, mask, ego)
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        predictor.predict_neighbours(hist, mask, ego)
        times.append(time.perf_counter() - t)
    per_call = float(np.median(times))
    vehicles = args.batch * cfg.num_neighbours
    result = {
        "batch": args.batch,
        "vehicles_per_call": vehicles,
        "history_steps": cfg.history_steps,
        "future_steps": cfg.future_steps,
        "d_model": cfg.d_model,
        "num_layers": cfg.num_layers,
        "threads": args.threads,
        "absent_fraction": args.absent_fraction,
        "median_call_ms": per_call * 1e3,
        "best_call_ms": min(times) * 1e3,
        "vehicles_per_s": vehicles / per_call,
        "torch": torch.__version__,
        "machine": platform.processor() or platform.machine(),
    }
    if args.json:
        print(json.dumps(result))
    else:
        print(
            f"predictor {cfg.history_steps}+{cfg.future_steps}, d_model {cfg.d_model} x {cfg.num_layers} layers, {args.threads} threads"
        )
        print(
            f"batch {args.batch} x {cfg.num_neighbours} neighbours: {per_call * 1e3:.1f} ms/call (median), best {min(times) * 1e3:.1f} ms"
        )
        print(f"throughput: {vehicles / per_call:,.0f} vehicle predictions/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
