"""The trajectory transformer: one token per vehicle, residual over constant velocity.

Input is a token set per sample, already in the agent-centric frame (see ``lcdata.corpus``):
positions ``(N, T, H, 2)`` and presence ``(N, T, H)``, token 0 being the agent and tokens
``1..T-1`` its neighbours (T = 1 + K). Each token embeds its own history (positions, backward-
difference velocities and accelerations, presence) with a small MLP. Optional full self-attention
layers (``num_context_layers``) let all tokens exchange information; then ``num_layers`` pre-norm
transformer layers whose query is the agent token attend over all tokens (absent ones are padding)
— the agent-query form costs a fraction of full self-attention, which matters for the policy-time
throughput, since only the agent's output is needed. A head decodes all F future steps at once
as a standardised residual over the agent's constant-velocity extrapolation. With the head's last
layer at zero the model *is* the baseline (plus the training-set mean residual), so training starts
from it.

How the correction to constant velocity is shaped (:attr:`PredictorConfig.correction`), so that on traffic
unlike the training data the model can fall back towards the baseline instead of adding a confident
but wrong correction:

- ``plain``: ``CV + residual``, unbounded (every checkpoint written before the choice existed);
- ``bounded``: each coordinate of the residual through ``b_k tanh(residual / b_k)``, with ``b_k`` the
  largest deviation from constant velocity a vehicle can build up by step ``k``: a speed error of
  ``correction_speed_mps`` plus an acceleration of ``correction_accel_mps2`` held for ``t = k dt_s``
  (``b_k = v t + a t² / 2``);
- ``gated``: ``CV + g * residual`` with a confidence gate ``g`` in [0, 1] per future step: a learned
  gate from the agent token (trained on the correction as it stands, which itself learns ungated, and
  charged for opening, ``TrainConfig.gate_cost``, so it opens only where the correction pays) times the *familiarity* of the agent's motion, which no training can
  teach: the RMS of its standardised velocities and accelerations over the history, fully trusted up to
  the 99.9th percentile of the training windows (``familiar_limit``) and closing linearly to 0 at twice
  that. Motion unlike anything in training (a jitter of the positions that the training data never had,
  say) thus falls back to constant velocity instead of being read as real acceleration;
- ``bounded-gated``: both.

Normalisation statistics are buffers computed from the training split only
(:meth:`TrajectoryTransformer.fit_normalisation`), so they travel with the weights.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "FEATURES_PER_STEP",
    "AgentAttentionLayer",
    "PredictorConfig",
    "TrajectoryTransformer",
    "cv_extrapolate",
    "lane_extrapolate",
    "token_features",
]

#: Kinematic features per history step: x, y, vx, vy, ax, ay (frame metres, per step, per step²).
FEATURES_PER_STEP = 6
#: Lower bound of a standard deviation used for standardisation.
MIN_STD = 1e-6
#: Standardised inputs are clipped to this magnitude (robustness to out-of-distribution inputs).
CLIP = 50.0
#: The ways to shape the correction to constant velocity (see the module docstring).
CORRECTIONS = ("plain", "bounded", "gated", "bounded-gated")
#: The extrapolations the correction is a residual over: ``constant-velocity`` (:func:`cv_extrapolate` with the
#: fitted velocity) or ``lane-aware`` (:func:`lane_extrapolate`: along the road the neighbours give, a lane change
#: ending at the next lane centre).
BASES = ("constant-velocity", "lane-aware")
#: Share of training windows whose motion counts as familiar to a gated model (the gate's full-trust limit).
FAMILIAR_QUANTILE = 0.999
#: Plausible upper bounds of the sizes and constants of a config: a stored or crafted config beyond them is
#: refused before any weight is allocated (a feed-forward width of 1e10 would ask for terabytes).
LIMITS: dict[str, Any] = {
    "history_steps": 1_000, "future_steps": 1_000, "num_neighbours": 64, "d_model": 4_096, "num_heads": 64,
    "num_layers": 64, "num_context_layers": 64, "ff_dim": 16_384, "velocity_window": 1_000,
    "correction_speed_mps": 100.0, "correction_accel_mps2": 100.0, "dt_s": 10.0, "lane_width_m": 20.0,
    "lane_margin_m": 20.0, "lane_change_mps": 20.0, "lane_hold_mps": 20.0, "lane_approach_m": 20.0,
    "lane_smooth_jitter_m": 1.0, "lane_lateral_window": 1_000, "lane_smooth_window": 1_000,
}  # fmt: skip
#: The most weights a predictor may have (about 400 MB of float32).
MAX_PARAMETERS = 100_000_000
#: Values of fields a stored config may lack: what a checkpoint from before the field existed was.
LEGACY_VALUES: dict[str, Any] = {"correction": "plain", "velocity_window": 1, "base": "constant-velocity"}


@dataclass(frozen=True, slots=True, kw_only=True)
class PredictorConfig:
    """Architecture and horizons of the trajectory transformer."""

    history_steps: int = 10
    """H: observed steps, the current one included."""
    future_steps: int = 10
    """F: predicted steps."""
    num_neighbours: int = 8
    """K: context vehicles per agent."""
    d_model: int = 64
    """Token width."""
    num_heads: int = 4
    """Attention heads; must divide d_model."""
    num_layers: int = 2
    """Agent-query transformer layers (the agent token attends to all tokens)."""
    num_context_layers: int = 0
    """Full self-attention layers over all tokens before the agent-query layers (slower)."""
    ff_dim: int = 256
    """Feed-forward width inside each layer."""
    dropout: float = 0.0
    """Dropout inside the encoder (0 keeps training deterministic and fast)."""
    correction: str = "gated"
    """How the correction to constant velocity is shaped: plain, bounded, gated, bounded-gated (module doc)."""
    correction_speed_mps: float = 1.0
    """bounded: speed error the correction may make up, m/s (the linear part of the bound)."""
    correction_accel_mps2: float = 3.0
    """bounded: acceleration the correction may add, m/s², along each axis (the quadratic part)."""
    dt_s: float = 0.05
    """Step of the data, seconds (the corpus's 20 Hz); only the bound uses it."""
    velocity_window: int = 10
    """Steps of the agent's history the constant-velocity base fits its velocity to (least squares; 1: the
    last step's difference, as checkpoints from before this field). Positions measured with noise (SUMO
    writes centimetres, a dataset its tracker's error) make a one-step velocity jitter; a fit over 0.5 s
    does not, and the correction learns what the fit lags. At most the history is used."""
    base: str = "constant-velocity"
    """What the correction is a residual over (:data:`BASES`): the constant-velocity extrapolation, or the
    lane-aware one (``baselines.lane_aware_velocity``), which reads the road's direction and lane centres from
    the neighbours, keeps the fitted speed along the road, ends a lane change at the next lane centre and
    holds the lateral position otherwise."""
    lane_width_m: float = 3.5
    """lane-aware: the lanes' width, metres (lcsim's and the SUMO highway's)."""
    lane_margin_m: float = 0.1
    """lane-aware: a lane centre nearer than this ahead of a lane-changing agent is the one it leaves, metres."""
    lane_change_mps: float = 0.2
    """lane-aware: lateral speed above which the agent counts as changing lanes, m/s."""
    lane_approach_m: float = 0.8
    """lane-aware: the last stretch of a lane change, covered with an exponentially falling speed, metres."""
    lane_lateral_window: int = 2
    """lane-aware: steps the agent's lateral speed is fitted to (2: the last step's difference)."""
    lane_smooth_window: int = 3
    """lane-aware: steps the agent's speed along the road is fitted to where its positions do not jitter."""
    lane_smooth_jitter_m: float = 0.001
    """lane-aware: the jitter (mean absolute deviation of the second differences from their mean over
    ``velocity_window`` steps) below which positions count as smooth, metres."""
    lane_hold_mps: float = 0.1
    """lane-aware: lateral speed below which a neighbour counts as holding its lane (so marks a centre), m/s."""

    def __post_init__(self) -> None:
        ints = (
            "history_steps",
            "future_steps",
            "num_neighbours",
            "d_model",
            "num_heads",
            "num_layers",
            "ff_dim",
            "num_context_layers",
        )
        for name in ints:
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError(f"{name} must be an int, got {value!r}")
            if value > LIMITS[name]:
                raise ValueError(f"{name} must be at most {LIMITS[name]}, got {value}")
        if self.history_steps < 3:
            raise ValueError(f"history_steps must be >= 3, got {self.history_steps}")
        for name in ("future_steps", "d_model", "num_heads", "num_layers", "ff_dim"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.num_context_layers < 0:
            raise ValueError(f"num_context_layers must be >= 0, got {self.num_context_layers}")
        if self.num_neighbours < 0:
            raise ValueError(f"num_neighbours must be >= 0, got {self.num_neighbours}")
        if self.d_model % self.num_heads:
            raise ValueError(f"num_heads ({self.num_heads}) must divide d_model ({self.d_model})")
        if not isinstance(self.dropout, int | float) or isinstance(self.dropout, bool) or not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout!r}")
        if not isinstance(self.velocity_window, int) or isinstance(self.velocity_window, bool) or self.velocity_window < 1:
            raise ValueError(f"velocity_window must be an int >= 1, got {self.velocity_window!r}")
        if self.velocity_window > LIMITS["velocity_window"]:
            raise ValueError(f"velocity_window must be at most {LIMITS['velocity_window']}, got {self.velocity_window}")
        if not isinstance(self.correction, str) or self.correction not in CORRECTIONS:
            raise ValueError(f"correction must be one of {', '.join(CORRECTIONS)}; got {self.correction!r}")
        if not isinstance(self.base, str) or self.base not in BASES:
            raise ValueError(f"base must be one of {', '.join(BASES)}; got {self.base!r}")
        for name in ("lane_lateral_window", "lane_smooth_window"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 2 <= value <= LIMITS[name]:
                raise ValueError(f"{name} must be an int in [2, {LIMITS[name]}], got {value!r}")
        for name in ("correction_speed_mps", "correction_accel_mps2", "dt_s", "lane_width_m", "lane_margin_m",
                     "lane_change_mps", "lane_hold_mps", "lane_approach_m", "lane_smooth_jitter_m"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a number > 0, got {value!r}")
            if value > LIMITS[name]:
                raise ValueError(f"{name} must be at most {LIMITS[name]}, got {value!r}")
        params = self.parameter_estimate()
        if params > MAX_PARAMETERS:
            raise ValueError(f"the network these sizes describe has about {params:.3g} weights, more than "
                             f"{MAX_PARAMETERS:.0e}; lower d_model, ff_dim or the layer counts")

    def parameter_estimate(self) -> int:
        """About how many weights a network of these sizes has (the token MLP, every layer's attention and
        feed-forward, the head): what :data:`MAX_PARAMETERS` bounds before any is allocated."""
        d, ff = self.d_model, self.ff_dim
        token_in = self.history_steps * (FEATURES_PER_STEP + 1)
        layer = 4 * d * d + 2 * d * ff + 9 * d + ff
        head_out = 2 * self.future_steps * 2
        return token_in * d + 3 * d * d + (self.num_layers + self.num_context_layers) * layer + d * head_out

    @property
    def bounded(self) -> bool:
        """Whether the residual is tanh-bounded."""
        return self.correction in ("bounded", "bounded-gated")

    @property
    def gated(self) -> bool:
        """Whether a confidence gate scales the residual."""
        return self.correction in ("gated", "bounded-gated")

    def correction_bound_m(self) -> list[float]:
        """``b_k`` of the bounded correction for ``k = 1..F``, metres (module doc)."""
        t = [k * self.dt_s for k in range(1, self.future_steps + 1)]
        return [self.correction_speed_mps * ti + 0.5 * self.correction_accel_mps2 * ti * ti for ti in t]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PredictorConfig:
        """A stored config: a field it lacks gets the value it had before the field existed
        (:data:`LEGACY_VALUES`, so an old checkpoint computes what it always did), else the default."""
        if not isinstance(data, dict):
            raise ValueError(f"a PredictorConfig is a JSON object, got {type(data).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"unknown PredictorConfig fields: {sorted(map(str, unknown))[:5]}")
        try:
            return cls(**{**{k: v for k, v in LEGACY_VALUES.items() if k not in data}, **data})
        except TypeError as exc:  # a value of a type no check expected
            raise ValueError(f"PredictorConfig: a value of the wrong type ({exc})") from None


def token_features(pos: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-step kinematic features of every token, zero where not available.

    Args:
        pos: ``(N, T, H, 2)`` positions.
        mask: ``(N, T, H)`` bool presence.

    Returns:
        ``(N, T, H, 6)``: position, backward-difference velocity (both steps present, else 0),
        backward-difference acceleration (three steps present, else 0).
    """
    m = mask.to(pos.dtype).unsqueeze(-1)
    p = torch.where(mask.unsqueeze(-1), pos, torch.zeros_like(pos))  # NaN-safe, unlike pos * m
    v = torch.zeros_like(p)
    mv = m[..., 1:, :] * m[..., :-1, :]
    v[..., 1:, :] = (p[..., 1:, :] - p[..., :-1, :]) * mv
    a = torch.zeros_like(p)
    ma = mv[..., 1:, :] * mv[..., :-1, :]
    a[..., 2:, :] = (v[..., 2:, :] - v[..., 1:-1, :]) * ma
    return torch.cat((p, v, a), dim=-1)


def cv_extrapolate(hist: torch.Tensor, mask: torch.Tensor, future_steps: int, window: int = 1) -> torch.Tensor:
    """Constant-velocity extrapolation from the last position (torch twin of ``baselines.constant_velocity``,
    and of ``baselines.constant_velocity_fit`` for ``window`` > 1).

    Args:
        hist: ``(N, H, 2)``.
        mask: ``(N, H)`` bool.
        future_steps: F.
        window: 1, the velocity of the last step's difference; W > 1, the least-squares slope of the valid
            positions among the last W (the one-step velocity where fewer than 3 are valid).

    Returns:
        ``(N, F, 2)``; for an invalid last step the velocity is 0.
    """
    v = _last_velocity(hist, mask)
    if window > 1:
        w = mask[:, -window:].to(hist.dtype).unsqueeze(-1)  # (N, W, 1)
        t = torch.arange(window, dtype=hist.dtype, device=hist.device).view(1, -1, 1)
        cnt = w.sum(1, keepdim=True)
        t_mean = (w * t).sum(1, keepdim=True) / cnt.clamp_min(1.0)
        p = hist[:, -window:]
        p_mean = (w * p).sum(1, keepdim=True) / cnt.clamp_min(1.0)
        dt = (t - t_mean) * w
        slope = (dt * (p - p_mean)).sum(1) / (dt * (t - t_mean)).sum(1).clamp_min(1e-12)
        fit = (cnt[:, 0] >= 3) & mask[:, -1:]
        v = torch.where(fit, slope, v)
    k = torch.arange(1, future_steps + 1, dtype=hist.dtype, device=hist.device).view(1, -1, 1)
    return hist[:, -1:, :] + k * v.unsqueeze(1)


def _masked_slope(p: torch.Tensor, m: torch.Tensor, window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Least-squares velocity ``(..., 2)`` of the valid positions among the last ``window`` of ``(..., H, 2)`` and
    how many there are ``(...,)``."""
    w = m[..., -window:].to(p.dtype).unsqueeze(-1)
    q = torch.where(w > 0, p[..., -window:, :], torch.zeros_like(p[..., -window:, :]))
    t = torch.arange(window, dtype=p.dtype, device=p.device).view(-1, 1)
    cnt = w.sum(-2, keepdim=True)
    t_mean = (w * t).sum(-2, keepdim=True) / cnt.clamp_min(1.0)
    q_mean = (w * q).sum(-2, keepdim=True) / cnt.clamp_min(1.0)
    dt = (t - t_mean) * w
    return (dt * (q - q_mean)).sum(-2) / (dt * (t - t_mean)).sum(-2).clamp_min(1e-12), cnt[..., 0, 0]


def lane_extrapolate(pos: torch.Tensor, mask: torch.Tensor, future_steps: int, window: int, *,
                     smooth_window: int = 3, smooth_jitter_m: float = 0.001, lateral_window: int = 2,
                     lane_width_m: float = 3.5, margin_m: float = 0.1, approach_m: float = 0.8, move_mps: float = 0.2,
                     still_mps: float = 0.1, dt_s: float = 0.05) -> torch.Tensor:
    """The lane-aware base (torch twin of ``baselines.lane_aware_velocity``, which documents it and its arguments).

    An agent history with gaps in its last ``window`` steps counts as jittering (its velocity: that of
    :func:`cv_extrapolate`), and its lateral speed is that velocity's where the last ``lateral_window`` steps are
    not all valid.

    Args:
        pos: ``(N, 1+K, H, 2)`` token positions, token 0 the agent.
        mask: ``(N, 1+K, H)`` bool presence.
        future_steps: F.
        window: steps the velocities are fitted to (at least 3 for the neighbours' fit to mean anything).

    Returns:
        ``(N, F, 2)``.
    """
    hist, agent_mask = pos[:, 0], mask[:, 0]
    hist = torch.where(agent_mask.unsqueeze(-1), hist, torch.zeros_like(hist))
    n = pos.shape[0]
    v_fit = cv_extrapolate(hist, agent_mask, 1, window)[:, 0] - hist[:, -1]  # the fitted velocity, or its fallback
    complete = agent_mask[:, -window:].all(-1)
    second = hist[:, -window:][:, 2:] - 2 * hist[:, -window:][:, 1:-1] + hist[:, -window:][:, :-2]
    jitter = (second - second.mean(1, keepdim=True)).abs().sum(-1).mean(1)
    smooth = complete & (jitter < smooth_jitter_m)
    v_agent = torch.where(smooth.unsqueeze(-1), _masked_slope(hist, agent_mask, smooth_window)[0], v_fit)
    if pos.shape[1] < 2:
        return hist[:, -1:, :] + torch.arange(1, future_steps + 1, dtype=pos.dtype, device=pos.device).view(1, -1, 1) * v_agent.unsqueeze(1)
    v_lat, lat_cnt = _masked_slope(hist, agent_mask, lateral_window)
    v_lateral = torch.where(((lat_cnt >= lateral_window) & agent_mask[:, -1]).unsqueeze(-1), v_lat, v_fit)
    neighbours, n_mask = pos[:, 1:], mask[:, 1:]
    v_n, cnt = _masked_slope(neighbours, n_mask, window)  # (N, K, 2)
    ok = (cnt >= 3) & n_mask[..., -1] & (v_n.norm(dim=-1) > 0.5 * dt_s)
    inf = torch.full_like(v_n[..., 0], float("inf"))
    angle = torch.where(ok, torch.atan2(v_n[..., 1], v_n[..., 0]), inf).sort(dim=1).values
    count = ok.sum(1)
    middle = torch.stack(((count - 1).clamp_min(0) // 2, count // 2), 1).clamp_max(angle.shape[1] - 1)
    theta = torch.where(count > 0, angle.gather(1, middle).mean(1), torch.zeros_like(angle[:, 0]))
    c, s = torch.cos(theta), torch.sin(theta)

    def to_road(v: torch.Tensor) -> torch.Tensor:  # rotate by -theta
        shape = (n,) + (1,) * (v.dim() - 2)
        cc, ss = c.view(shape), s.view(shape)
        return torch.stack((cc * v[..., 0] + ss * v[..., 1], cc * v[..., 1] - ss * v[..., 0]), -1)

    last_n = torch.where(n_mask[..., -1:], neighbours[:, :, -1] - hist[:, None, -1], torch.zeros_like(neighbours[:, :, -1]))
    lateral_n = to_road(last_n)[..., 1]
    holding = ok & (to_road(v_n)[..., 1].abs() < still_mps * dt_s)
    phase_angle = 2 * math.pi * lateral_n / lane_width_m
    zero = torch.zeros_like(phase_angle)
    phase = torch.atan2(torch.where(holding, phase_angle.sin(), zero).sum(1),
                        torch.where(holding, phase_angle.cos(), zero).sum(1)) * lane_width_m / (2 * math.pi)  # fmt: skip
    road = holding.any(1) & agent_mask[:, -1]
    vy = to_road(v_lateral)[:, 1]
    sign = torch.sign(vy)
    speed = vy.abs().clamp_min(1e-9)
    changing = vy.abs() > move_mps * dt_s
    steps = (sign * margin_m - phase) / lane_width_m
    distance = (phase + lane_width_m * torch.where(sign > 0, torch.ceil(steps), torch.floor(steps))).abs()
    last = distance.clamp_max(approach_m)
    k = torch.arange(1, future_steps + 1, dtype=pos.dtype, device=pos.device).view(1, -1)
    straight = torch.minimum(speed.unsqueeze(1) * k, (distance - last).unsqueeze(1))
    settle = last.unsqueeze(1) * -torch.expm1(-(k - ((distance - last) / speed).unsqueeze(1)).clamp_min(0.0)
                                              * (speed / last.clamp_min(1e-9)).unsqueeze(1))  # fmt: skip
    across = torch.where(changing.unsqueeze(1), sign.unsqueeze(1) * (straight + settle), torch.zeros_like(straight))
    along = to_road(v_agent)[:, :1] * k
    cc, ss = c.unsqueeze(1), s.unsqueeze(1)
    lane = torch.stack((cc * along - ss * across, ss * along + cc * across), -1)
    fitted = v_agent.unsqueeze(1) * k.unsqueeze(-1)
    return hist[:, -1:, :] + torch.where(road.view(-1, 1, 1), lane, fitted)


def _last_velocity(hist: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``(N, 2)`` the backward-difference velocity at the last step, per step (0 when it is not known)."""
    h = hist.shape[-2]
    earlier = mask[:, :-1].flip(-1)  # index 0 is step H-2
    back = earlier.to(torch.int64).argmax(-1) + 1  # (N,)
    ok = earlier.any(-1) & mask[:, -1]
    j = (h - 1 - back).view(-1, 1, 1).expand(-1, 1, 2)
    pj = hist.gather(1, j)[:, 0]
    v = (hist[:, -1] - pj) / back.unsqueeze(-1).to(hist.dtype)
    return torch.where(ok.unsqueeze(-1), v, torch.zeros_like(v))


class AgentAttentionLayer(nn.Module):
    """Pre-norm transformer layer whose only query is the agent token.

    ``forward(agent (N, d), tokens (N, T, d), keep (N, T) bool) -> (N, d)``; ``keep[:, 0]`` must be
    True (the agent attends at least to itself, so no row is fully masked and no NaN can appear).

    The key/value projection ``kv`` is never applied to the T tokens: with a single query, the key
    projection folds into the query (``score_t = x_t . (W_k^T q) + b_k . q`` per head) and the value
    projection moves behind the attention pooling (``sum_t w_t (W_v x_t + b_v) = W_v (sum_t w_t x_t)
    + b_v sum_t w_t``). Same function and parameters as projecting every token, about a fifth of
    the multiply-adds at T = 9, d = 64, 4 heads.
    """

    def __init__(self, d_model: int, num_heads: int, ff_dim: int, dropout: float) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.norm_q = nn.LayerNorm(d_model)
        self.norm_kv = nn.LayerNorm(d_model)
        self.q = nn.Linear(d_model, d_model)
        self.kv = nn.Linear(d_model, 2 * d_model)
        self.out = nn.Linear(d_model, d_model)
        self.norm_ff = nn.LayerNorm(d_model)
        self.ff = nn.Sequential(nn.Linear(d_model, ff_dim), nn.GELU(), nn.Linear(ff_dim, d_model))
        self.dropout = nn.Dropout(dropout)

    def forward(self, agent: torch.Tensor, tokens: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
        return self.attend(agent, F.layer_norm(tokens, tokens.shape[-1:], eps=self.norm_kv.eps), keep)

    def attend(self, agent: torch.Tensor, normed: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` with the tokens already standardised by a LayerNorm *without* its affine
        part (``norm_kv``'s weight and bias are applied here), so that layers can share that work."""
        n, _, d = normed.shape
        h = self.num_heads
        dh = d // h
        q = self.q(self.norm_q(agent)).view(n, h, dh) * dh**-0.5
        w_k, w_v = self.kv.weight.view(2, h, dh, d).unbind(0)  # rows of kv: (key|value, head, channel)
        b_k, b_v = self.kv.bias.view(2, h, dh).unbind(0)
        gamma, beta = self.norm_kv.weight, self.norm_kv.bias
        # Query folded into the key projection (and the LayerNorm's affine part): (N, h, d), (N, h).
        qk = torch.bmm(q.transpose(0, 1), w_k).transpose(0, 1)
        offset = (q * b_k).sum(-1) + qk @ beta
        scores = torch.bmm(qk * gamma, normed.transpose(1, 2)).transpose(1, 2) + offset.unsqueeze(1)  # (N, T, h)
        scores = scores.masked_fill(~keep.unsqueeze(-1), float("-inf"))
        weights = self.dropout(scores.softmax(dim=1))
        weight_sum = weights.sum(1).unsqueeze(-1)  # (N, h, 1): 1 unless dropout is active
        pooled = torch.bmm(weights.transpose(1, 2), normed) * gamma + weight_sum * beta  # (N, h, d)
        attended = torch.bmm(pooled.transpose(0, 1), w_v.transpose(1, 2)).transpose(0, 1)  # (N, h, dh)
        attended = (attended + weight_sum * b_v).reshape(n, d)
        agent = agent + self.dropout(self.out(attended))
        return agent + self.dropout(self.ff(self.norm_ff(agent)))


class TrajectoryTransformer(nn.Module):
    """``forward(pos (N, 1+K, H, 2), mask (N, 1+K, H)) -> (N, F, 2)`` agent future in the agent frame."""

    def __init__(self, config: PredictorConfig) -> None:
        super().__init__()
        self.config = config
        h, f, d = config.history_steps, config.future_steps, config.d_model
        feat = h * (FEATURES_PER_STEP + 1)
        self.embed = nn.Sequential(nn.Linear(feat, d), nn.GELU(), nn.Linear(d, d))
        self.type_embedding = nn.Parameter(torch.zeros(2, d))  # 0: agent, 1: neighbour
        self.context: nn.TransformerEncoder | None = None
        if config.num_context_layers:
            layer = nn.TransformerEncoderLayer(
                d,
                config.num_heads,
                config.ff_dim,
                config.dropout,
                activation="gelu",
                batch_first=True,
                norm_first=True,
            )
            self.context = nn.TransformerEncoder(layer, config.num_context_layers, enable_nested_tensor=False)
        self.layers = nn.ModuleList(
            AgentAttentionLayer(d, config.num_heads, config.ff_dim, config.dropout)
            for _ in range(config.num_layers)
        )
        self.head = nn.Sequential(nn.LayerNorm(d), nn.Linear(d, d), nn.GELU(), nn.Linear(d, f * 2))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)
        # Confidence gate, one logit per future step; it starts half open (sigmoid(0)).
        self.gate: nn.Linear | None = None
        if config.gated:
            self.gate = nn.Linear(d, f)
            nn.init.zeros_(self.gate.weight)
            nn.init.zeros_(self.gate.bias)
            self.register_buffer("familiar_limit", torch.tensor(float("inf")))  # set by fit_normalisation
        if config.bounded:
            self.register_buffer(
                "correction_bound", torch.tensor(config.correction_bound_m()).unsqueeze(-1), persistent=False
            )
        # Normalisation statistics (training split only), see fit_normalisation.
        self.register_buffer("agent_mean", torch.zeros(h, FEATURES_PER_STEP))
        self.register_buffer("agent_std", torch.ones(h, FEATURES_PER_STEP))
        self.register_buffer("neighbour_mean", torch.zeros(h, FEATURES_PER_STEP))
        self.register_buffer("neighbour_std", torch.ones(h, FEATURES_PER_STEP))
        self.register_buffer("residual_mean", torch.zeros(f, 2))
        self.register_buffer("residual_std", torch.ones(f, 2))
        self._orders: dict[int, torch.Tensor] = {}

    @torch.no_grad()
    def fit_normalisation(self, pos: torch.Tensor, mask: torch.Tensor, future: torch.Tensor) -> None:
        """Set the standardisation buffers from training windows.

        Args:
            pos: ``(N, 1+K, H, 2)`` training token positions.
            mask: ``(N, 1+K, H)`` bool.
            future: ``(N, F, 2)`` agent futures.
        """
        feats = token_features(pos.double(), mask)
        m = mask.unsqueeze(-1).double()

        def masked_stats(x: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            dims = tuple(range(x.dim() - 2))
            cnt = w.sum(dims).clamp_min(1.0)
            mean = (x * w).sum(dims) / cnt
            var = (((x - mean) ** 2) * w).sum(dims) / cnt
            return mean, var.sqrt().clamp_min(MIN_STD)

        am, asd = masked_stats(feats[:, 0], m[:, 0])
        nm, nsd = masked_stats(feats[:, 1:], m[:, 1:]) if pos.shape[1] > 1 else (am, asd)
        residual = future.double() - self.base_prediction(pos.double(), mask)
        self.agent_mean.copy_(am)
        self.agent_std.copy_(asd)
        self.neighbour_mean.copy_(nm)
        self.neighbour_std.copy_(nsd)
        self.residual_mean.copy_(residual.mean(0))
        self.residual_std.copy_(residual.std(0).clamp_min(MIN_STD))
        if self.gate is not None:
            z = ((feats[:, 0] - am) / asd).clamp(-CLIP, CLIP) * m[:, 0]
            motion = self._motion_rms(z.transpose(1, 2))
            self.familiar_limit.copy_(torch.quantile(motion, FAMILIAR_QUANTILE).clamp_min(MIN_STD))

    @staticmethod
    def _motion_rms(z: torch.Tensor) -> torch.Tensor:
        """RMS of the standardised velocities and accelerations ``z[:, 2:6, 2:]`` of ``(N, 6+, H)`` features."""
        return z[:, 2:6, 2:].pow(2).mean((1, 2)).sqrt()

    def familiarity(self, pos: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``(N,)`` in [0, 1]: 1 for agent motion like the training windows', 0 for motion far outside them
        (module doc); all ones for a model without a gate."""
        x, _ = self._standardised_inputs(pos, mask)
        return self._familiarity(x)

    def _familiarity(self, x: torch.Tensor) -> torch.Tensor:
        n, _, width = x.shape
        if self.gate is None:
            return x.new_ones(n)
        z = x[:, 0].view(n, FEATURES_PER_STEP + 1, width // (FEATURES_PER_STEP + 1))
        return (2.0 - self._motion_rms(z) / self.familiar_limit).clamp(0.0, 1.0)

    def forward(self, pos: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Predict the agent's (token 0) future.

        Args:
            pos: ``(N, 1+K, H, 2)`` float32 positions in the agent frame.
            mask: ``(N, 1+K, H)`` bool presence.

        Returns:
            ``(N, F, 2)`` future positions in the agent frame.
        """
        return self.predict_with_gate(pos, mask)[0]

    def predict_with_gate(self, pos: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`forward` and the confidence gate ``(N, F)`` in [0, 1] behind it (None when not gated)."""
        cv, residual, gate = self.prediction_parts(pos, mask)
        if gate is None:
            return cv + residual, None
        return cv + residual * gate.unsqueeze(-1), gate

    def prediction_parts(
        self, pos: torch.Tensor, mask: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The parts of a prediction: the constant-velocity extrapolation ``(N, F, 2)``, the (bounded)
        correction ``(N, F, 2)`` before the gate, and the gate ``(N, F)`` (None when not gated)."""
        agent, agent_pos, x = self._encode(pos, mask)
        n, f = agent.shape[0], self.config.future_steps
        out = self.head(agent).view(n, f, 2)
        residual = out * self.residual_std + self.residual_mean
        if self.config.bounded:
            residual = self.correction_bound * torch.tanh(residual / self.correction_bound)
        gate = None
        if self.gate is not None:
            gate = torch.sigmoid(self.gate(agent)) * self._familiarity(x).unsqueeze(-1)
        if self.config.base == "lane-aware":
            return self.base_prediction(pos, mask), residual, gate
        window = min(self.config.velocity_window, agent_pos.shape[1])
        return cv_extrapolate(agent_pos, mask[:, 0], f, window), residual, gate

    def base_prediction(self, pos: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``(N, F, 2)`` the extrapolation the correction is added to (:attr:`PredictorConfig.base`)."""
        c = self.config
        window = min(c.velocity_window, pos.shape[2])
        if c.base == "lane-aware":
            return lane_extrapolate(pos, mask, c.future_steps, window, smooth_window=min(c.lane_smooth_window, window),
                                    smooth_jitter_m=c.lane_smooth_jitter_m,
                                    lateral_window=min(c.lane_lateral_window, window), lane_width_m=c.lane_width_m,
                                    margin_m=c.lane_margin_m, approach_m=c.lane_approach_m,
                                    move_mps=c.lane_change_mps, still_mps=c.lane_hold_mps, dt_s=c.dt_s)  # fmt: skip
        agent = torch.where(mask[:, 0].unsqueeze(-1), pos[:, 0], torch.zeros_like(pos[:, 0]))
        return cv_extrapolate(agent, mask[:, 0], c.future_steps, window)

    def _encode(self, pos: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The agent's output token ``(N, d)``, its masked history positions ``(N, H, 2)`` and the token
        inputs ``(N, T, 7 * H)`` (:meth:`_standardised_inputs`)."""
        _n, t, h, _ = pos.shape
        if h != self.config.history_steps:
            raise ValueError(f"expected {self.config.history_steps} history steps, got {h}")
        x, agent_pos = self._standardised_inputs(pos, mask)  # x: (N, T, 7 * H), step-minor layout
        embed_in, embed_out = self.embed[0], self.embed[2]
        tok = self.embed[1](F.linear(x, embed_in.weight[:, self._input_order(h)], embed_in.bias))
        type_bias = torch.cat((self.type_embedding[:1], self.type_embedding[1:].expand(t - 1, -1))) + embed_out.bias
        tok = torch.matmul(tok, embed_out.weight.t()).add_(type_bias)  # embed's last layer + type embedding
        pad = ~mask.any(-1)
        pad[:, 0] = False  # the agent token is always attended to: no all-padding rows, no NaN
        if self.context is not None:
            tok = self.context(tok, src_key_padding_mask=pad)
        agent = tok[:, 0]
        keep = ~pad
        normed: dict[float, torch.Tensor] = {}  # LayerNorm without affine part, shared by the layers
        for layer in self.layers:
            eps = layer.norm_kv.eps
            if eps not in normed:
                normed[eps] = F.layer_norm(tok, tok.shape[-1:], eps=eps)
            agent = layer.attend(agent, normed[eps], keep)
        return agent, agent_pos, x

    def _input_order(self, h: int) -> torch.Tensor:
        """Columns of ``embed[0].weight`` in the order of :meth:`_standardised_inputs`' layout
        (feature-major: x of all steps, y, vx, vy, ax, ay, presence) rather than the checkpoint's
        step-major order (step 0: x, y, vx, vy, ax, ay, presence; step 1: ...)."""
        order = self._orders.get(h)
        if order is None:
            per_step = FEATURES_PER_STEP + 1
            order = self._orders[h] = torch.arange(h * per_step).view(h, per_step).t().reshape(-1)
        return order

    def _standardised_inputs(self, pos: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Token inputs and the agent's masked positions ``(N, H, 2)``.

        The inputs are :func:`token_features`, standardised with the agent/neighbour statistics,
        clipped to ``CLIP`` and zeroed where absent, then the presence flag: the same numbers as
        ``cat((((token_features - mean) / std).clamp(-CLIP, CLIP) * m, m), -1)``, but laid out
        feature-major per token, ``(N, T, 7 * H)`` = (x of steps 0..H-1, y, vx, vy, ax, ay, presence),
        so that every operation runs over contiguous rows of H values or more instead of pairs.
        """
        n, t, h, _ = pos.shape
        x = pos.new_empty(n, t, FEATURES_PER_STEP + 1, h)
        m = x[:, :, 6]  # (N, T, H)
        m.copy_(mask)
        present = mask.unsqueeze(2)  # (N, T, 1, H)
        p = x[:, :, 0:2]
        torch.where(present, pos.transpose(-1, -2), pos.new_zeros(()), out=p)  # garbage behind the mask -> 0
        agent_pos = p[:, 0].transpose(-1, -2).contiguous()  # (N, H, 2), before standardising in place
        rows = x.view(n * t, (FEATURES_PER_STEP + 1) * h)
        # Backward differences along the steps on rows (x_0..x_H-1, y_0..y_H-1): step 0 of each
        # coordinate gets garbage (or nothing) and is set to zero; mv[h] = m[h] * m[h-1] (0 at h = 0).
        mv = torch.zeros_like(m)
        torch.mul(m[..., 1:], m[..., :-1], out=mv[..., 1:])
        ma = torch.zeros_like(m)
        torch.mul(mv[..., 2:], mv[..., 1:-1], out=ma[..., 2:])
        for src, dst, weight in ((0, 2 * h, mv), (2 * h, 4 * h, ma)):  # v from p, a from v
            torch.sub(rows[:, src + 1 : src + 2 * h], rows[:, src : src + 2 * h - 1], out=rows[:, dst + 1 : dst + 2 * h])
            out = x[:, :, dst // h : dst // h + 2]
            out[..., 0] = 0.0
            if dst == 4 * h:
                out[..., 1] = 0.0
            out.mul_(weight.unsqueeze(2))
        mean = torch.cat((self.agent_mean.t().unsqueeze(0), self.neighbour_mean.t().expand(t - 1, -1, -1)))
        std = torch.cat((self.agent_std.t().unsqueeze(0), self.neighbour_std.t().expand(t - 1, -1, -1)))
        x[:, :, :6].sub_(mean).div_(std).clamp_(-CLIP, CLIP).mul_(present)
        return x.view(n, t, (FEATURES_PER_STEP + 1) * h), agent_pos
