"""Checkpoints: weights, normalisation statistics (buffers) and config, loadable with ``weights_only=True``.

Layout of the saved dict (tensors and primitive types only)::

    {"format": "lc-toolkit/predictor", "version": 1,
     "config": "<PredictorConfig JSON>", "state_dict": {name: tensor, ...}, "extra": "<JSON>"}
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from lckit.fileio import loads_json, write_file
from lcmodels.fileio import check_dtypes
from lcmodels.predictor.model import MAX_PARAMETERS, PredictorConfig, TrajectoryTransformer

__all__ = ["ANALYTIC_BASES", "CHECKPOINT_FORMAT", "analytic_model", "load_model", "save_model"]

CHECKPOINT_FORMAT = "lc-toolkit/predictor"
CHECKPOINT_VERSION = 1
MAX_FILE_BYTES = 4 * MAX_PARAMETERS + (64 << 20)
"""The largest file read as a predictor: the most weights a config may describe as float32, plus room for the
normalisation buffers and the archive (a larger file is refused before it is read)."""


def save_model(
    model: TrajectoryTransformer, path: str | os.PathLike[str], *, extra: dict[str, Any] | None = None
) -> Path:
    """Write ``model`` (weights + normalisation buffers + config) to ``path`` atomically."""
    path = Path(path)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": model.config.to_json(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
        "extra": json.dumps(extra or {}, sort_keys=True),
    }
    write_file(path, lambda tmp: torch.save(payload, tmp), by_name=True)  # by name: the bytes name the file
    return path


def load_model(
    path: str | os.PathLike[str], *, history_steps: int | None = None, future_steps: int | None = None
) -> tuple[TrajectoryTransformer, dict[str, Any]]:
    """Load a checkpoint written by :func:`save_model`.

    Args:
        path: checkpoint file.
        history_steps, future_steps: if given, the horizons the caller needs; a checkpoint for other
            horizons is refused.

    Returns:
        The model in eval mode and the ``extra`` dict stored with it.

    Raises:
        ValueError: unreadable or corrupt file, not a predictor checkpoint, or wrong horizons.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"predictor checkpoint {path} does not exist")
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ValueError(f"{path} is {size} bytes, more than a predictor checkpoint can be "
                         f"({MAX_FILE_BYTES >> 20} MiB); not a predictor.pt")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for truncated / foreign files
        # torch's own message advises weights_only=False, which would run code from the file: not shown
        raise ValueError(
            f"{path} is not a readable predictor checkpoint ({size} bytes; truncated, corrupt or "
            f"not a predictor.pt: {type(exc).__name__})"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not an lc-toolkit predictor checkpoint")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: unsupported checkpoint version {str(payload.get('version'))[:40]!r}")
    state = payload.get("state_dict")
    if not isinstance(payload.get("config"), str) or not isinstance(payload.get("extra", "{}"), str) or not (
            isinstance(state, dict) and all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                            for k, v in state.items())):
        raise ValueError(f"{path}: checkpoint is corrupt (its config, extra or state_dict has the wrong type)")
    try:
        config = PredictorConfig.from_dict(loads_json(payload["config"]))
        extra = loads_json(payload.get("extra", "{}"))
    except ValueError as exc:
        raise ValueError(f"{path}: checkpoint config is corrupt: {' '.join(str(exc).split())[:200]}") from None
    if not isinstance(extra, dict):
        raise ValueError(f"{path}: checkpoint config is corrupt: its extra record is not a JSON object")
    for name, wanted in (("history_steps", history_steps), ("future_steps", future_steps)):
        have = getattr(config, name)
        if wanted is not None and wanted != have:
            raise ValueError(
                f"{path} was trained with {name}={have}, but {name}={wanted} was requested; "
                "train a predictor for these horizons or request the checkpoint's"
            )
    model = TrajectoryTransformer(config)
    check_dtypes(state, model.state_dict(), str(path))
    try:
        model.load_state_dict(state)
    except (KeyError, RuntimeError) as exc:
        detail = " ".join(str(exc).split())[:200]
        raise ValueError(f"{path}: weights do not match the stored config: {detail}") from None
    model.eval()
    return model, extra


ANALYTIC_BASES = ("lane-aware",)
"""The extrapolations :func:`analytic_model` can stand in for a trained predictor."""


def analytic_model(config: PredictorConfig) -> TrajectoryTransformer:
    """A predictor that is its base extrapolation alone (``config.base``, one of :data:`ANALYTIC_BASES`): the
    network is built as ``config`` says but its correction is zero, so it predicts exactly what the analytic base
    does (:func:`lcmodels.predictor.model.lane_extrapolate`) and loads wherever a trained ``predictor.pt`` does.
    The policy's prediction input fed by an analytic predictor tells whether a learned one earns its place."""
    if config.base not in ANALYTIC_BASES:
        raise ValueError(f"an analytic predictor needs base one of {', '.join(ANALYTIC_BASES)}, got {config.base!r}")
    model = TrajectoryTransformer(config)
    with torch.no_grad():
        model.head[-1].weight.zero_()  # already zero at construction: said here, since the claim rests on it
        model.head[-1].bias.zero_()
        model.residual_mean.zero_()
        if model.gate is not None:
            model.familiar_limit.fill_(1.0)  # finite, so the checkpoint holds no inf; the correction is zero anyway
    return model.eval()
