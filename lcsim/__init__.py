"""lcsim: a fast, batched, deterministic numpy highway simulator with gymnasium environments.

Importing the package registers the environments:

- ``lcsim/LaneChange-v0``: the paper's scenario (100 autopilot vehicles at ~24 km/h on a 4-lane
  Town06-like highway; the ego targets 30 km/h and decides right / keep / left every 0.5 s).
- ``lcsim/LaneChangeLight-v0``: the same task with 30 vehicles on a 300 m route, for quick experiments.

``gymnasium.make_vec(id, num_envs=E, vectorization_mode="vector_entry_point")`` gives the native
batched vector environment.
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

from lcsim.config import (
    EgoConfig,
    PIDGains,
    RenderConfig,
    RewardConfig,
    RoadConfig,
    ScenarioConfig,
    TrafficConfig,
    corpus_scenario,
    paper_scenario,
)

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
]


def light_scenario() -> ScenarioConfig:
    """A smaller version of the paper's task (30 vehicles, 300 m route) for quick experiments."""
    return ScenarioConfig(traffic=TrafficConfig(num_vehicles=30, spawn_behind_m=80.0, spawn_ahead_m=200.0),
                          route_length_m=300.0, time_limit_s=40.0)


ENV_IDS = ("lcsim/LaneChange-v0", "lcsim/LaneChangeLight-v0")


def _register() -> None:
    for env_id in ENV_IDS:
        if env_id in registry:
            continue
        kwargs = {"config": light_scenario()} if env_id.endswith("Light-v0") else {}
        register(id=env_id, entry_point="lcsim.envs:LaneChangeEnv",
                 vector_entry_point="lcsim.envs:LaneChangeVectorEnv", kwargs=kwargs)


_register()
