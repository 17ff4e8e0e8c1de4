"""gymnasium environments: one episode (:class:`LaneChangeEnv`) and a native batch (:class:`LaneChangeVectorEnv`).

Both wrap :class:`~lcsim.core.LaneChangeCore`; the vector environment advances all E episodes in one
numpy call per simulation step and resets finished ones in the same step (``AutoresetMode.SAME_STEP``,
final observation in ``info["final_obs"]``). ``reset(seed=s)`` fully determines an episode; in the
vector environment, environment ``i`` gets seed ``s + i`` and then equals ``LaneChangeEnv`` reset with
``s + i`` bit for bit.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from lcsim.config import ScenarioConfig
from lcsim.core import RUNNING, LaneChangeCore, StepResult, current_features
from lcsim.render import BevRenderer
from lcsim.suite import check_unsealed

_BOUND = 1.0e4


def observation_space(config: ScenarioConfig) -> spaces.Dict:
    """The single-environment observation space (see :meth:`LaneChangeCore.observe`)."""
    k, h = config.num_neighbours, config.history_steps
    d: dict[str, spaces.Space] = {
        "current": spaces.Box(-_BOUND, _BOUND, (1 + k, len(current_features(config))), np.float32),
        "history": spaces.Box(-_BOUND, _BOUND, (k, h, 3), np.float32),
    }
    if config.render_image:
        s = config.render.image_size_px
        d["image"] = spaces.Box(0, 255, (3, s, s), np.uint8)
    return spaces.Dict(d)


def _episode_seed(gen: np.random.Generator) -> int:
    return int(gen.integers(0, 2**63 - 1))


def episode_seed(seed: int) -> int:
    """The episode seed ``reset(seed=seed)`` hands to the simulator (what a recording stores)."""
    return _episode_seed(seeding.np_random(seed)[0])


def _info(res: StepResult | None, mask: np.ndarray, i: int, sim_t: float) -> dict[str, Any]:
    info: dict[str, Any] = {"action_mask": mask[i], "t_s": sim_t}
    if res is not None:
        info["outcome"] = res.outcome[i]
        info["reward_components"] = {k: float(v[i]) for k, v in res.components.items()}
        if res.outcome[i] != RUNNING:
            info["is_success"] = res.outcome[i] == "success"
    return info


class LaneChangeEnv(gym.Env):
    """The paper's lane-change task: 100 autopilot vehicles, the ego decides right / keep / left.

    Args:
        config: scenario (defaults to the paper's).
        render_mode: ``"rgb_array"`` returns a 480x480 RGB bird's-eye view for people.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(self, config: ScenarioConfig | None = None, render_mode: str | None = None) -> None:
        self.config = config or ScenarioConfig()
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.core = LaneChangeCore(self.config, 1)
        self.observation_space = observation_space(self.config)
        self.action_space = spaces.Discrete(3)
        self._view: BevRenderer | None = None
        self._started = False

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None:
            check_unsealed([seed])  # the sealed test episodes run only through the benchmark's final path
        super().reset(seed=seed)
        self.core.reset([0], [_episode_seed(self.np_random)])
        self._started = True
        return self._get_obs(), _info(None, self.core.action_mask(), 0, 0.0)

    def step(self, action: Any):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        # an integer (or 0-d integer array) in {0, 1, 2} (a plain int checked first: the common case, cheaply)
        if not (type(action) is int and 0 <= action <= 2) and not self.action_space.contains(action):
            raise ValueError(f"action must be 0 (right), 1 (keep) or 2 (left), got {action!r}")
        res = self.core.step(np.array([int(action)]))
        info = _info(res, self.core.action_mask(), 0, float(self.core.sim.t_s[0]))
        return self._get_obs(), float(res.reward[0]), bool(res.terminated[0]), bool(res.truncated[0]), info

    def action_masks(self) -> np.ndarray:
        """Valid actions (right, keep, left), for maskable algorithms (sb3-contrib)."""
        return self.core.action_mask()[0]

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        if self._view is None:
            self._view = BevRenderer(self.config.road, self.config.render, size_px=480, resolution_m_per_px=0.125)
        sim = self.core.sim
        return self._view.render(sim.x[:1], sim.y[:1], sim.yaw[:1], sim.length[:1], sim.width[:1])[0].transpose(1, 2, 0)

    def _get_obs(self) -> dict[str, np.ndarray]:
        return {k: v[0] for k, v in self.core.observe().items()}


class LaneChangeVectorEnv(VectorEnv):
    """E lane-change episodes advanced together in numpy (not a loop over single environments).

    ``threads``: how many threads step the batch, each a contiguous shard of environments (the same bytes however
    many); None: the process's default (:mod:`lcsim.threads`: ``LC_THREADS``, else every core for batches of 16 or
    more on two cores), 1: the calling thread only.
    """

    metadata: ClassVar[dict[str, Any]] = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 8, config: ScenarioConfig | None = None, *, threads: int | None = None,
                 **kwargs: Any) -> None:
        if kwargs:
            raise TypeError(f"unexpected arguments {sorted(kwargs)}")
        self.config = config or ScenarioConfig()
        self.num_envs = num_envs
        self.core = LaneChangeCore(self.config, num_envs, threads=threads)
        self.single_observation_space = observation_space(self.config)
        self.single_action_space = spaces.Discrete(3)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._rngs = [seeding.np_random(None)[0] for _ in range(num_envs)]
        self._started = False

    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(self.num_envs)]
        else:
            if len(seed) != self.num_envs:
                raise ValueError(f"expected {self.num_envs} seeds, got {len(seed)}")
            seeds = list(seed)
        check_unsealed(s for s in seeds if s is not None)  # the sealed test episodes: the benchmark's final path only
        self._rngs = [seeding.np_random(s)[0] for s in seeds]
        ids = np.arange(self.num_envs)
        self.core.reset(ids, [_episode_seed(g) for g in self._rngs])
        self._started = True
        mask = self.core.action_mask()
        return self.core.observe(), {"action_mask": mask, "_action_mask": np.ones(self.num_envs, bool)}

    def step(self, actions: Any):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        res, obs = self.core.step_observe(np.asarray(actions))
        infos: dict[str, Any] = {
            "outcome": res.outcome, "_outcome": np.ones(self.num_envs, bool),
            "reward_components": res.components,
            "_reward_components": np.ones(self.num_envs, bool),
        }
        ended = res.terminated | res.truncated
        done = np.flatnonzero(ended)
        if done.size:
            final_obs = np.full(self.num_envs, None, dtype=object)
            for i in done:
                final_obs[i] = {k: v[i].copy() for k, v in obs.items()}
            infos["final_obs"], infos["_final_obs"] = final_obs, ended
            self.core.reset(done, [_episode_seed(self._rngs[i]) for i in done])
            fresh = self.core.observe(done)
            for k in obs:
                obs[k][done] = fresh[k]
        infos["action_mask"] = self.core.action_mask()
        infos["_action_mask"] = np.ones(self.num_envs, bool)
        return obs, res.reward.copy(), res.terminated, res.truncated, infos

    def action_masks(self) -> np.ndarray:
        return self.core.action_mask()
