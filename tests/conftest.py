"""Shared fixtures: small real scenarios the simulator makes itself (a few vehicles, a few steps)."""

from __future__ import annotations

import os
import time
from pathlib import Path

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
    """pytest -n 2 runs two workers on two cores: one torch thread each avoids oversubscription (3x slower), and
    one simulator thread each (tests that step batches on threads say so)."""
    import torch

    from lcsim.threads import set_threads

    torch.set_num_threads(1)
    if os.environ.get("PYTEST_XDIST_WORKER"):
        set_threads(1)
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


@pytest.fixture(scope="session")
def predictor_path(tmp_path_factory: pytest.TempPathFactory):
    """A small predictor (untrained: exactly the constant-velocity baseline, which is what it starts as)."""
    import torch

    from lcmodels.predictor import Predictor, PredictorConfig, TrajectoryTransformer

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("pred") / "predictor.pt"
    Predictor(TrajectoryTransformer(PredictorConfig(d_model=16, ff_dim=32, num_layers=1))).save(path)
    return path


def tiny_policy(**kw):
    """A :class:`~lcmodels.policy.PolicyConfig` that trains in seconds in the tiny scenario."""
    from lcmodels.policy import PolicyConfig

    base = dict(scenario="tiny", timesteps=128, n_envs=2, n_steps=32, batch_size=64, n_epochs=2,
                eval_episodes=2, eval_batch=2, checkpoint_every=64, buffer_size=500, learning_starts=32)
    base.update(kw)
    return PolicyConfig(**base)


EVAL_KEYS = {"success_rate", "collision_rate", "off_road_rate", "timeout_rate", "mean_safe_forward_m",
             "mean_return", "success_rate_ci95", "collision_rate_ci95", "off_road_rate_ci95",
             "timeout_rate_ci95", "mean_safe_forward_m_ci95", "mean_return_ci95", "episodes"}  # fmt: skip
"""The keys every evaluation summary has."""


class CountingPool:
    """A shard pool that counts what is given to it (``submitted``) and the evaluation shards among it
    (``shards``); the real processes run them."""

    def __init__(self, pool) -> None:
        self.pool, self.submitted, self.shards = pool, 0, 0

    def map(self, fn, jobs, **kwargs):
        jobs = list(jobs)
        self.submitted += len(jobs)
        self.shards += len(jobs) if getattr(fn, "__name__", "") == "_evaluate_shard" else 0
        return self.pool.map(fn, jobs, **kwargs)

    def submit(self, *args, **kwargs):
        self.submitted += 1
        self.shards += getattr(args[0], "__name__", "") == "_evaluate_shard"  # not other work given to the pool
        return self.pool.submit(*args, **kwargs)

    def close(self, **kwargs) -> None:
        self.pool.close(**kwargs)

    def __enter__(self) -> CountingPool:
        return self

    def __exit__(self, *exc) -> None:
        self.pool.__exit__(*exc)


@pytest.fixture
def tiny_suite(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """A suite of two tiny roads with 6 sealed test episodes each, and a ledger of its own (``LC_LEDGER``)."""
    import dataclasses

    from lcsim import suite as suite_mod
    from lcsim.config import tiny_scenario
    from lcsim.suite import SuiteScenario

    for name, block, lanes in (("tiny-a", 900, 4), ("tiny-b", 901, 3)):
        def make(lanes=lanes):
            base = tiny_scenario()
            return dataclasses.replace(base, road=dataclasses.replace(base.road, num_lanes=lanes))

        monkeypatch.setitem(suite_mod.SUITE_SCENARIOS, name, SuiteScenario(name=name, block=block, test_episodes=6,
                                                                            what="tiny", make=make))  # fmt: skip
    monkeypatch.setitem(suite_mod.SUITES, "tiny", ("tiny-a", "tiny-b"))
    ledger = tmp_path / "ledger.jsonl"
    monkeypatch.setenv("LC_LEDGER", str(ledger))
    return ledger


@pytest.fixture
def shard_pools(monkeypatch: pytest.MonkeyPatch) -> list[CountingPool]:
    """Every :func:`lcmodels.policy.evaluate.shard_pool` the test starts, counting the shards it runs."""
    import importlib

    ev = importlib.import_module("lcmodels.policy.evaluate")  # (lcmodels.policy.evaluate is also a function)
    pools: list[CountingPool] = []
    real = ev.shard_pool

    def counting(*args, **kwargs) -> CountingPool:
        pools.append(CountingPool(real(*args, **kwargs)))
        return pools[-1]

    monkeypatch.setattr(ev, "shard_pool", counting)
    return pools
