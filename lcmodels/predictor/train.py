"""Training and evaluation of the trajectory predictor.

:func:`train_predictor` is the library entry point behind ``lc-train-predictor``: tracks in,
``out_dir/predictor.pt`` + ``out_dir/metrics.json`` + TensorBoard logs out, metrics dict returned.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from tqdm.auto import tqdm

from lcdata.corpus import Corpus, WindowBatch, WindowOptions, split_episodes
from lckit.fileio import write_file
from lcmodels.predictor import metrics as M
from lcmodels.predictor.baselines import (
    constant_acceleration,
    constant_velocity,
    constant_velocity_fit,
    lane_aware_velocity,
)
from lcmodels.predictor.checkpoint import save_model
from lcmodels.predictor.model import PredictorConfig, TrajectoryTransformer

__all__ = ["CHECKPOINT_NAME", "METRICS_NAME", "TrainConfig", "evaluate", "train_predictor"]

FIT_WINDOW = 10
"""Steps of the fitted-velocity baseline (``constant_velocity_fit``) in every evaluation: 0.5 s at 20 Hz."""

logger = logging.getLogger(__name__)

CHECKPOINT_NAME = "predictor.pt"
METRICS_NAME = "metrics.json"


@dataclass(frozen=True, slots=True, kw_only=True)
class TrainConfig:
    """Everything :func:`train_predictor` needs besides the data."""

    model: PredictorConfig = field(default_factory=PredictorConfig)
    """Architecture and horizons (H, F, K)."""
    stride: int = 1
    """Steps between window start points of one vehicle."""
    val_fraction: float = 0.15
    """Share of episodes for validation (early stopping)."""
    test_fraction: float = 0.15
    """Share of episodes for the reported test metrics."""
    batch_size: int = 512
    """Windows per optimisation step."""
    learning_rate: float = 2e-3
    """AdamW peak learning rate (cosine decay over max_epochs)."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    max_epochs: int = 20
    """Upper bound on epochs."""
    patience: int = 4
    """Epochs without validation improvement before stopping."""
    grad_clip_norm: float = 1.0
    """Gradient norm clip."""
    max_train_windows: int | None = 200_000
    """Deterministic subsample of the training windows per run (None: all)."""
    max_eval_windows: int | None = 50_000
    """Deterministic subsample of validation windows per epoch (None: all); test always uses all."""
    miss_threshold_m: float = 0.5
    """Final-step error above which a prediction counts as a miss, metres."""
    input_noise_m: float = 0.0
    """Standard deviation of Gaussian noise added to every observed position of a training batch (drawn
    afresh per batch; targets stay clean), metres: recorded traffic elsewhere is measured with noise and
    rounding that a simulator's exact positions lack, and a model that never saw any reads the jitter of
    a difference as real acceleration. 0 trains on the positions as recorded."""
    gate_cost: float = 0.05
    """Gated models: loss charged for the mean gate opening, in units of the typical residual (the loss's
    unit), so that the gate stays closed (constant velocity) unless the correction gains more than that."""
    seed: int = 0
    """Seeds the split, subsampling, initialisation and batch order."""
    num_threads: int = 2
    """torch intra-op threads during training."""
    time_limit_s: float | None = None
    """Stop after the epoch that crosses this much compute: the process's CPU seconds over ``num_threads``, so that
    other busy processes do not move the stop; a slower machine still can (bit-determinism ends when it stops
    training; ``metrics.json``'s ``training.stopped_by`` says what ended it)."""
    progress: bool = True
    """Show a tqdm progress bar."""
    tensorboard: bool = True
    """Write TensorBoard scalars under out_dir/tensorboard."""

    def __post_init__(self) -> None:
        if not isinstance(self.model, PredictorConfig):
            raise ValueError(f"model must be a PredictorConfig, got {type(self.model).__name__}")
        for name in ("stride", "batch_size", "max_epochs", "num_threads"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if not isinstance(self.patience, int) or self.patience < 0:
            raise ValueError(f"patience must be an int >= 0, got {self.patience!r}")
        for name in ("max_train_windows", "max_eval_windows"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be None or an int >= 1, got {value!r}")
        for name in ("val_fraction", "test_fraction"):
            if not 0.0 < getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be in (0, 1), got {getattr(self, name)}")
        if self.val_fraction + self.test_fraction >= 1.0:
            raise ValueError("val_fraction + test_fraction must be < 1")
        for name in ("gate_cost", "input_noise_m"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a number >= 0, got {value!r}")
        for name in ("learning_rate", "grad_clip_norm", "miss_threshold_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.weight_decay < 0:
            raise ValueError(f"weight_decay must be >= 0, got {self.weight_decay}")
        if self.time_limit_s is not None and self.time_limit_s <= 0:
            raise ValueError(f"time_limit_s must be None or > 0, got {self.time_limit_s}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        data = dict(data)
        if isinstance(data.get("model"), dict):
            data["model"] = PredictorConfig.from_dict(data["model"])
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"unknown TrainConfig fields: {sorted(unknown)}")
        return cls(**data)

    def window_options(self) -> WindowOptions:
        m = self.model
        return WindowOptions(
            history_steps=m.history_steps, future_steps=m.future_steps, num_neighbours=m.num_neighbours,
            stride=self.stride,
        )  # fmt: skip


def _tensors(batch: WindowBatch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    pos, mask = batch.tokens()
    return torch.from_numpy(pos), torch.from_numpy(mask), torch.from_numpy(batch.future)


def _ade_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean Euclidean error, ``(N, F, 2)`` x2 -> scalar (eps keeps the gradient finite at 0)."""
    return torch.sqrt(((pred - target) ** 2).sum(-1) + 1e-12).mean()


@torch.no_grad()
def _predict(
    model: TrajectoryTransformer, pos: torch.Tensor, mask: torch.Tensor, batch_size: int = 4096
) -> torch.Tensor:
    model.eval()
    out = [model(pos[i : i + batch_size], mask[i : i + batch_size]) for i in range(0, len(pos), batch_size)]
    return torch.cat(out) if out else torch.zeros(0, model.config.future_steps, 2)


def evaluate(
    model: TrajectoryTransformer | None, batch: WindowBatch, *, miss_threshold_m: float
) -> dict[str, dict[str, Any]]:
    """Model (if given) and baseline metrics on windows, metres.

    Returns:
        ``{"model"?: summary, "constant_velocity": summary, "constant_velocity_fit": summary (the velocity
        fitted to the last FIT_WINDOW steps, where the history is that long), "lane_aware": summary (the lane-aware
        extrapolation, ``lane_aware_velocity`` with its defaults, where the history is that long),
        "constant_acceleration": summary}``,
        each summary as :func:`lcmodels.predictor.metrics.summary`, plus ``"lane_change"`` with
        the same three on the windows whose future contains a lane change (when there are any).
    """
    f = batch.future.shape[1]
    preds = {
        "constant_velocity": constant_velocity(batch.history, f),
        **({"constant_velocity_fit": constant_velocity_fit(batch.history, f, window=FIT_WINDOW),
            "lane_aware": lane_aware_velocity(batch.history, batch.neighbours, batch.neighbour_mask, f, window=FIT_WINDOW)}
           if batch.history.shape[1] >= FIT_WINDOW else {}),
        "constant_acceleration": constant_acceleration(batch.history, f),
    }
    if model is not None:
        pos, mask, _ = _tensors(batch)
        preds = {"model": _predict(model, pos, mask).numpy(), **preds}
    out: dict[str, dict[str, Any]] = {
        name: M.summary(p, batch.future, miss_threshold_m=miss_threshold_m) for name, p in preds.items()
    }
    lc = batch.lane_change
    if lc.any():
        out["lane_change"] = {
            name: M.summary(p[lc], batch.future[lc], miss_threshold_m=miss_threshold_m)
            for name, p in preds.items()
        }
    return out


def _subsample(rows: np.ndarray, limit: int | None, rng: np.random.Generator) -> np.ndarray:
    if limit is None or len(rows) <= limit:
        return rows
    return np.sort(rng.choice(rows, size=limit, replace=False))


def train_predictor(
    episodes_tracks: pd.DataFrame | list[pd.DataFrame],
    config: TrainConfig | None = None,
    out_dir: str | os.PathLike[str] = "runs/predictor",
) -> dict[str, Any]:
    """Train the trajectory transformer on recorded episodes and report test metrics.

    Episodes are split into train/val/test by episode id (:func:`lcdata.corpus.split_episodes`);
    normalisation statistics come from the training split only; early stopping watches the
    validation ADE; the reported metrics are on the test split, next to the constant-velocity and
    constant-acceleration baselines on the very same windows.

    Args:
        episodes_tracks: long-form tracks (docs/INTERFACES.md), one DataFrame or one per file;
            at least 3 distinct episodes.
        config: training configuration (defaults: 10+10 steps, 8 neighbours).
        out_dir: created if needed; receives ``predictor.pt``, ``metrics.json``, ``tensorboard/``.

    Returns:
        The dict written to ``metrics.json``: ``model``, ``constant_velocity``,
        ``constant_acceleration`` (test split, metres: ``ade, fde, curve, miss_rate, ...``),
        ``lane_change`` (same, on test windows with a lane change), ``val`` (best validation ADE),
        ``corpus`` (statistics and split), ``training`` (epochs, time, losses), ``config``.

    Raises:
        ValueError: too few episodes or windows, malformed tracks.
    """
    config = config or TrainConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    old_threads = torch.get_num_threads()
    torch.set_num_threads(config.num_threads)
    try:
        return _train(episodes_tracks, config, out)
    finally:
        torch.set_num_threads(old_threads)


def _train(
    episodes_tracks: pd.DataFrame | list[pd.DataFrame], config: TrainConfig, out: Path
) -> dict[str, Any]:
    start, cpu_start = time.perf_counter(), time.process_time()
    corpus = Corpus.from_tracks(episodes_tracks, config.window_options())
    ids = corpus.episode_ids
    if len(ids) < 3:
        raise ValueError(f"need at least 3 episodes for a train/val/test split by episode, got {len(ids)}")
    split = split_episodes(
        ids, val_fraction=config.val_fraction, test_fraction=config.test_fraction, seed=config.seed
    )
    rng = np.random.default_rng(config.seed)
    rows = {name: corpus.windows_of(getattr(split, name)) for name in ("train", "val", "test")}
    for name, r in rows.items():
        if len(r) == 0:
            raise ValueError(f"the {name} split has no windows (episodes too short for the horizons?)")
    train_rows = _subsample(rows["train"], config.max_train_windows, rng)
    val_rows = _subsample(rows["val"], config.max_eval_windows, rng)
    train_b, val_b = corpus.gather(train_rows), corpus.gather(val_rows)
    logger.info(
        "windows: train %d (of %d), val %d, test %d",
        len(train_rows),
        len(rows["train"]),
        len(val_rows),
        len(rows["test"]),
    )

    torch.manual_seed(config.seed)
    model = TrajectoryTransformer(config.model)
    pos, mask, fut = _tensors(train_b)
    vpos, vmask, vfut = _tensors(val_b)
    if config.input_noise_m > 0:  # the statistics of the inputs the model will be trained on
        noise_gen = torch.Generator().manual_seed(config.seed + 1)
        model.fit_normalisation(pos + config.input_noise_m * torch.randn(pos.shape, generator=noise_gen), mask, fut)
    else:
        model.fit_normalisation(pos, mask, fut)

    opt = torch.optim.AdamW(model.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay)
    steps_per_epoch = math.ceil(len(pos) / config.batch_size)
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, max_lr=config.learning_rate, total_steps=steps_per_epoch * config.max_epochs, pct_start=0.1
    )
    writer = None
    if config.tensorboard:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(log_dir=str(out / "tensorboard"))
    gen = torch.Generator().manual_seed(config.seed)
    scale = float(model.residual_std.mean())  # loss in units of the typical residual: well conditioned

    def val_ade() -> float:
        return float(_ade_loss(_predict(model, vpos, vmask), vfut))

    best_val = val_ade()
    initial_val = best_val
    best_state = copy.deepcopy(model.state_dict())
    best_epoch, history, stale, global_step = 0, [], 0, 0
    stopped_by = "max_epochs"
    bar = tqdm(range(1, config.max_epochs + 1), desc="predictor", disable=not config.progress, leave=False)
    for epoch in bar:
        model.train()
        perm = torch.randperm(len(pos), generator=gen)
        total = 0.0
        for i in range(0, len(pos), config.batch_size):
            idx = perm[i : i + config.batch_size]
            p = pos[idx]
            if config.input_noise_m > 0:
                p = p + config.input_noise_m * torch.randn(p.shape, generator=gen, dtype=p.dtype)
            cv, residual, gate = model.prediction_parts(p, mask[idx])
            ade = _ade_loss(cv + residual, fut[idx])
            loss = ade / scale
            if gate is not None:
                # The correction learns as if ungated (a gate that closed early would starve it of gradient);
                # the gate learns how far to trust the correction as it stands, and pays for opening.
                gated = cv + residual.detach() * gate.unsqueeze(-1)
                ade = _ade_loss(gated, fut[idx])  # the model's output: what the training ADE reports
                loss = loss + ade / scale + config.gate_cost * gate.mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip_norm)
            opt.step()
            sched.step()
            total += ade.item() * len(idx)
            global_step += 1
        train_ade = total / len(pos)
        v = val_ade()
        history.append({"epoch": epoch, "train_ade": train_ade, "val_ade": v})
        if writer is not None:
            writer.add_scalar("losses/train_ade_m", train_ade, epoch)
            writer.add_scalar("losses/val_ade_m", v, epoch)
            writer.add_scalar("charts/learning_rate", sched.get_last_lr()[0], epoch)
        bar.set_postfix(train=f"{train_ade:.5f}", val=f"{v:.5f}")
        logger.info("epoch %d: train ADE %.5f m, val ADE %.5f m", epoch, train_ade, v)
        if v < best_val:
            best_val, best_epoch, stale = v, epoch, 0
            best_state = copy.deepcopy(model.state_dict())
        else:
            stale += 1
            if stale > config.patience:
                logger.info("early stop after epoch %d (best %d)", epoch, best_epoch)
                stopped_by = "patience"
                break
        compute_s = (time.process_time() - cpu_start) / config.num_threads
        if config.time_limit_s is not None and compute_s > config.time_limit_s and epoch < config.max_epochs:
            logger.warning("time limit of %.0f s of compute reached after epoch %d", config.time_limit_s, epoch)
            stopped_by = "time_limit"
            break
    bar.close()
    model.load_state_dict(best_state)
    model.eval()
    train_time = time.perf_counter() - start

    test_b = corpus.gather(rows["test"])
    result: dict[str, Any] = evaluate(model, test_b, miss_threshold_m=config.miss_threshold_m)
    result["val"] = {"initial_ade": initial_val, "best_ade": best_val, "best_epoch": best_epoch}
    result["corpus"] = {
        "all": corpus.statistics(),
        "test": corpus.statistics(rows["test"]),
        "split": {name: [ids[i] for i in getattr(split, name)] for name in ("train", "val", "test")},
        "windows": {
            "train_used": len(train_rows),
            "train": len(rows["train"]),
            "val": len(val_rows),
            "test": len(rows["test"]),
        },
    }
    result["training"] = {"epochs": len(history), "seconds": train_time, "stopped_by": stopped_by,
                          "history": history}
    result["config"] = config.to_dict()
    for name in ("model", "constant_velocity", "constant_acceleration"):
        logger.info("test %s: ADE %.5f m, FDE %.5f m", name, result[name]["ade"], result[name]["fde"])
    if writer is not None:
        for name in ("model", "constant_velocity", "constant_acceleration"):
            writer.add_scalar(f"test/{name}_ade_m", result[name]["ade"], 0)
            writer.add_scalar(f"test/{name}_fde_m", result[name]["fde"], 0)
        writer.close()
    save_model(model, out / CHECKPOINT_NAME, extra={"train_config": config.to_dict(), "val_ade": best_val})
    write_file(out / METRICS_NAME, json.dumps(result, indent=2, sort_keys=True), root=out)
    return result
