"""Offline warm start: pretrain a policy on recorded MCAP episodes before online training.

The recorded decisions are replayed into observations (:func:`lcdata.offline.rebuild_observations`,
bit-exact with what the driver saw), turned into the policy's observation mode (with the predictor
run on the rebuilt histories), and paired with the recorded actions and the discounted returns of the
recorded rewards. The objective:

- PPO / A2C: behaviour cloning (negative log-likelihood of the recorded action, each action weighted by
  the inverse square root of its frequency, as lane changes are rare) plus a value
  regression on the Monte-Carlo return, so online training starts with a critic that agrees with the
  actor instead of one that pulls it back to random.
- DQN: the large-margin loss of DQfD (``max_a Q(s, a) + margin * [a != a_E] - Q(s, a_E)``) plus Q
  regression of the demonstrated action on the Monte-Carlo return; the target network is synced after.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from stable_baselines3 import DQN
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.utils import obs_as_tensor

from lcdata.offline import episode_config, rebuild_observations
from lcdata.reader import list_episodes, read_episode
from lcmodels.policy.checkpoint import scenario_differences
from lcmodels.policy.extractor import HybridExtractor, pooled_images, prepools
from lcmodels.policy.obs import build_observation, mode_keys
from lcmodels.predictor.inference import Predictor
from lcsim.config import ScenarioConfig

if TYPE_CHECKING:
    from lcmodels.policy.config import PolicyConfig

# Scenario fields that change only what is observed, not the episode: demonstrations recorded with other
# values are replayed and observed the policy's way (rendering aside: a mode with the image needs it recorded).
_REOBSERVED = ("neighbour_selection", "num_neighbours", "observe_acceleration")
_OBSERVATION_ONLY = ("render_image", *_REOBSERVED)


@dataclass
class Demonstrations:
    """Recorded decisions: policy observations ``(M, ...)``, actions ``(M,)`` and returns ``(M,)``."""

    obs: dict[str, np.ndarray | RowChunks]
    actions: np.ndarray
    returns: np.ndarray
    episodes: int
    weights: np.ndarray | None = None
    """``(M,)`` how much each decision counts in :func:`pretrain` (on top of the action-frequency weights);
    None: all alike."""

    def __len__(self) -> int:
        return len(self.actions)


class RowChunks:
    """Arrays of one dtype and trailing shape read as their concatenation by row indices (``chunks[rows]``),
    never copied into one: DAgger's training set grows by a round at a time, and a concatenation of image
    observations would hold it twice (gigabytes each at six rounds of 200 episodes)."""

    def __init__(self, parts: list[np.ndarray]) -> None:
        if not parts:
            raise ValueError("RowChunks needs at least one array")
        self.parts = list(parts)
        self._ends = np.cumsum([len(p) for p in self.parts])
        self._starts = self._ends - np.array([len(p) for p in self.parts])

    def __len__(self) -> int:
        return int(self._ends[-1])

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self), *self.parts[0].shape[1:])

    @property
    def dtype(self) -> np.dtype:
        return self.parts[0].dtype

    def __getitem__(self, rows: np.ndarray) -> np.ndarray:
        rows = np.asarray(rows, dtype=np.int64)
        if rows.ndim != 1 or (rows.size and (rows.min() < 0 or rows.max() >= len(self))):
            raise IndexError(f"RowChunks takes a 1-D array of row indices in [0, {len(self)})")
        which = np.searchsorted(self._ends, rows, side="right")
        out = np.empty((rows.size, *self.parts[0].shape[1:]), self.dtype)
        for i in np.unique(which):
            sel = which == i
            out[sel] = self.parts[i][rows[sel] - self._starts[i]]
        return out


def _discounted(rewards: np.ndarray, gamma: float) -> np.ndarray:
    out = np.zeros(len(rewards))
    acc = 0.0
    for i in range(len(rewards) - 1, -1, -1):
        acc = rewards[i] + gamma * acc
        out[i] = acc
    return out


def every_tenth(say: Callable[[str], None], message: str) -> Callable[[int, int], None]:
    """A (done, total) progress callback that says ``message.format(done, total)`` at each tenth of the total."""
    def report(done: int, total: int) -> None:
        if done == total or done * 10 // total != (done - 1) * 10 // total:
            say(message.format(done, total))
    return report


def _reporting(items: list[Path], progress: Callable[[int, int], None] | None) -> Iterator[Path]:
    """``items``, calling ``progress(done, total)`` once the loop body has finished with each one."""
    for done, item in enumerate(items, start=1):
        yield item
        if progress is not None:
            progress(done, len(items))


def load_demonstrations(
    data: str | os.PathLike[str],
    mode: str,
    predictor: Predictor | None,
    *,
    gamma: float = 0.99,
    reward_scale: float = 1.0,
    collision_weight: float = 1.0,
    scenario: ScenarioConfig | None = None,
    max_episodes: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Demonstrations:
    """Read every ``.mcap`` in ``data`` (a directory or one file) into demonstrations for ``mode``.

    ``scenario``, when given, must equal the recorded episodes' (apart from rendering); ``ValueError``
    otherwise, and when there are no recorded decisions. ``progress`` is called with (episodes read,
    episodes in all) after each episode. Returns are of the recorded rewards with the collision component
    times ``collision_weight``, times ``reward_scale`` (what the learner is paid online).
    """
    data = Path(data)
    paths = [data] if data.is_file() else list_episodes(data)
    if not paths:
        raise ValueError(f"no .mcap episodes in {data}")
    paths = paths[:max_episodes] if max_episodes else paths
    keys = mode_keys(mode)
    chunks: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    actions: list[np.ndarray] = []
    returns: list[np.ndarray] = []
    used = 0
    for path in _reporting(paths, progress):
        episode = read_episode(path)
        if episode.steps.empty:
            continue
        config = episode_config(episode)
        if scenario is not None:
            # What the observation shows does not change the episode: it is rebuilt the policy's way.
            if diffs := scenario_differences(config.to_dict(), scenario, ignore=_OBSERVATION_ONLY):
                raise ValueError(f"{path} was recorded in another scenario than the one being trained ({diffs[0]})")
            config = dataclasses.replace(config, **{k: getattr(scenario, k) for k in _REOBSERVED})
        if "image" in keys and not config.render_image:
            raise ValueError(f"{path} was recorded without the bird's-eye image, which mode {mode!r} needs")
        rows = [obs for _step, obs in rebuild_observations(episode, config)]
        batched = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
        pobs = build_observation(batched, mode, predictor)
        for k in keys:
            chunks[k].append(pobs[k])
        actions.append(episode.steps["action"].to_numpy(dtype=np.int64))
        rewards = episode.steps["reward"].to_numpy(dtype=np.float64)
        rewards = rewards + (collision_weight - 1.0) * episode.steps["r_collision"].to_numpy(dtype=np.float64)
        returns.append(_discounted(rewards * reward_scale, gamma))
        used += 1
    if not actions:
        raise ValueError(f"no recorded decisions in {data}")
    return Demonstrations({k: np.concatenate(v) for k, v in chunks.items()}, np.concatenate(actions),
                          np.concatenate(returns).astype(np.float32), used)  # fmt: skip


def _pools_images(policy: torch.nn.Module) -> bool:
    """Whether the policy's image branch starts with the pooling :func:`pooled_images` computes ahead."""
    return any(isinstance(m, HybridExtractor) and "image" in m.branches and prepools(m.branches["image"])
               for m in policy.modules())  # fmt: skip


def _batch(demos: Demonstrations, rows: np.ndarray, pooled: bool) -> dict[str, np.ndarray]:
    # Pooled images: a ninth of the pixels for stable-baselines3 to scale, the network's pooling skipped.
    obs = {k: v[rows] for k, v in demos.obs.items() if not (pooled and k == "image")}
    if pooled and "image" in demos.obs:
        images = demos.obs["image"]
        obs["image"] = pooled_images(images, rows) if isinstance(images, np.ndarray) else pooled_images(images[rows])
    return obs


def pretrain(
    model: BaseAlgorithm,
    demos: Demonstrations,
    *,
    epochs: int = 10,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
    value_coef: float = 0.5,
    margin: float = 0.8,
    seed: int = 0,
    balance_actions: bool = True,
    progress: Callable[[int, float], None] | None = None,
) -> list[float]:
    """Pretrain ``model``'s policy on ``demos``; returns the mean loss of each epoch.

    Args:
        balance_actions: weight each decision by the inverse square root of its action's frequency (rare lane
            changes count more); False: every decision alike (times ``demos.weights``), as when distilling a
            policy whose lane changes are already as frequent as they should be.
        progress: called with (epoch, mean loss) after each epoch.
    """
    policy = model.policy
    policy.set_training_mode(True)
    optimizer = torch.optim.Adam(policy.parameters(), lr=learning_rate)
    gen = np.random.default_rng(seed)
    n = len(demos)
    is_dqn = isinstance(model, DQN)
    # Lane changes are rare in driving data (a few of a rule driver's decisions in a hundred): weight each action
    # by the inverse square root of its frequency, or cloning learns "always keep" (which collides).
    counts = np.bincount(demos.actions, minlength=3).astype(np.float64)
    weights = np.where(counts > 0, 1.0 / np.sqrt(np.maximum(counts, 1.0) / n), 0.0) if balance_actions else np.ones(3)
    weights = torch.as_tensor(weights / weights[demos.actions].mean(), dtype=torch.float32, device=policy.device)
    sample_w = None if demos.weights is None else torch.as_tensor(demos.weights / demos.weights.mean(),
                                                                   dtype=torch.float32, device=policy.device)
    pooled = _pools_images(policy)
    losses: list[float] = []
    for epoch in range(epochs):
        perm = gen.permutation(n)
        total, count = 0.0, 0
        for start in range(0, n, batch_size):
            idx = perm[start : start + batch_size]
            obs = obs_as_tensor(_batch(demos, idx, pooled), policy.device)
            act = torch.as_tensor(demos.actions[idx], device=policy.device)
            ret = torch.as_tensor(demos.returns[idx], device=policy.device)
            w = weights[act] if sample_w is None else weights[act] * sample_w[torch.as_tensor(idx)]
            if is_dqn:
                q = policy.q_net(obs)  # type: ignore[attr-defined]
                q_e = q.gather(1, act[:, None]).squeeze(1)
                margins = torch.full_like(q, margin).scatter(1, act[:, None], 0.0)
                loss = (w * ((q + margins).max(dim=1).values - q_e)).mean()
                loss = loss + value_coef * torch.nn.functional.mse_loss(q_e, ret)
            else:
                values, log_prob, _entropy = policy.evaluate_actions(obs, act)  # type: ignore[attr-defined]
                loss = -(w * log_prob).mean() + value_coef * torch.nn.functional.mse_loss(values.flatten(), ret)
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), 0.5)
            optimizer.step()
            total += float(loss.detach()) * len(idx)
            count += len(idx)
        losses.append(total / max(count, 1))
        if progress is not None:
            progress(epoch + 1, losses[-1])
    if is_dqn:
        model.q_net_target.load_state_dict(model.q_net.state_dict())  # type: ignore[attr-defined]
    policy.set_training_mode(False)
    return losses


def bc_loss(model: BaseAlgorithm, demos: Demonstrations, batch_size: int = 1024) -> float:
    """Mean negative log-likelihood (PPO/A2C) or cross-entropy of Q logits (DQN) of the recorded actions."""
    policy = model.policy
    policy.set_training_mode(False)
    total = 0.0
    pooled = _pools_images(policy)
    with torch.no_grad():
        for start in range(0, len(demos), batch_size):
            sl = slice(start, start + batch_size)
            obs = obs_as_tensor(_batch(demos, np.arange(sl.start, min(sl.stop, len(demos))), pooled), policy.device)
            act = torch.as_tensor(demos.actions[sl], device=policy.device)
            if isinstance(model, DQN):
                logits = policy.q_net(obs)  # type: ignore[attr-defined]
                total += float(torch.nn.functional.cross_entropy(logits, act, reduction="sum"))
            else:
                _v, log_prob, _e = policy.evaluate_actions(obs, act)  # type: ignore[attr-defined]
                total += float(-log_prob.sum())
    return total / len(demos)


def warm_start(cfg: PolicyConfig, model: BaseAlgorithm, pred: Predictor | None, scenario: ScenarioConfig,
               say: Callable[..., None]) -> dict[str, Any]:
    """Pretrain ``model`` on the episodes of ``cfg.warm_start`` as ``cfg`` says (observation mode, rewards,
    epochs, seed), observed in ``scenario``; returns what was done (``warm_start.json``). ``say``: where the
    progress goes (a logger's ``info``: a message and its arguments)."""
    t0 = time.perf_counter()
    demos = load_demonstrations(cfg.warm_start, cfg.obs, pred, gamma=cfg.gamma, reward_scale=cfg.reward_scale,
                                collision_weight=cfg.collision_weight, scenario=scenario,
                                progress=every_tenth(say, "warm start: read {}/{} episodes"))
    before = bc_loss(model, demos)
    epochs = cfg.warm_start_epochs
    losses = pretrain(model, demos, epochs=epochs, seed=cfg.seed,
                      progress=lambda e, loss: say("warm start: epoch %d/%d, loss %.4f", e, epochs, loss))
    after = bc_loss(model, demos)
    say("warm start on %d decisions of %d episodes: NLL %.3f -> %.3f", len(demos), demos.episodes, before, after)
    return {"data": cfg.warm_start, "episodes": demos.episodes, "decisions": len(demos), "nll_before": before,
            "nll_after": after, "epoch_losses": losses, "wall_s": time.perf_counter() - t0}  # fmt: skip
