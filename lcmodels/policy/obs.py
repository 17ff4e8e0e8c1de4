"""Observation modes of the ablation (Table IV) and the vector-env wrapper that builds them.

=============  =====================================  ==========================
mode           keys the policy sees                   the paper's row
=============  =====================================  ==========================
``pure``       ``current``                            Pure (sensor data only)
``image``      ``current``, ``image``                 Image
``prediction`` ``current``, ``prediction``            Prediction
``hybrid``     ``current``, ``image``, ``prediction`` Hybrid (Hybrid-PPO)
=============  =====================================  ==========================

``prediction`` is ``(K, F, 2)``: the trained predictor's positions of the K neighbour slots F steps
ahead, in the ego frame, from the ``history`` the simulator observes (zeros for absent neighbours).
:class:`PolicyVecEnv` computes it once per step for all environments and neighbours in one batched call,
drops the keys the mode does not use, and keeps per-episode statistics (outcome, return, forward
distance) for logging.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from lcmodels.policy.extractor import IMAGE_FEATURES, ImageEncoder
from lcmodels.predictor.inference import Predictor
from lcsim.config import ScenarioConfig
from lcsim.core import COLLISION, OFF_ROAD, OUTCOMES
from lcsim.envs import observation_space

OBS_MODES: tuple[str, ...] = ("pure", "image", "prediction", "hybrid")
_KEYS = {
    "pure": ("current",),
    "image": ("current", "image"),
    "prediction": ("current", "prediction"),
    "hybrid": ("current", "image", "prediction"),
}


def mode_keys(mode: str) -> tuple[str, ...]:
    """The observation keys of ``mode``; ``ValueError`` for an unknown mode."""
    if mode not in _KEYS:
        raise ValueError(f"unknown observation mode {mode!r}; choose one of {', '.join(OBS_MODES)}")
    return _KEYS[mode]


def needs_predictor(mode: str) -> bool:
    return "prediction" in mode_keys(mode)


def scenario_for_mode(config: ScenarioConfig, mode: str) -> ScenarioConfig:
    """``config`` with the bird's-eye image rendered only when the mode uses it (rendering costs time)."""
    return dataclasses.replace(config, render_image="image" in mode_keys(mode))


def policy_observation_space(config: ScenarioConfig, mode: str, future_steps: int = 10,
                             image_features: int | None = None) -> spaces.Dict:
    """The observation space a policy of ``mode`` sees in ``config``; with ``image_features``, a frozen
    image branch's ``(image_features,)`` output (key ``image_features``) in place of the image."""
    base = observation_space(scenario_for_mode(config, mode))
    out: dict[str, spaces.Space] = {}
    for key in mode_keys(mode):
        if key == "prediction":
            out[key] = spaces.Box(-1.0e4, 1.0e4, (config.num_neighbours, future_steps, 2), np.float32)
        elif key == "image" and image_features is not None:
            out[IMAGE_FEATURES] = spaces.Box(-np.inf, np.inf, (image_features,), np.float32)
        else:
            out[key] = base.spaces[key]
    return spaces.Dict(out)


def predict(predictor: Predictor, history: np.ndarray) -> np.ndarray:
    """Batched neighbour predictions from the simulator's ``history`` observation.

    Args:
        history: ``(B, K, H, 3)`` ego-frame positions and a validity flag (``LaneChangeCore.observe``).

    Returns:
        ``(B, K, F, 2)`` float32 ego-frame positions; zeros for neighbours absent now.
    """
    history = np.asarray(history)
    return predictor.predict_neighbours(history[..., :2], history[..., 2] > 0.5)


def build_observation(obs: dict[str, np.ndarray], mode: str, predictor: Predictor | None) -> dict[str, np.ndarray]:
    """The policy observation of ``mode`` from a batched simulator observation (``(B, ...)`` arrays)."""
    out: dict[str, np.ndarray] = {}
    for key in mode_keys(mode):
        if key == "prediction":
            if predictor is None:
                raise ValueError(f"observation mode {mode!r} needs a trained predictor")
            out[key] = predict(predictor, obs["history"])
        else:
            out[key] = obs[key]
    return out


@dataclasses.dataclass(slots=True)
class EpisodeStats:
    """One finished training episode."""

    outcome: str
    ret: float
    """Return in the environment's reward units (before any reward scaling)."""
    length: int
    forward_m: float
    safe_forward_m: float
    """``forward_m`` when the episode ended without a collision or leaving the road, else 0."""
    seed: int

    @classmethod
    def of(cls, outcome: str, ret: float, length: int, forward_reward: float, forward_per_m: float,
           seed: int) -> EpisodeStats:
        """Statistics of a finished episode from its summed ``forward`` reward component."""
        fwd = forward_reward / forward_per_m if forward_per_m else 0.0
        return cls(outcome, ret, length, fwd, 0.0 if outcome in (COLLISION, OFF_ROAD) else fwd, seed)


class PolicyVecEnv(VecEnvWrapper):
    """Observation mode, batched prediction and episode statistics on top of a SB3 vector env.

    Args:
        venv: :class:`lcsim.sb3.LaneChangeSB3VecEnv` (or a wrapper of it).
        mode: one of :data:`OBS_MODES`.
        predictor: required by ``prediction`` and ``hybrid``.
        reward_scale: rewards handed to the learner are multiplied by this; statistics stay unscaled.
        image_encoder: a frozen image branch; when given, the policy sees its output (key
            ``image_features``) in place of the image (``image`` and ``hybrid`` modes).
        collision_weight: the collision component of the learner's reward is multiplied by this (training
            shaping; statistics and the environment's reward stay as they are).
    """

    def __init__(self, venv: VecEnv, mode: str, predictor: Predictor | None = None,
                 reward_scale: float = 1.0, image_encoder: ImageEncoder | None = None,
                 collision_weight: float = 1.0) -> None:
        self.mode = mode
        if needs_predictor(mode) and predictor is None:
            raise ValueError(f"observation mode {mode!r} needs a trained predictor (--predictor)")
        if image_encoder is not None and "image" not in mode_keys(mode):
            raise ValueError(f"observation mode {mode!r} has no image to encode")
        self.predictor = predictor if needs_predictor(mode) else None
        self.image_encoder = image_encoder
        base: Any = venv
        while not hasattr(base, "venv") or not hasattr(base.venv, "core"):
            base = base.venv
        self.core = base.venv.core
        config: ScenarioConfig = base.venv.config
        future = predictor.future_steps if self.predictor is not None else 10
        features = image_encoder.out_features if image_encoder is not None else None
        super().__init__(venv, observation_space=policy_observation_space(config, mode, future, features))
        self.reward_scale = float(reward_scale)
        self.collision_weight = float(collision_weight)
        self.forward_per_m = config.reward.forward_per_m
        n = self.num_envs
        self._ret = np.zeros(n)
        self._len = np.zeros(n, dtype=np.int64)
        self._fwd = np.zeros(n)
        self._seed = np.zeros(n, dtype=np.int64)
        self._t0 = time.perf_counter()
        self.finished: list[EpisodeStats] = []
        """Every episode finished since the last :meth:`pop_finished`."""
        self.episode_seeds: list[int] = []
        """Simulator seeds of every episode started (what the held-out check compares against)."""

    def _convert(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        out = build_observation(obs, self.mode, self.predictor)
        if self.image_encoder is not None:
            out[IMAGE_FEATURES] = self.image_encoder(out.pop("image"))
        return out

    def reset(self) -> dict[str, np.ndarray]:
        obs = self.venv.reset()
        self._ret[:] = 0.0
        self._len[:] = 0
        self._fwd[:] = 0.0
        self._seed[:] = self.core.seeds
        self.episode_seeds.extend(int(s) for s in self.core.seeds)
        return self._convert(obs)

    def step_wait(self):
        obs, reward, dones, infos = self.venv.step_wait()
        self._ret += reward
        self._len += 1
        collision = np.zeros(len(infos), dtype=reward.dtype)  # (in the reward's dtype: w = 1 pays it exactly)
        for i, info in enumerate(infos):
            components = info["reward_components"]
            self._fwd[i] += components["forward"]
            collision[i] = components["collision"]
        done_ids = np.flatnonzero(dones)
        if done_ids.size:
            terminal = [infos[i]["terminal_observation"] for i in done_ids]
            batched = {k: np.stack([t[k] for t in terminal]) for k in terminal[0]}
            converted = self._convert(batched)
            for j, i in enumerate(done_ids):
                info = infos[i]
                info["terminal_observation"] = {k: v[j] for k, v in converted.items()}
                outcome = str(info["outcome"])
                stats = EpisodeStats.of(outcome, float(self._ret[i]), int(self._len[i]), float(self._fwd[i]),
                                        self.forward_per_m, int(self._seed[i]))  # fmt: skip
                self.finished.append(stats)
                info["episode"] = {"r": stats.ret, "l": stats.length, "t": round(time.perf_counter() - self._t0, 6)}
                info["lc_episode"] = dataclasses.asdict(stats)
                self._ret[i], self._len[i], self._fwd[i] = 0.0, 0, 0.0
                self._seed[i] = self.core.seeds[i]
                self.episode_seeds.append(int(self.core.seeds[i]))
        learner = reward + (self.collision_weight - 1.0) * collision  # the learner's pay (reward when w is 1)
        return self._convert(obs), (learner * self.reward_scale).astype(np.float32), dones, infos

    def pop_finished(self) -> list[EpisodeStats]:
        out, self.finished = self.finished, []
        return out


def summarize(episodes: list[EpisodeStats]) -> dict[str, float]:
    """Rates of each outcome, mean return and mean (safe) forward distance of ``episodes``."""
    n = len(episodes)
    out: dict[str, float] = {"episodes": float(n)}
    for o in OUTCOMES:
        out[f"{o}_rate"] = sum(e.outcome == o for e in episodes) / n if n else float("nan")
    out["mean_return"] = float(np.mean([e.ret for e in episodes])) if n else float("nan")
    out["mean_forward_m"] = float(np.mean([e.forward_m for e in episodes])) if n else float("nan")
    out["mean_safe_forward_m"] = float(np.mean([e.safe_forward_m for e in episodes])) if n else float("nan")
    return out
