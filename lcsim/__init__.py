"""lcsim: a fast, batched, deterministic numpy highway simulator with gymnasium environments.

Importing the package registers the environments:

- ``lcsim/LaneChange-v0``: the paper's scenario (100 autopilot vehicles at ~24 km/h on a 4-lane
  Town06-like highway; the ego targets 30 km/h and decides right / keep / left every 0.5 s).
- ``lcsim/LaneChangeLight-v0``: the same task with 30 vehicles on a 300 m route, for quick experiments.

``gymnasium.make_vec(id, num_envs=E, vectorization_mode="vector_entry_point")`` gives the native
batched vector environment.
"""

from __future__ import annotations

from gymnasium.envs import registration as gym_registration

from lcsim.config import (
    EgoConfig,
    PIDGains,
    RenderConfig,
    RewardConfig,
    RoadConfig,
    ScenarioConfig,
    TrafficConfig,
    corpus_scenario,
    light_scenario,
    paper_scenario,
    tiny_scenario,
)
from lcsim.registry import SCENARIOS

__version__ = "0.1.0"
__all__ = [
    "EgoConfig",
    "PIDGains",
    "RenderConfig",
    "RewardConfig",
    "RoadConfig",
    "ScenarioConfig",
    "TrafficConfig",
    "__version__",
    "corpus_scenario",
    "light_scenario",
    "paper_scenario",
    "tiny_scenario",
]


ENV_IDS = {"lcsim/LaneChange-v0": "paper", "lcsim/LaneChangeLight-v0": "light"}
"""The registered gym ids and the scenario (:data:`lcsim.registry.SCENARIOS`) each runs."""


def _register() -> None:
    for env_id, name in ENV_IDS.items():
        if env_id in gym_registration.registry:
            continue
        kwargs = {} if name == "paper" else {"config": SCENARIOS[name]()}
        gym_registration.register(id=env_id, entry_point="lcsim.envs:LaneChangeEnv",
                                  vector_entry_point="lcsim.envs:LaneChangeVectorEnv", kwargs=kwargs)


_register()
