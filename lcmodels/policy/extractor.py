"""The hybrid features extractor: one branch per observation key, concatenated.

- ``image`` (3, 120, 120) uint8, scaled to [0, 1] by stable-baselines3: the paper's VGG-16
  (:class:`VGG16`, 13 convolutions and 5 poolings, then two linear layers down to 10 features) or the
  compact VGG-style default (:class:`CompactVGG`, three 3x3-convolution blocks on the image average-pooled
  to 40x40; about 4000x fewer multiply-adds, so it trains on a CPU), or the same with stride-2 convolutions
  in place of the max poolings (:class:`StridedCompact`, a quarter of the compact network's multiply-adds).
  The compact networks' first layer, the average pooling, is linear: training and the frozen branch
  compute it once per image from the uint8 pixels (:func:`pooled_images`) and feed the rest of the network.
- ``current`` (1+K, 9): the ego and its K neighbour slots (:data:`lcsim.core.CURRENT_FEATURES`; a tenth
  column, the acceleration, with ``ScenarioConfig.observe_acceleration``), scaled per column to order
  one, flattened, two-layer MLP. With ``contact_features`` the MLP also gets, per slot, the time to
  contact, the bumper gap and a proximity (:class:`ContactFeatures`): quotients a ReLU network
  approximates poorly from the raw columns, and the quantities a lane change hinges on. With
  ``window_features``, also when over the next 16 s each side lane has room for a change, against when
  the leader traps the ego (:class:`WindowFeatures`; a second such look with the accelerations kept when
  there is the acceleration column).
  With ``sensor_encoder="attention"`` the rows are read as a set instead (:class:`EgoAttention`): each
  vehicle embedded by one shared network, then the ego attends to every sensed vehicle (the ego-attention
  of Leurent and Mercat, "Social Attention for Autonomous Decision-Making in Dense Traffic", 2019): the
  weights do not depend on which slot a vehicle is in or on how many slots there are.
- ``prediction`` (K, F, 2): predicted neighbour positions in the ego frame, scaled, flattened, MLP.

The output size is the sum of the branch sizes and is computed here (``features_dim``), so the policy
and value heads adapt to whichever keys the observation mode keeps.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from lcmodels.policy.names import IMAGE_FEATURES, IMAGE_NETS, SENSOR_ENCODERS
from lcsim.config import LANE_SLOTS
from lcsim.core import CURRENT_FEATURES

# Scales of the `current` columns x, y, vx, vy, yaw, speed, lane, target_lane, present (and accel_mps2,
# with ScenarioConfig.observe_acceleration).
CURRENT_SCALE = (50.0, 10.0, 10.0, 2.0, 1.0, 10.0, 4.0, 4.0, 1.0)
ACCEL_SCALE = 2.0
PREDICTION_SCALE = (50.0, 10.0)
# ContactFeatures: bumper gap = |x| - CONTACT_BODY_M (the mean of the ego's and a traffic vehicle's length,
# 4.18 m and 5.37 m, rounded), times to contact capped at CONTACT_HORIZON_S.
CONTACT_BODY_M = 4.8
CONTACT_HORIZON_S = 10.0
_X, _VX, _PRESENT = (CURRENT_FEATURES.index(name) for name in ("x_m", "vx_mps", "present"))
_ACCEL = len(CURRENT_FEATURES)  # the acceleration column, when there is one
# WindowFeatures: a look over the next WINDOW_HORIZON_S on a grid of WINDOW_STEP_S, every vehicle at its
# present relative speed; a change needs its gap for WINDOW_CHANGE_S (about the 2 s lateral move, plus the
# start); a gap is clear of a vehicle WINDOW_MARGIN_M beyond the bodies, plus WINDOW_HEADWAY_S times the
# speed at which it closes; the ego is trapped when its leader is WINDOW_MARGIN_M ahead of the bodies.
WINDOW_HORIZON_S = 16.0
WINDOW_STEP_S = 0.5
WINDOW_CHANGE_S = 2.5
WINDOW_MARGIN_M = 2.0
WINDOW_HEADWAY_S = 1.0
# With the acceleration column, a second look in which each vehicle keeps its acceleration relative to the
# ego's for WINDOW_ACCEL_S (about how long an IDM follower or a braking leader keeps it), then its speed.
WINDOW_ACCEL_S = 2.5

# torchvision's VGG-16 layer plan ("D"): channels, "M" = 2x2 max pooling.
VGG16_PLAN: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M",
                                     512, 512, 512, "M")  # fmt: skip


def _vgg_features(plan: tuple[int | str, ...], in_channels: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    c = in_channels
    for item in plan:
        if item == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c, int(item), 3, padding=1), nn.ReLU(inplace=True)]
            c = int(item)
    return nn.Sequential(*layers)


class VGG16(nn.Module):
    """VGG-16 as in the paper: 3x120x120 -> 10 features (13 conv layers, 5 poolings, 512x3x3 map)."""

    def __init__(self, in_channels: int = 3, size: int = 120, out_features: int = 10, hidden: int = 256) -> None:
        super().__init__()
        self.features = _vgg_features(VGG16_PLAN, in_channels)
        side = size // 32
        if side < 1:
            raise ValueError(f"VGG-16 needs images of at least 32x32 pixels, got {size}")
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(512 * side * side, hidden), nn.ReLU(inplace=True),
                                  nn.Linear(hidden, out_features), nn.ReLU(inplace=True))  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


IMAGE_POOL = 3
"""The compact networks' first layer: IMAGE_POOL x IMAGE_POOL average pooling (120 px -> 40 px)."""


def _pooled_forward(features: nn.Sequential, x: torch.Tensor, size: int) -> torch.Tensor:
    # A (size/IMAGE_POOL)-pixel input is the image pooled already (pooled_images): the rest of the layers.
    return features(x) if x.shape[-1] == size else features[1:](x)


def prepools(net: nn.Module) -> bool:
    """Whether ``net`` starts with the average pooling that :func:`pooled_images` computes ahead of it."""
    return isinstance(net, (CompactVGG, StridedCompact))


@numba.njit(cache=True, nogil=True)
def _pool_rows(images: np.ndarray, rows: np.ndarray, k: int, out: np.ndarray) -> None:
    n_c, side = out.shape[1], out.shape[2]
    inv = np.float32(1.0 / (k * k))
    for r in range(rows.size):
        src = rows[r]
        for c in range(n_c):
            for i in range(side):
                for j in range(side):
                    acc = 0
                    for a in range(k):
                        for b in range(k):
                            acc += images[src, c, i * k + a, j * k + b]
                    out[r, c, i, j] = np.float32(acc) * inv


def pooled_images(images: np.ndarray, rows: np.ndarray | None = None, k: int = IMAGE_POOL) -> np.ndarray:
    """``(N, C, S, S)`` uint8 images -> ``(len(rows), C, S // k, S // k)`` float32 means of k x k blocks.

    What the compact networks' first layer computes (``nn.AvgPool2d(k)``, the remainder rows and columns
    dropped), on the 0-255 scale, in one pass over the pixels of ``rows`` (default: all) and without the
    image ever held as floats: a ninth of the values stable-baselines3 then scales to [0, 1], which is how
    cloning and the frozen branch feed the networks (:func:`_pooled_forward` takes the smaller input for
    pooled). The same values as the pooling layer up to float rounding.
    """
    images = np.ascontiguousarray(images)
    if images.dtype != np.uint8 or images.ndim != 4:
        raise ValueError(f"pooled_images needs (N, C, S, S) uint8 images, got {images.dtype} {images.shape}")
    rows = np.arange(len(images)) if rows is None else np.asarray(rows, dtype=np.int64)
    out = np.empty((rows.size, images.shape[1], images.shape[2] // k, images.shape[3] // k), np.float32)
    _pool_rows(images, rows.astype(np.int64, copy=False), k, out)
    return out


class CompactVGG(nn.Module):
    """A small VGG-style network for the semantic bird's-eye image.

    3x3 average pooling first (120 px at 0.5 m -> 40 px at 1.5 m: a car is still 3x1 pixels, a lane 2),
    then three blocks of 3x3 convolution + ReLU + 2x2 max pooling (16, 32, 32 channels) and a linear
    layer: about 3.5 M multiply-adds per image, against 15 G for VGG-16.
    """

    def __init__(self, in_channels: int = 3, size: int = 120, out_features: int = 10) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.AvgPool2d(IMAGE_POOL),
            _vgg_features((16, "M", 32, "M", 32, "M"), in_channels),
        )
        side = size // IMAGE_POOL // 8
        if side < 1:
            raise ValueError(f"the compact VGG needs images of at least 24x24 pixels, got {size}")
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(32 * side * side, out_features), nn.ReLU(inplace=True))
        self.size = size

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(_pooled_forward(self.features, x, self.size))


class StridedCompact(nn.Module):
    """The compact network with its 2x2 max poolings folded into stride-2 convolutions.

    The same 3x3 average pooling first (40 px at 1.5 m), then three 3x3 convolutions of stride 2 + ReLU
    (16, 32, 32 channels: 20, 10 and 5 px) and a linear layer: the same channels and the same 8x reduction
    as :class:`CompactVGG`, each convolution computed at its output's resolution rather than its input's,
    so about 0.9 M multiply-adds per image against 3.5 M, and no max pooling (which costs a CPU more than
    the convolutions do).
    """

    def __init__(self, in_channels: int = 3, size: int = 120, out_features: int = 10) -> None:
        super().__init__()
        layers: list[nn.Module] = [nn.AvgPool2d(IMAGE_POOL)]
        c = in_channels
        for width in (16, 32, 32):
            layers += [nn.Conv2d(c, width, 3, stride=2, padding=1), nn.ReLU(inplace=True)]
            c = width
        self.features = nn.Sequential(*layers)
        side = size // IMAGE_POOL
        if side < 8:
            raise ValueError(f"the strided network needs images of at least 24x24 pixels, got {size}")
        for _ in range(3):
            side = (side + 1) // 2
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(32 * side * side, out_features), nn.ReLU(inplace=True))
        self.size = size

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(_pooled_forward(self.features, x, self.size))


def make_image_net(name: str, in_channels: int, size: int, out_features: int) -> nn.Module:
    if name == "compact":
        return CompactVGG(in_channels, size, out_features)
    if name == "strided":
        return StridedCompact(in_channels, size, out_features)
    if name == "vgg16":
        return VGG16(in_channels, size, out_features)
    raise ValueError(f"unknown image network {name!r}; choose one of {', '.join(IMAGE_NETS)}")


class ImageEncoder:
    """A frozen image branch run outside the policy: ``(B, 3, S, S)`` uint8 images -> ``(B, F)`` float32.

    The same computation as the branch inside :class:`HybridExtractor` (stable-baselines3 scales images to
    [0, 1] by dividing by 255 before the extractor sees them), without gradients. Training with it in the
    observation wrapper stores F numbers per step in the rollout buffer instead of an image, so the
    policy's update epochs do not run the network again.
    """

    def __init__(self, net: nn.Module, out_features: int) -> None:
        self.net = net.eval()
        for p in self.net.parameters():
            p.requires_grad_(False)
        self.out_features = out_features

    def __call__(self, images: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            if prepools(self.net):
                x = torch.from_numpy(pooled_images(np.asarray(images))) / 255.0
            else:
                x = torch.as_tensor(np.asarray(images)).float() / 255.0
            return self.net(x).numpy().astype(np.float32, copy=False)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return self.net.state_dict()


class ContactFeatures(nn.Module):
    """Per neighbour slot of ``current``: time to contact, bumper gap and proximity, each in [0, 1].

    From the slot's relative position ``x`` and velocity ``vx`` along the ego's heading (columns 0 and 2):
    the gap is ``|x| - CONTACT_BODY_M`` (at least 0), the closing speed ``-sign(x) vx`` (a leader that is
    slower, a follower that is faster), the time to contact ``gap / closing`` when closing, else
    ``CONTACT_HORIZON_S``. Outputs ``(B, 3K)``: ``ttc / horizon`` (capped at 1), ``gap / 50 m`` (capped at
    1), ``5 m / max(|x|, 1 m)``; an empty slot reads 1, 1, 0 (far, no contact).
    """

    def __init__(self, slots: int) -> None:
        super().__init__()
        self.out_features = 3 * slots

    def forward(self, current: torch.Tensor) -> torch.Tensor:
        nb = current[:, 1:]
        x, vx, present = nb[..., _X], nb[..., _VX], nb[..., _PRESENT] > 0.5
        gap = (x.abs() - CONTACT_BODY_M).clamp(min=0.0)
        closing = -torch.sign(x) * vx
        ttc = torch.where(closing > 0.05, gap / closing.clamp(min=0.05), torch.full_like(gap, CONTACT_HORIZON_S))
        ones = torch.ones_like(gap)
        return torch.cat([
            torch.where(present, ttc.clamp(max=CONTACT_HORIZON_S) / CONTACT_HORIZON_S, ones),
            torch.where(present, gap.clamp(max=50.0) / 50.0, ones),
            torch.where(present, 5.0 / x.abs().clamp(min=1.0), torch.zeros_like(gap)),
        ], dim=1)


class WindowFeatures(nn.Module):
    """When the ego could change into each side lane over the next 16 s, against when its leader traps it.

    Needs the lane slots (:data:`lcsim.config.LANE_SLOTS`): every vehicle shown in the lane right (left) of
    the ego is moved on at its present relative speed (columns ``x`` and ``vx``); the lane is *open* at a
    time when each of them is clear of the ego, and *changeable* when it stays open for ``WINDOW_CHANGE_S``.
    The ego is *trapped* when its leader, moved on the same way, comes within ``WINDOW_MARGIN_M``. Outputs
    ``(B, 11)``, each in [0, 1]: the trap time over the horizon (1: not within it), then per side lane (right,
    then left) changeable now; the first changeable time and the end of the open window that starts now,
    over the horizon (1: never / open throughout, 0: not open now); whether it is changeable at some time
    before the trap; the share of the times before the trap at which it is. A quantity the planner gets by
    simulating, which an MLP would have to learn as a minimum over a grid; vehicles the slots do not show
    count as absent, and a lane that does not exist reads open (the ``lane`` column tells).

    With ``accel`` (the ``accel_mps2`` column of ``ScenarioConfig.observe_acceleration``), 11 more: the same
    look with each vehicle keeping its acceleration relative to the ego's for ``WINDOW_ACCEL_S``, so a
    follower closing on its desired speed or a braking leader shows before its speed does.
    """

    def __init__(self, slots: int, accel: bool = False) -> None:
        super().__init__()
        layout = LANE_SLOTS[:slots]
        offsets = {o for o, _, _ in layout}
        if (0, True, 1) not in layout or not {-1, 1} <= offsets:
            raise ValueError(f"window features need the lane slots with the leader and both side lanes, "
                             f"got {slots}")
        self.lead = layout.index((0, True, 1))
        self.register_buffer("right", torch.tensor([j for j, (o, _, _) in enumerate(layout) if o == -1]),
                             persistent=False)
        self.register_buffer("left", torch.tensor([j for j, (o, _, _) in enumerate(layout) if o == 1]),
                             persistent=False)
        n = round(WINDOW_HORIZON_S / WINDOW_STEP_S) + 1
        self.span = round(WINDOW_CHANGE_S / WINDOW_STEP_S)
        self.register_buffer("t", torch.arange(n + self.span, dtype=torch.float32) * WINDOW_STEP_S, persistent=False)
        self.n = n
        self.accel = accel
        self.out_features = 22 if accel else 11

    def forward(self, current: torch.Tensor) -> torch.Tensor:
        nb = current[:, 1:]
        x, vx, present = nb[..., _X], nb[..., _VX], nb[..., _PRESENT] > 0.5
        t, horizon = self.t, WINDOW_HORIZON_S
        # the trap: the leader's bumper gap down to the margin, at the present closing speed
        gap = x[:, self.lead] - CONTACT_BODY_M - WINDOW_MARGIN_M
        closing = -vx[:, self.lead]
        trap = torch.where(present[:, self.lead] & (closing > 0.05), gap.clamp(min=0.0) / closing.clamp(min=0.05),
                           torch.full_like(gap, horizon)).clamp(max=horizon)
        out = self._look(trap, x[..., None] + vx[..., None] * t, vx[..., None], present)
        if not self.accel:
            return out
        # the same look with each vehicle's acceleration relative to the ego's kept for WINDOW_ACCEL_S:
        # displacement a * ta * (t - ta / 2) and speed v + a * ta, with ta = min(t, WINDOW_ACCEL_S)
        rel_a = nb[..., _ACCEL] - current[:, :1, _ACCEL]
        ta = t.clamp(max=WINDOW_ACCEL_S)
        xt = x[..., None] + vx[..., None] * t + rel_a[..., None] * (ta * (t - 0.5 * ta))  # (B, K, G)
        vt = vx[..., None] + rel_a[..., None] * ta
        lead_gap = xt[:, self.lead, :self.n] - CONTACT_BODY_M - WINDOW_MARGIN_M
        hit = (lead_gap <= 0.0) & present[:, self.lead, None]
        grid = t[:self.n]
        trap_a = torch.where(hit, grid, torch.full_like(grid, 2 * horizon)).min(dim=1).values.clamp(max=horizon)
        return torch.cat([out, self._look(trap_a, xt, vt, present)], dim=1)

    def _look(self, trap: torch.Tensor, xt: torch.Tensor, vt: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """The 11 outputs from the trap time ``(B,)`` and every slot's relative position ``(B, K, G)`` and
        speed ``(B, K, G or 1)`` over the grid."""
        t, n, horizon = self.t, self.n, WINDOW_HORIZON_S
        before = t[None, :n] <= trap[:, None]  # (B, n)
        grid = t[:n]
        out = [trap / horizon]
        for side in (self.right, self.left):
            xs, vs = xt[:, side], vt[:, side]  # the side lane's shown vehicles, (B, S, G)
            ahead = CONTACT_BODY_M + WINDOW_MARGIN_M + WINDOW_HEADWAY_S * (-vs).clamp(min=0.0)
            behind = CONTACT_BODY_M + WINDOW_MARGIN_M + WINDOW_HEADWAY_S * vs.clamp(min=0.0)
            clear = (xs >= ahead) | (xs <= -behind) | ~present[:, side, None]
            open_ = clear.all(dim=1)  # (B, G)
            can = open_.unfold(1, self.span + 1, 1).all(dim=2)[:, :n]  # open for the whole change, (B, n)
            never = torch.full_like(grid, 2 * horizon)
            first = torch.where(can, grid, never).min(dim=1).values.clamp(max=horizon)
            closes = torch.where(~open_[:, :n], grid, never).min(dim=1).values.clamp(max=horizon)
            usable = can & before
            out += [can[:, 0].float(), first / horizon, closes / horizon, usable.any(dim=1).float(),
                    usable.float().sum(dim=1) / before.float().sum(dim=1).clamp(min=1.0)]
        return torch.stack(out, dim=1)


class ConcatFeatures(nn.Module):
    """Several feature modules of the same input, side by side."""

    def __init__(self, *parts: nn.Module) -> None:
        super().__init__()
        self.parts = nn.ModuleList(parts)
        self.out_features = sum(int(p.out_features) for p in parts)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([p(x) for p in self.parts], dim=1)


class ScaledMLP(nn.Module):
    """Divide the last axis by fixed scales, flatten, append ``extra(x)`` when given (the sensor branch's
    :class:`ContactFeatures` and :class:`WindowFeatures`), then two linear layers with ReLU."""

    def __init__(self, shape: tuple[int, ...], scale: tuple[float, ...], hidden: int, out: int,
                 extra: nn.Module | None = None) -> None:
        super().__init__()
        if shape[-1] != len(scale):
            raise ValueError(f"expected a last axis of {len(scale)} columns, got shape {shape}")
        self.register_buffer("inv_scale", 1.0 / torch.tensor(scale, dtype=torch.float32))
        self.extra = extra
        n = int(extra.out_features) if extra is not None else 0
        n += math.prod(int(s) for s in shape)
        self.net = nn.Sequential(nn.Flatten(), nn.Linear(n, hidden), nn.ReLU(), nn.Linear(hidden, out), nn.ReLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scaled = x * self.inv_scale
        if self.extra is None:
            return self.net(scaled)
        return self.net(torch.cat([scaled.flatten(1), self.extra(x)], dim=1))


class EgoAttention(nn.Module):
    """The sensor rows read as a set: the ego attends to every sensed vehicle.

    Each row of ``current`` (the ego, then K neighbour slots), scaled per column as :class:`ScaledMLP` does,
    with its slot's :class:`ContactFeatures` when given (the ego's row reads far, no contact), goes through
    one shared two-layer embedding. The ego's embedding is the query of multi-head attention over all the
    embeddings, the ego's own included, with the empty slots (``present`` 0) masked out. Its output, beside
    the ego's embedding and the per-lane features when given (:class:`WindowFeatures`, which depend on the
    lane layout and so are not read per vehicle), goes through two linear layers with ReLU.

    Which slot a vehicle is in changes nothing (the weights are shared across rows, attention sums over
    them), nor does the number of slots: weights trained with K slots read any other number.
    """

    def __init__(self, columns: int, scale: tuple[float, ...], hidden: int, out: int, *, contact: bool = False,
                 window: nn.Module | None = None, embed: int = 64, heads: int = 4) -> None:
        super().__init__()
        if columns != len(scale):
            raise ValueError(f"expected {len(scale)} columns per row, got {columns}")
        if embed % heads:
            raise ValueError(f"the embedding width {embed} must be a multiple of the heads {heads}")
        self.register_buffer("inv_scale", 1.0 / torch.tensor(scale, dtype=torch.float32))
        self.contact = contact
        width = columns + (3 if contact else 0)
        self.embed = nn.Sequential(nn.Linear(width, embed), nn.ReLU(), nn.Linear(embed, embed), nn.ReLU())
        self.attention = nn.MultiheadAttention(embed, heads, batch_first=True)
        self.window = window
        n = 2 * embed + (int(window.out_features) if window is not None else 0)
        self.net = nn.Sequential(nn.Linear(n, hidden), nn.ReLU(), nn.Linear(hidden, out), nn.ReLU())

    def forward(self, current: torch.Tensor) -> torch.Tensor:
        tokens = current * self.inv_scale  # (B, 1+K, C)
        if self.contact:
            k = current.shape[1] - 1
            per_slot = ContactFeatures(k)(current).view(-1, 3, k).transpose(1, 2)  # (B, K, 3)
            ego = per_slot.new_tensor((1.0, 1.0, 0.0)).expand(len(current), 1, 3)
            tokens = torch.cat([tokens, torch.cat([ego, per_slot], dim=1)], dim=2)
        emb = self.embed(tokens)
        absent = current[..., _PRESENT] <= 0.5
        absent[:, 0] = False  # the ego always attends to itself
        seen, _ = self.attention(emb[:, :1], emb, emb, key_padding_mask=absent, need_weights=False)
        parts = [emb[:, 0], seen[:, 0]]
        if self.window is not None:
            parts.append(self.window(current))
        return self.net(torch.cat(parts, dim=1))


class HybridExtractor(BaseFeaturesExtractor):
    """stable-baselines3 features extractor over a ``Dict`` observation (see the module docstring).

    Args:
        observation_space: must hold ``current``; ``image`` and ``prediction`` are used when present.
        image_net: ``"compact"`` (default) or ``"vgg16"``.
        image_features: width of the image branch (10 in the paper).
        sensor_features, prediction_features: widths of the other branches.
        contact_features: the sensor branch also gets :class:`ContactFeatures` (off in checkpoints saved
            before the option existed, which load as they were).
        window_features: ... and :class:`WindowFeatures` (lane slots only).
        sensor_encoder: ``"mlp"`` (the rows flattened; checkpoints saved before the option existed) or
            ``"attention"`` (:class:`EgoAttention`).
    """

    def __init__(self, observation_space: spaces.Dict, image_net: str = "compact", image_features: int = 10,
                 sensor_features: int = 64, prediction_features: int = 64, hidden: int = 128,
                 contact_features: bool = False, window_features: bool = False,
                 sensor_encoder: str = "mlp") -> None:
        if sensor_encoder not in SENSOR_ENCODERS:
            raise ValueError(f"unknown sensor encoder {sensor_encoder!r}; choose one of {', '.join(SENSOR_ENCODERS)}")
        if "current" not in observation_space.spaces:
            raise ValueError(f"the observation needs a 'current' key, got {sorted(observation_space.spaces)}")
        branches: dict[str, nn.Module] = {}
        dims = 0
        for key, space in observation_space.spaces.items():
            shape = tuple(space.shape or ())
            if key == "image":
                branches[key] = make_image_net(image_net, shape[0], shape[1], image_features)
                dims += image_features
            elif key == "current":
                slots, accel = int(shape[0]) - 1, int(shape[-1]) == len(CURRENT_SCALE) + 1
                scale = CURRENT_SCALE + ((ACCEL_SCALE,) if accel else ())
                if sensor_encoder == "attention":
                    window = WindowFeatures(slots, accel) if window_features else None
                    branches[key] = EgoAttention(int(shape[-1]), scale, hidden, sensor_features,
                                                 contact=contact_features, window=window)
                    dims += sensor_features
                    continue
                parts = [ContactFeatures(slots)] if contact_features else []
                parts += [WindowFeatures(slots, accel)] if window_features else []
                extra = ConcatFeatures(*parts) if parts else None  # (no parameters: checkpoints keep their keys)
                branches[key] = ScaledMLP(shape, scale, hidden, sensor_features, extra=extra)
                dims += sensor_features
            elif key == "prediction":
                branches[key] = ScaledMLP(shape, PREDICTION_SCALE, hidden, prediction_features)
                dims += prediction_features
            elif key == IMAGE_FEATURES:  # the image branch's output, computed outside (ImageEncoder)
                branches[key] = nn.Identity()
                dims += int(shape[0])
            else:
                raise ValueError(f"no branch for observation key {key!r} (known: current, image, "
                                 f"{IMAGE_FEATURES}, prediction)")
        super().__init__(observation_space, features_dim=dims)
        self.branches = nn.ModuleDict(branches)
        self.keys = tuple(branches)

    def forward(self, observations: dict[str, torch.Tensor]) -> torch.Tensor:
        return torch.cat([self.branches[k](observations[k]) for k in self.keys], dim=1)


def plain_policy_state(policy: nn.Module, encoder: ImageEncoder) -> dict[str, torch.Tensor]:
    """The tensors of ``policy``, which reads the features of a frozen image branch run outside it (``encoder``),
    as the policy of its observation mode holds them: its own, and the image branch's under every features
    extractor that reads those features. Each extractor module gets its own copy, which the names sharing that
    module share (as loading them into a network of the mode would have them)."""
    state = dict(policy.state_dict())
    image = encoder.state_dict()
    copies: dict[int, dict[str, torch.Tensor]] = {}
    for name, module in policy.named_modules(remove_duplicate=False):
        if isinstance(module, HybridExtractor) and IMAGE_FEATURES in module.branches:
            mine = copies.setdefault(id(module), {k: v.detach().clone() for k, v in image.items()})
            state.update({f"{name}.branches.image.{k}": v for k, v in mine.items()})
    return state
