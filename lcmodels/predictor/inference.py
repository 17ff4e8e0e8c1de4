"""Batched inference for the policy stage.

:meth:`Predictor.predict_neighbours` takes the observation's neighbour histories (in the ego frame
of the current step) and predicts every present neighbour in one forward pass: each neighbour is
re-centred in its own agent-centric frame (``lcdata.corpus`` code, heading from positions only), the
other neighbours (and the ego, when its history is given) are its context, and the predictions are
transformed back into the input frame.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import torch

from lcdata.corpus import WindowBatch, heading_from_positions
from lcmodels.predictor.checkpoint import load_model, save_model
from lcmodels.predictor.model import TrajectoryTransformer

__all__ = ["Predictor"]


@functools.lru_cache(maxsize=8)
def _token_order(k: int) -> np.ndarray:
    """``(K, K+1)``: token order for neighbour i, ``[i, the other K-1 neighbours, ego (K)]``."""
    order = np.array([[i, *(j for j in range(k) if j != i), k] for i in range(k)], dtype=np.int64)
    order.setflags(write=False)
    return order


class Predictor:
    """A trained :class:`TrajectoryTransformer` behind numpy in / numpy out calls."""

    def __init__(self, model: TrajectoryTransformer) -> None:
        self.model = model.eval()
        self.config = model.config

    @classmethod
    def load(
        cls,
        path: str | os.PathLike[str],
        *,
        history_steps: int | None = None,
        future_steps: int | None = None,
    ) -> Predictor:
        """Load a checkpoint; ``ValueError`` when corrupt or trained for other horizons."""
        model, _ = load_model(path, history_steps=history_steps, future_steps=future_steps)
        return cls(model)

    def save(self, path: str | os.PathLike[str]) -> Path:
        return save_model(self.model, path)

    @property
    def history_steps(self) -> int:
        return self.config.history_steps

    @property
    def future_steps(self) -> int:
        return self.config.future_steps

    @torch.inference_mode()
    def predict_tokens(self, pos: np.ndarray, mask: np.ndarray, *, batch_size: int = 8192) -> np.ndarray:
        """Agent futures from token sets in the agent frame.

        Args:
            pos: ``(N, T, H, 2)``, token 0 the agent.
            mask: ``(N, T, H)`` bool.

        Returns:
            ``(N, F, 2)`` float32, agent frame.
        """
        pos_t = torch.as_tensor(np.asarray(pos, dtype=np.float32))
        mask_t = torch.as_tensor(np.asarray(mask, dtype=bool))
        return self._predict_tensors(pos_t, mask_t, batch_size).numpy()

    def _predict_tensors(self, pos_t: torch.Tensor, mask_t: torch.Tensor, batch_size: int = 8192) -> torch.Tensor:
        """:meth:`predict_tokens` on tensors (call under ``torch.inference_mode``)."""
        t = self.config.num_neighbours + 1
        if pos_t.shape[1] < t:  # fewer context slots than trained with: pad with absent tokens
            extra = t - pos_t.shape[1]
            pos_t = torch.cat((pos_t, pos_t.new_zeros(pos_t.shape[0], extra, *pos_t.shape[2:])), 1)
            mask_t = torch.cat((mask_t, mask_t.new_zeros(mask_t.shape[0], extra, mask_t.shape[2])), 1)
        outs = [
            self.model(pos_t[i : i + batch_size], mask_t[i : i + batch_size])
            for i in range(0, len(pos_t), batch_size)
        ]
        if not outs:
            return pos_t.new_zeros((0, self.future_steps, 2))
        return torch.cat(outs)

    def predict_windows(self, batch: WindowBatch) -> np.ndarray:
        """``(N, F, 2)`` predictions for corpus windows, in each window's agent frame."""
        pos, mask = batch.tokens()
        return self.predict_tokens(pos, mask)

    def predict_neighbours(
        self, history: np.ndarray, mask: np.ndarray, ego_history: np.ndarray | None = None
    ) -> np.ndarray:
        """Predict all neighbours of B observations in one forward pass.

        Args:
            history: ``(B, K, H, 2)`` neighbour positions in any common frame (the ego frame).
            mask: ``(B, K, H)`` bool presence; a neighbour absent at the last step is not predicted.
            ego_history: optional ``(B, H, 2)`` ego positions in the same frame, used as context.

        Returns:
            ``(B, K, F, 2)`` float32 in the input frame; zeros for neighbours absent at the last step
            (never NaN).
        """
        history = np.asarray(history, dtype=np.float64)
        mask = np.asarray(mask, dtype=bool)
        b, k, h, _ = history.shape
        if h != self.history_steps:
            raise ValueError(f"history has {h} steps; this predictor was trained with {self.history_steps}")
        if mask.shape != (b, k, h):
            raise ValueError(f"mask must be {(b, k, h)}, got {mask.shape}")
        f = self.future_steps
        result = np.zeros((b, k, f, 2), dtype=np.float32)
        valid = mask[:, :, -1]  # only vehicles present now are predicted
        if not valid.any():
            return result
        # Geometry in float32: positions are tens of metres, float32 resolves micrometres there.
        history = np.where(mask[..., None] & np.isfinite(history), history, 0.0).astype(np.float32)
        if ego_history is not None:
            ego = np.asarray(ego_history, dtype=np.float32).reshape(b, 1, h, 2)
            ego_mask = np.ones((b, 1, h), dtype=bool)
        else:
            ego = np.zeros((b, 1, h, 2), dtype=np.float32)
            ego_mask = np.zeros((b, 1, h), dtype=bool)
        all_pos = np.concatenate((history, ego), axis=1)  # (B, K+1, H, 2)
        all_mask = np.concatenate((mask, ego_mask), axis=1)
        # Token order for neighbour i: [i, the other K-1 neighbours, ego] (slot order is irrelevant to
        # the model: it has no slot embedding).
        order = _token_order(k)
        bi, ki = np.nonzero(valid)  # (M,) each
        tok_pos = all_pos[bi[:, None], order[ki]]  # (M, K+1, H, 2)
        tok_mask = all_mask[bi[:, None], order[ki]]  # (M, K+1, H)
        origin = history[bi, ki, -1]  # (M, 2)
        heading = heading_from_positions(history[bi, ki], mask[bi, ki]).astype(np.float32)  # (M,)
        m = len(bi)
        # The frame change as one batched 2x2 product in torch (the transform of lcdata.corpus.to_frame
        # and from_frame, which do it in numpy): local = (p - origin) @ R, R = [[c, -s], [s, c]].
        with torch.inference_mode():
            c, s = torch.from_numpy(np.cos(heading)), torch.from_numpy(np.sin(heading))
            rot = torch.stack((torch.stack((c, -s), -1), torch.stack((s, c), -1)), -2)  # (M, 2, 2)
            origin_t = torch.from_numpy(origin).unsqueeze(1)  # (M, 1, 2)
            local = torch.bmm(torch.from_numpy(tok_pos.reshape(m, (k + 1) * h, 2)) - origin_t, rot)
            # Absent positions need no zeroing here: the model ignores whatever is behind the mask.
            pred = self._predict_tensors(local.view(m, k + 1, h, 2), torch.from_numpy(tok_mask))  # (M, F, 2)
            back = torch.bmm(pred, rot.transpose(1, 2)) + origin_t  # (M, F, 2) in the input frame
        result[bi, ki] = back.numpy()
        return result
