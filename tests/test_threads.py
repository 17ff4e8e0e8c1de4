"""A batch stepped on several threads gives the same bytes as on one; the thread count is a setting."""

import itertools
import multiprocessing as mp
import threading
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from lcsim import threads as T
from lcsim.config import TrafficConfig
from lcsim.envs import LaneChangeVectorEnv
from lcsim.sb3 import LaneChangeSB3VecEnv

from .conftest import small_config

_STATE = ("vf", "vi", "vb", "ef", "ei", "eb", "keys", "hist")


def _assert_same(a, b, where):
    """Exact equality of nested results: arrays by dtype, shape and bytes, NaN included."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _assert_same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, np.ndarray) and a.dtype == object:
        assert a.shape == b.shape, where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), where
    else:
        assert type(a) is type(b) and a == b, where


def _rollout(threads, config, num_envs, steps, seed):
    """Every step's returns and the final state of a batch driven by a fixed stream of random actions."""
    env = LaneChangeVectorEnv(num_envs, config, threads=threads)
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    out = [(obs, info)]
    for _ in range(steps):
        change = rng.random(num_envs) < 0.3
        pick = (rng.random((num_envs, 3)) * info["action_mask"]).argmax(axis=1)
        obs, reward, terminated, truncated, info = env.step(np.where(change, pick, 1))
        out.append((obs, reward, terminated, truncated, info))
    sim = env.core.sim
    state = {name: getattr(sim, name).copy() for name in _STATE}
    state["pid_errors"], state["pid_count"] = sim.pid.errors.copy(), sim.pid.count.copy()
    return env, out, state


@pytest.mark.parametrize("threads", [2, 3, 4])
def test_a_batch_on_threads_gives_the_same_bytes_as_on_one(threads):
    """Observations (the image too), rewards, endings, infos (final observations of the autoresets included) and
    the whole state agree byte for byte, for even and uneven shards."""
    config = small_config()
    serial_env, serial, serial_state = _rollout(1, config, 21, 80, seed=5)
    env, parallel, state = _rollout(threads, config, 21, 80, seed=5)
    assert serial_env.core.sim.shards == 1 and env.core.sim.shards == threads
    assert any(step[2].any() or step[3].any() for step in serial[1:])  # episodes ended, and were reset, inside
    assert len(serial) == len(parallel)
    for t, (a, b) in enumerate(zip(serial, parallel, strict=True)):
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"step {t} item {k}")
    _assert_same(serial_state, state, "state")


def test_the_exact_traffic_on_threads_gives_the_same_bytes_as_on_one():
    config = small_config(traffic=TrafficConfig(num_vehicles=6, spawn_behind_m=40.0, spawn_ahead_m=80.0,
                                                human_like=False))
    _, serial, serial_state = _rollout(1, config, 12, 40, seed=9)
    _, parallel, state = _rollout(2, config, 12, 40, seed=9)
    for t, (a, b) in enumerate(zip(serial, parallel, strict=True)):
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"step {t} item {k}")
    _assert_same(serial_state, state, "state")


def test_the_sb3_adapter_takes_the_thread_count():
    venv = LaneChangeSB3VecEnv(4, small_config(), threads=2)
    assert venv.venv.core.sim.shards == 2


def _environment(monkeypatch, **values):
    """Set (a value) or unset (None) environment variables, and have the thread count read them anew."""
    for name, value in values.items():
        if value is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, value)
    monkeypatch.setattr(T, "_setting", None)
    monkeypatch.setattr(T, "_from_environment", None)  # (both restored after the test)


def test_one_thread_is_the_serial_path_and_the_default_follows_the_setting(monkeypatch):
    _environment(monkeypatch, LC_THREADS="1", OMP_NUM_THREADS=None)
    assert T.default_threads() == 1
    assert LaneChangeVectorEnv(64, small_config()).core.sim.shards == 1  # the opt-out
    _environment(monkeypatch, LC_THREADS="2")
    assert T.default_threads() == 2
    assert T.shard_count(64, None) == 2
    assert T.shard_count(2 * T.MIN_ENVS_PER_THREAD - 1, None) == 1  # a small batch stays on one thread
    assert T.shard_count(64, 1) == 1 and T.shard_count(3, 8) == 3  # given: exactly that, one env per shard at most
    T.set_threads(1)  # the process's setting comes before the environment
    assert T.default_threads() == 1
    T.set_threads(None)
    assert T.default_threads() == 2
    _environment(monkeypatch, LC_THREADS=None, OMP_NUM_THREADS="1")
    assert T.default_threads() == 1


@pytest.mark.parametrize("bad", ["0", "-2", "two", "1.5"])
def test_a_bad_thread_count_is_refused_with_its_name(monkeypatch, bad):
    _environment(monkeypatch, LC_THREADS=bad)
    with pytest.raises(ValueError, match=T.ENV_VAR):
        T.default_threads()
    with pytest.raises(ValueError, match="threads"):
        LaneChangeVectorEnv(2, small_config(), threads=0)


def test_a_worker_process_defaults_to_one_thread(monkeypatch):
    monkeypatch.delenv(T.ENV_VAR, raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as pool:
        assert pool.submit(T.default_threads).result(timeout=120) == 1


def test_run_shards_covers_the_range_once_on_several_threads():
    seen: list[tuple[int, int, int]] = []
    lock = threading.Lock()
    two_threads = threading.Event()

    def fn(a, b):
        with lock:
            seen.append((a, b, threading.get_ident()))
            if len({ident for *_, ident in seen}) == 2:
                two_threads.set()
        assert two_threads.wait(timeout=60)  # the first chunk waits until another thread has taken one

    T.run_shards(fn, 21, 2)
    parts = sorted((a, b) for a, b, _ in seen)
    assert parts[0][0] == 0 and parts[-1][1] == 21 and all(p[1] == q[0] for p, q in itertools.pairwise(parts))
    assert all(b > a for a, b in parts) and len({ident for *_, ident in seen}) == 2

    def fails(a, b):
        if a > 0:
            raise RuntimeError("shard failed")

    with pytest.raises(RuntimeError, match="shard failed"):
        T.run_shards(fails, 10, 2)
