"""Shared fixtures: small real scenarios the simulator makes itself (a few vehicles, a few steps)."""

from __future__ import annotations

import time

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


def wait_gone(pid: int, timeout: float = 30.0) -> None:
    """Wait until process ``pid`` (not necessarily a child of ours) has exited."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X"):  # exited, not yet reaped
                    return
        except FileNotFoundError:
            return
        assert time.monotonic() < deadline, f"process {pid} still running"
        time.sleep(0.05)
