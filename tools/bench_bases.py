#!/usr/bin/env python
"""Analytic extrapolations (no learning) on the windows of corpus folders: which base is worth a model?

For each data set (``NAME=FOLDER``; ``FOLDER:val`` takes only the validation episodes of the split that
``lc-train-predictor`` makes with its defaults, so a choice made here never sees the windows a model is tested on),
the FDE at 0.5 s and 3 s of:

- CV (the last step's difference) and the velocity fitted to the last 5, 10 or 20 steps (FV);
- least-squares fits of the *state*: position and velocity over the last W steps (the fitted position instead of
  the last measured one), and position, velocity and acceleration over 20 steps with the acceleration decaying
  (time constant 5 steps);
- the lane-aware base (``lcmodels.predictor.baselines.lane_aware_velocity``) with its defaults and with one of
  its settings changed at a time (and its first form, all four changes at once);

each row with its change against FV over 10 steps.

    python tools/bench_bases.py --data lcsim-val=runs/transfer/lcsim-train:val --data sumo=runs/transfer/sumo/corpus

Windows are 20+60 steps, stride 5, at most --max-windows of them per data set (a deterministic subsample).
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from collections.abc import Callable, Sequence

import numpy as np

from lccli.common import fail, positive_int

PROG = "bench_bases.py"
HISTORY, FUTURE, STRIDE = 20, 60, 5
HORIZONS = ((0.5, 10), (3.0, 60))


def state_fit(history: np.ndarray, window: int, degree: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares polynomial of ``degree`` (1 or 2) over the last ``window`` steps of ``(N, H, 2)``, time 0
    at the last step: position, velocity (per step) and acceleration (per step², 0 for degree 1) there."""
    t = np.arange(-window + 1, 1, dtype=np.float64)
    coef = np.einsum("cw,nwx->ncx", np.linalg.pinv(np.stack([t**i for i in range(degree + 1)], 1)),
                     history[:, -window:])  # fmt: skip
    accel = 2 * coef[:, 2] if degree >= 2 else np.zeros_like(coef[:, 0])
    return coef[:, 0], coef[:, 1], accel


def extrapolate(pos: np.ndarray, vel: np.ndarray, accel: np.ndarray, future: int, accel_tau: float | None) -> np.ndarray:
    """``(N, F, 2)`` from a state; the acceleration held (``accel_tau`` None) or decaying with that time constant."""
    k = np.arange(1, future + 1, dtype=np.float64)[None, :, None]
    a_term = k * k / 2 if accel_tau is None else accel_tau * (k - accel_tau * (1 - np.exp(-k / accel_tau)))
    return pos[:, None] + k * vel[:, None] + a_term * accel[:, None]


def candidates() -> dict[str, Callable[..., np.ndarray]]:
    """Name -> ``f(history, neighbours, neighbour_mask) -> (N, F, 2)``."""
    from lcmodels.predictor.baselines import constant_velocity, constant_velocity_fit, lane_aware_velocity

    out: dict[str, Callable[..., np.ndarray]] = {"CV": lambda h, n, m: constant_velocity(h, FUTURE)}
    for w in (5, 10, 20):
        out[f"FV, {w} steps"] = lambda h, n, m, w=w: constant_velocity_fit(h, FUTURE, window=w)
    for w in (5, 10, 20):
        out[f"position+velocity fit, {w} steps"] = lambda h, n, m, w=w: extrapolate(*state_fit(h, w, 1), FUTURE, None)
    out["position+velocity+acceleration fit, 20 steps, tau 5"] = lambda h, n, m: extrapolate(*state_fit(h, 20, 2), FUTURE, 5.0)
    variants: list[tuple[str, dict[str, float]]] = [
        ("defaults", {}),
        ("velocity window 5", {"window": 5}),
        ("velocity window 7", {"window": 7}),
        ("no short window on smooth tracks", {"smooth_jitter_m": 0.0}),
        ("lateral speed over the velocity window", {"lateral_window": 10}),
        ("lane change stopping at the centre (no approach)", {"approach_m": 0.0}),
        ("approach 0.5 m", {"approach_m": 0.5}),
        ("lane change above 0.3 m/s", {"move_mps": 0.3}),
        ("margin 0.3 m", {"margin_m": 0.3}),
        ("the first form: velocity window, lane change stopping at the centre above 0.3 m/s",
         {"smooth_jitter_m": 0.0, "lateral_window": 10, "approach_m": 0.0, "move_mps": 0.3}),
    ]
    for label, kwargs in variants:
        out[f"lane-aware, {label}"] = lambda h, n, m, kw=kwargs: lane_aware_velocity(h, n, m, FUTURE, **kw)  # type: ignore[arg-type]
    return out


def load_windows(spec: str, max_windows: int, seed: int):
    """``FOLDER`` or ``FOLDER:val`` -> the windows (``ValueError`` when there are none)."""
    from lcdata.corpus import Corpus, WindowOptions, load_tracks, split_episodes

    folder, _, part = spec.rpartition(":") if spec.endswith(":val") else (spec, "", "")
    path = pathlib.Path(folder)
    if not (path.is_dir() and any(path.glob("*.mcap"))):
        raise ValueError(f"{folder} is not a folder of .mcap episodes")
    corpus = Corpus.from_tracks(load_tracks(path), WindowOptions(history_steps=HISTORY, future_steps=FUTURE, stride=STRIDE))
    rows = np.arange(len(corpus))
    if part == "val":
        if len(corpus.episode_ids) < 3:
            raise ValueError(f"{folder}: a validation split needs at least 3 episodes")
        rows = corpus.windows_of(split_episodes(corpus.episode_ids, seed=0).val)
    if len(rows) == 0:
        raise ValueError(f"{spec}: no window of {HISTORY}+{FUTURE} steps")
    if len(rows) > max_windows:
        rows = np.sort(np.random.default_rng(seed).choice(rows, size=max_windows, replace=False))
    return corpus.gather(rows)


def measure(data: dict[str, object]) -> dict[str, dict[str, dict[str, float]]]:
    """``{base: {data set: {"0.5s": FDE, "3s": FDE}}}``, metres."""
    result: dict[str, dict[str, dict[str, float]]] = {}
    for name, fn in candidates().items():
        result[name] = {}
        for data_name, b in data.items():
            pred = fn(b.history, b.neighbours, b.neighbour_mask)  # type: ignore[attr-defined]
            err = np.linalg.norm(pred - b.future, axis=-1)  # type: ignore[attr-defined]
            result[name][data_name] = {f"{t:g}s": float(err[:, k - 1].mean()) for t, k in HORIZONS}
    return result


def format_table(result: dict[str, dict[str, dict[str, float]]]) -> str:
    names = list(next(iter(result.values())))
    ref = result["FV, 10 steps"]
    lines = ["| base | " + " | ".join(f"{d} FDE 0.5 s / 3 s (vs FV)" for d in names) + " |", "|---" * (len(names) + 1) + "|"]
    for base, per in result.items():
        cells = []
        for d in names:
            a, b = per[d]["0.5s"], per[d]["3s"]
            cells.append(f"{a:.4f} / {b:.3f} ({a / ref[d]['0.5s'] - 1:+.1%} / {b / ref[d]['3s'] - 1:+.1%})")
        lines.append(f"| {base} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", action="append", default=[], metavar="NAME=FOLDER[:val]", required=True,
                   help="a data set: a corpus folder, ':val' for its validation episodes only (repeatable)")
    p.add_argument("--max-windows", type=positive_int, default=20_000, help="windows per data set (default 20000)")
    p.add_argument("--seed", type=int, default=0, help="subsampling seed (default 0)")
    try:
        args = p.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    data = {}
    try:
        for item in args.data:
            name, eq, spec = item.partition("=")
            if not eq or not name or not spec:
                return fail(PROG, f"--data takes NAME=FOLDER[:val], got {item!r}")
            print(f"loading {name}", file=sys.stderr, flush=True)
            data[name] = load_windows(spec, args.max_windows, args.seed)
    except (ValueError, OSError) as exc:
        return fail(PROG, str(exc))
    print(format_table(measure(data)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
