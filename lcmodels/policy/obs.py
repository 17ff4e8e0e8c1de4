"""Observation modes of the ablation (Table IV) and the vector-env wrappers a policy trains in.

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

:func:`policy_vec_env` composes small wrappers, each with one job, over the simulator's SB3 vector env:
:class:`EpisodeInfoVecEnv` + SB3's ``VecMonitor`` (episode statistics in ``info["episode"]``: return,
length, outcome, distance, seed), :class:`RewardShapingVecEnv` (the learner's pay) and
:class:`ObservationModeVecEnv` (the mode's keys, the predictor's batched prediction of all environments'
neighbours in one call, a frozen image branch's features in place of the image).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper, VecMonitor

from lcmodels.policy.extractor import ImageEncoder
from lcmodels.policy.names import (  # noqa: F401  (named here too, as before)
    IMAGE_FEATURES,
    OBS_MODES,
    ObsMode,
    mode_keys,
    needs_predictor,
    scenario_for_mode,
)
from lcmodels.predictor.inference import Predictor
from lcsim.config import ScenarioConfig
from lcsim.core import COLLISION, OFF_ROAD, OUTCOMES
from lcsim.envs import observation_space


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


class EpisodeInfoVecEnv(VecEnvWrapper):
    """Puts in the info of each finished episode what :class:`~stable_baselines3.common.vec_env.VecMonitor`
    does not sum itself: the distance travelled (``forward_m``, from the reward's go-forward component) and
    the episode's simulator seed (``episode_seed``); keeps the seed of every episode started
    (:attr:`episode_seeds`, what the held-out check compares against)."""

    def __init__(self, venv: VecEnv) -> None:
        super().__init__(venv)
        base: Any = venv
        while not hasattr(base, "core") and hasattr(base, "venv"):
            base = base.venv
        self.core = base.core
        self.forward_per_m = base.config.reward.forward_per_m
        self._fwd = np.zeros(self.num_envs)
        self._seed = np.zeros(self.num_envs, dtype=np.int64)
        self.episode_seeds: list[int] = []

    def reset(self) -> Any:
        obs = self.venv.reset()
        self._fwd[:] = 0.0
        self._seed[:] = self.core.seeds
        self.episode_seeds.extend(int(s) for s in self.core.seeds)
        return obs

    def step_wait(self) -> Any:
        obs, reward, dones, infos = self.venv.step_wait()
        for i, info in enumerate(infos):
            self._fwd[i] += info["reward_components"]["forward"]
        for i in np.flatnonzero(dones):
            infos[i]["forward_m"] = float(self._fwd[i]) / self.forward_per_m if self.forward_per_m else 0.0
            infos[i]["episode_seed"] = int(self._seed[i])
            self._fwd[i] = 0.0
            self._seed[i] = self.core.seeds[i]
            self.episode_seeds.append(int(self.core.seeds[i]))
        return obs, reward, dones, infos


EPISODE_INFO_KEYS = ("outcome", "forward_m", "episode_seed")
"""What :class:`VecMonitor` copies into ``info["episode"]`` next to its return ``r`` and length ``l``."""


def monitored(venv: VecEnv) -> VecMonitor:
    """``venv`` with episode statistics: SB3's :class:`VecMonitor` over :class:`EpisodeInfoVecEnv`."""
    return VecMonitor(EpisodeInfoVecEnv(venv), info_keywords=EPISODE_INFO_KEYS)


def episode_stats(info: dict[str, Any]) -> EpisodeStats | None:
    """The statistics of the episode an info reports finished (``info["episode"]`` of :func:`monitored`)."""
    ep = info.get("episode")
    if ep is None:
        return None
    outcome, fwd = str(ep["outcome"]), float(ep["forward_m"])
    return EpisodeStats(outcome, float(ep["r"]), int(ep["l"]), fwd, 0.0 if outcome in (COLLISION, OFF_ROAD) else fwd,
                        int(ep["episode_seed"]))


class RewardShapingVecEnv(VecEnvWrapper):
    """The learner's pay: the collision component weighted by ``collision_weight``, all scaled by
    ``reward_scale`` (training shaping; the environment's reward, and so the statistics below, stay)."""

    def __init__(self, venv: VecEnv, *, reward_scale: float = 1.0, collision_weight: float = 1.0) -> None:
        super().__init__(venv)
        self.reward_scale, self.collision_weight = float(reward_scale), float(collision_weight)

    def reset(self) -> Any:
        return self.venv.reset()

    def step_wait(self) -> Any:
        obs, reward, dones, infos = self.venv.step_wait()
        collision = np.array([info["reward_components"]["collision"] for info in infos],
                             dtype=reward.dtype)  # (in the reward's dtype: weight 1 pays it exactly)
        learner = reward + (self.collision_weight - 1.0) * collision
        return obs, (learner * self.reward_scale).astype(np.float32), dones, infos


class ObservationModeVecEnv(VecEnvWrapper):
    """The policy's observation of a mode: the keys it sees, the predictor's batched prediction of the
    neighbours, and, with a frozen ``image_encoder``, its features in place of the image (key
    ``image_features``). Terminal observations are converted too."""

    def __init__(self, venv: VecEnv, mode: str, predictor: Predictor | None = None,
                 image_encoder: ImageEncoder | None = None) -> None:
        self.mode = ObsMode.of(mode)
        if self.mode.needs_predictor and predictor is None:
            raise ValueError(f"observation mode {mode!r} needs a trained predictor (--predictor)")
        if image_encoder is not None and not self.mode.reads_image:
            raise ValueError(f"observation mode {mode!r} has no image to encode")
        self.predictor = predictor if self.mode.needs_predictor else None
        self.image_encoder = image_encoder
        base: Any = venv
        while not hasattr(base, "config") and hasattr(base, "venv"):
            base = base.venv
        future = predictor.future_steps if self.predictor is not None else 10
        features = image_encoder.out_features if image_encoder is not None else None
        super().__init__(venv, observation_space=policy_observation_space(base.config, mode, future, features))

    def convert(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The policy observation of a batched simulator observation."""
        out = build_observation(obs, self.mode, self.predictor)
        if self.image_encoder is not None:
            out[IMAGE_FEATURES] = self.image_encoder(out.pop("image"))
        return out

    def reset(self) -> dict[str, np.ndarray]:
        return self.convert(self.venv.reset())

    def step_wait(self) -> Any:
        obs, reward, dones, infos = self.venv.step_wait()
        done_ids = np.flatnonzero(dones)
        if done_ids.size:
            terminal = [infos[i]["terminal_observation"] for i in done_ids]
            converted = self.convert({k: np.stack([t[k] for t in terminal]) for k in terminal[0]})
            for j, i in enumerate(done_ids):
                infos[i]["terminal_observation"] = {k: v[j] for k, v in converted.items()}
        return self.convert(obs), reward, dones, infos


def policy_vec_env(venv: VecEnv, mode: str, predictor: Predictor | None = None, *, reward_scale: float = 1.0,
                   image_encoder: ImageEncoder | None = None, collision_weight: float = 1.0) -> ObservationModeVecEnv:
    """The training environment of a policy: ``venv`` (a :class:`lcsim.sb3.LaneChangeSB3VecEnv`) with
    episode statistics (:func:`monitored`), the learner's reward (:class:`RewardShapingVecEnv`) and the
    observation of ``mode`` (:class:`ObservationModeVecEnv`), composed in that order. The episode
    statistics come in ``info["episode"]`` (:func:`episode_stats`); :func:`episode_seeds_of` gives the
    seeds of every episode started."""
    shaped = RewardShapingVecEnv(monitored(venv), reward_scale=reward_scale, collision_weight=collision_weight)
    return ObservationModeVecEnv(shaped, mode, predictor, image_encoder)


def episode_seeds_of(venv: VecEnv) -> list[int]:
    """The simulator seeds of every episode started in a :func:`policy_vec_env` (or any stack holding an
    :class:`EpisodeInfoVecEnv`)."""
    while not isinstance(venv, EpisodeInfoVecEnv):
        if not hasattr(venv, "venv"):
            raise ValueError("no EpisodeInfoVecEnv in this stack of environments")
        venv = venv.venv
    return venv.episode_seeds


def summarize(episodes: Sequence[EpisodeStats]) -> dict[str, Any]:
    """``episodes`` (their count), the rate of each outcome, the mean return and mean (safe) forward distance
    (NaN for no episodes): what training logs and evaluation reports (with intervals)."""
    n = len(episodes)
    out: dict[str, Any] = {"episodes": n}
    for o in OUTCOMES:
        out[f"{o}_rate"] = sum(e.outcome == o for e in episodes) / n if n else float("nan")
    out["mean_return"] = float(np.mean([e.ret for e in episodes])) if n else float("nan")
    out["mean_forward_m"] = float(np.mean([e.forward_m for e in episodes])) if n else float("nan")
    out["mean_safe_forward_m"] = float(np.mean([e.safe_forward_m for e in episodes])) if n else float("nan")
    return out
