"""The policy network: stable-baselines3 algorithms with the hybrid features extractor, built from a
:class:`~lcmodels.policy.config.PolicyConfig` for training or, from spaces alone, for loading a policy file."""

from __future__ import annotations

from typing import Any

from gymnasium import spaces
from stable_baselines3 import A2C, DQN, PPO
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecEnv

from lcmodels.policy.config import ALGORITHMS, PolicyConfig
from lcmodels.policy.extractor import HybridExtractor

ALGOS: dict[str, type[BaseAlgorithm]] = dict(zip(ALGORITHMS, (PPO, A2C, DQN), strict=True))
ACTION_SPACE = spaces.Discrete(3)


def build_model(cfg: PolicyConfig, env: VecEnv | None, tensorboard: str | None = None,
                device: str = "cpu", observation_space: spaces.Dict | None = None) -> BaseAlgorithm:
    """A fresh SB3 model of ``cfg.algo`` with the hybrid extractor.

    Args:
        env: the training environment; ``None`` builds a model for inference from ``observation_space``
            alone (how a policy file is loaded: the network rebuilt from its card, then filled with its
            tensors; a DQN gets a one-transition replay buffer).
    """
    learner, view = cfg.algorithm, cfg.observation
    n_steps, buffer_size = learner.n_steps, learner.buffer_size
    if env is None:
        if observation_space is None:
            raise ValueError("build_model needs an environment or an observation space")
        # Nothing is collected for inference: a one-step rollout buffer, a one-transition replay buffer (the
        # card's sizes, untrusted, allocate nothing).
        n_steps, buffer_size = 1, 1
    policy_kwargs: dict[str, Any] = {
        "features_extractor_class": HybridExtractor,
        "features_extractor_kwargs": {"image_net": view.image_net, "image_features": view.image_features,
                                      "contact_features": view.contact_features,
                                      "window_features": view.window_features,
                                      "sensor_encoder": view.sensor_encoder},
        "net_arch": [128, 64] if learner.algo == "dqn" else {"pi": [64, 64], "vf": [64, 64]},
    }
    common: dict[str, Any] = {"policy_kwargs": policy_kwargs, "seed": cfg.seed, "device": device,
                              "gamma": learner.gamma, "tensorboard_log": tensorboard, "verbose": 0}  # fmt: skip
    if env is None:
        common["_init_setup_model"] = False
    if learner.algo == "ppo":
        model = ALGOS["ppo"]("MultiInputPolicy", env, learning_rate=learner.learning_rate, n_steps=n_steps,
                             batch_size=learner.batch_size, n_epochs=learner.n_epochs, ent_coef=learner.ent_coef,
                             **common)
    elif learner.algo == "a2c":
        model = ALGOS["a2c"]("MultiInputPolicy", env, learning_rate=learner.learning_rate, n_steps=n_steps,
                             ent_coef=learner.ent_coef, **common)
    else:
        model = ALGOS["dqn"]("MultiInputPolicy", env, learning_rate=learner.learning_rate,
                             buffer_size=buffer_size, learning_starts=learner.learning_starts, batch_size=learner.batch_size,
                             train_freq=1, gradient_steps=1,  # one minibatch per vector step (n_envs transitions)
                             target_update_interval=learner.target_update_interval,
                             exploration_fraction=learner.exploration_fraction, exploration_final_eps=0.02, **common)
    if env is None:  # what stable-baselines3's own load does, from the spaces instead of a pickle
        model.observation_space, model.action_space, model.n_envs = observation_space, ACTION_SPACE, 1
        model._setup_model()
    return model


