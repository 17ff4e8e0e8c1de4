"""Shared fixtures: small real scenarios the simulator makes itself (a few vehicles, a few steps)."""

from __future__ import annotations

import pytest

from lcsim.config import ScenarioConfig, TrafficConfig


def small_config(**overrides) -> ScenarioConfig:
    """6 traffic vehicles on a 150 m route: fast, but with traffic around the ego."""
    kwargs = dict(traffic=TrafficConfig(num_vehicles=6, spawn_behind_m=40.0, spawn_ahead_m=80.0),
                  route_length_m=150.0, time_limit_s=25.0)
    kwargs.update(overrides)
    return ScenarioConfig(**kwargs)


@pytest.fixture
def small() -> ScenarioConfig:
    return small_config()


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread_per_worker():
    """pytest -n 2 runs two workers on two cores: one torch thread each avoids oversubscription (3x slower)."""
    import torch

    torch.set_num_threads(1)
    yield
