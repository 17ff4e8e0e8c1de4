"""stable-baselines3 ``VecEnv`` over the native batched simulator (no subprocesses, one numpy call)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from lcsim.config import ScenarioConfig
from lcsim.envs import LaneChangeVectorEnv


def env_indices(num_envs: int, indices: VecEnvIndices) -> Sequence[int]:
    """The environments SB3's ``indices`` name (None: all of them)."""
    if indices is None:
        return range(num_envs)
    if isinstance(indices, int):
        return [indices]
    return list(indices)


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
        return env_indices(self.num_envs, indices)

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


class _RoadCores:
    """What the wrappers read from a batch's core (:attr:`seeds`, :meth:`action_mask`), over the batches of
    :class:`MixedRoadsSB3VecEnv` in environment order."""

    def __init__(self, parts: Sequence[LaneChangeSB3VecEnv]) -> None:
        self.parts = parts

    @property
    def seeds(self) -> np.ndarray:
        return np.concatenate([p.venv.core.seeds for p in self.parts])

    def action_mask(self) -> np.ndarray:
        return np.concatenate([p.venv.core.action_mask() for p in self.parts])


class MixedRoadsSB3VecEnv(VecEnv):
    """One SB3 ``VecEnv`` over several roads: ``num_envs`` environments split into contiguous blocks, one
    :class:`LaneChangeSB3VecEnv` per road (sizes as even as they go, the first roads one larger), stepped one
    after the other and seen as one batch. Every road must give the same observation and action spaces (the
    same observation shapes: neighbours, history, image size). Environment ``i`` keeps its road for good; the
    seeds :meth:`seed` hands out run over the whole batch (``seed + i``), so each road's episodes differ.

    ``config`` is the first road's (the one a policy card names); :attr:`configs` every road's, in block order.
    """

    render_mode = None

    def __init__(self, num_envs: int, configs: Sequence[ScenarioConfig], *, threads: int | None = None) -> None:
        if not configs:
            raise ValueError("a mix of roads needs at least one road")
        if num_envs < len(configs):
            raise ValueError(f"{num_envs} environments cannot drive {len(configs)} roads (one environment a road "
                             "at least)")  # fmt: skip
        sizes = [num_envs // len(configs) + (k < num_envs % len(configs)) for k in range(len(configs))]
        self.parts = [LaneChangeSB3VecEnv(n, c, threads=threads) for n, c in zip(sizes, configs, strict=True)]
        first = self.parts[0]
        for k, p in enumerate(self.parts):
            if p.observation_space != first.observation_space or p.action_space != first.action_space:
                raise ValueError(f"the roads of a mix must give the same observations: road {k} gives "
                                 f"{p.observation_space}, road 0 {first.observation_space}")
        self.configs = tuple(configs)
        self.config = configs[0]
        self.core = _RoadCores(self.parts)
        self._bounds = np.cumsum([0, *sizes])
        self._slices = [slice(int(a), int(b)) for a, b in zip(self._bounds[:-1], self._bounds[1:], strict=True)]
        super().__init__(num_envs, first.observation_space, first.action_space)
        self._actions: np.ndarray | None = None

    def reset(self) -> dict[str, np.ndarray]:
        for part, s in zip(self.parts, self._slices, strict=True):
            part._seeds, part._options = self._seeds[s], self._options[s]
        obs = [p.reset() for p in self.parts]
        self._reset_seeds()
        self._reset_options()
        return {k: np.concatenate([o[k] for o in obs]) for k in obs[0]}

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None, "step_async() first"
        steps = []
        for part, s in zip(self.parts, self._slices, strict=True):
            part.step_async(self._actions[s])
            steps.append(part.step_wait())
        obs = {k: np.concatenate([st[0][k] for st in steps]) for k in steps[0][0]}
        infos: list[dict[str, Any]] = [info for st in steps for info in st[3]]
        return (obs, np.concatenate([st[1] for st in steps]), np.concatenate([st[2] for st in steps]),
                infos)  # fmt: skip

    def close(self) -> None:
        for p in self.parts:
            p.close()

    def _indices(self, indices: VecEnvIndices) -> Sequence[int]:
        return env_indices(self.num_envs, indices)

    def _part_index(self, i: int) -> int:
        return int(np.searchsorted(self._bounds, i, side="right")) - 1

    def _part_of(self, i: int) -> LaneChangeSB3VecEnv:
        return self.parts[self._part_index(i)]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [self._part_of(i).get_attr(attr_name, 0)[0] for i in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        for k in sorted({self._part_index(i) for i in self._indices(indices)}):
            self.parts[k].set_attr(attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        if method_name == "action_masks":
            masks = self.action_masks()
            return [masks[i] for i in self._indices(indices)]
        return [self._part_of(i).env_method(method_name, *method_args, indices=0, **method_kwargs)[0]
                for i in self._indices(indices)]  # fmt: skip

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._indices(indices)]

    def action_masks(self) -> np.ndarray:
        return np.concatenate([p.action_masks() for p in self.parts])
