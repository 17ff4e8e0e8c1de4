"""stable-baselines3 ``VecEnv`` over the native batched simulator (no subprocesses, one numpy call)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from lcsim.config import ScenarioConfig
from lcsim.envs import LaneChangeVectorEnv


class LaneChangeSB3VecEnv(VecEnv):
    """SB3 view of :class:`~lcsim.envs.LaneChangeVectorEnv`.

    Follows SB3's conventions: finished environments are reset in the same step, the last observation
    is in ``infos[i]["terminal_observation"]``, ``"TimeLimit.truncated"`` marks time limits and
    ``"is_success"`` the outcome. ``env_method("action_masks")`` feeds sb3-contrib's MaskablePPO.
    """

    render_mode = None

    def __init__(self, num_envs: int = 8, config: ScenarioConfig | None = None, *, threads: int | None = None) -> None:
        """``threads``: as :class:`~lcsim.envs.LaneChangeVectorEnv`'s (None: the process's default)."""
        self.venv = LaneChangeVectorEnv(num_envs, config, threads=threads)
        super().__init__(num_envs, self.venv.single_observation_space, self.venv.single_action_space)
        self._actions: np.ndarray | None = None

    def reset(self) -> dict[str, np.ndarray]:
        # SB3 passes one seed per environment (seed + i), or None to continue the streams.
        if all(s is not None for s in self._seeds):
            obs, _ = self.venv.reset(seed=[int(s) for s in self._seeds])  # type: ignore[arg-type]
        elif not self.venv._started:
            obs, _ = self.venv.reset()
        else:
            ids = np.arange(self.num_envs)
            self.venv.core.reset(ids, [int(g.integers(0, 2**63 - 1)) for g in self.venv._rngs])
            obs = self.venv.core.observe()
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None, "step_async() first"
        obs, reward, terminated, truncated, info = self.venv.step(self._actions)
        dones = terminated | truncated
        infos: list[dict[str, Any]] = []
        for i in range(self.num_envs):
            d: dict[str, Any] = {
                "action_mask": info["action_mask"][i],
                "outcome": info["outcome"][i],
                "reward_components": {k: float(v[i]) for k, v in info["reward_components"].items()},
            }
            if dones[i]:
                d["terminal_observation"] = info["final_obs"][i]
                d["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                d["is_success"] = info["outcome"][i] == "success"
            infos.append(d)
        return obs, reward.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def _indices(self, indices: VecEnvIndices) -> Sequence[int]:
        if indices is None:
            return range(self.num_envs)
        if isinstance(indices, int):
            return [indices]
        return list(indices)

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        if attr_name == "render_mode":
            return [None for _ in self._indices(indices)]
        value = getattr(self.venv, attr_name)
        return [value for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        if method_name == "action_masks":
            masks = self.venv.action_masks()
            return [masks[i] for i in self._indices(indices)]
        method = getattr(self.venv, method_name)
        return [method(*method_args, **method_kwargs) for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._indices(indices)]

    def action_masks(self) -> np.ndarray:
        return self.venv.action_masks()
