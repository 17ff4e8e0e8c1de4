"""Property tests: files from elsewhere (recordings, policy files, configs) damaged at random give their
complete part or a clear ``ValueError``, never another exception and never a hang."""

from __future__ import annotations

import json
import signal
import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lcdata.reader import read_episode
from lcdata.record import record_episode
from lcmodels.policy import PolicyConfig, read_meta, train_policy
from lcmodels.policy.checkpoint import load_policy
from lcsim.config import ScenarioConfig, paper_scenario

FUZZ = settings(max_examples=60, deadline=None, print_blob=False,
                suppress_health_check=[HealthCheck.function_scoped_fixture])
EXAMPLE_TIME_LIMIT_S = 20


@contextmanager
def time_limit(seconds: int) -> Iterator[None]:
    """Fail (instead of hanging for good) when the block runs longer than ``seconds``."""

    def expired(signum, frame):
        raise TimeoutError(f"still running after {seconds} s: a hang")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    import dataclasses

    config = dataclasses.replace(paper_scenario(), traffic=dataclasses.replace(paper_scenario().traffic,
                                                                               num_vehicles=10), time_limit_s=6.0)
    path = tmp_path_factory.mktemp("rec") / "ep.mcap"
    record_episode(config, 3, "rule", path, writer="inline")
    return path.read_bytes()


@pytest.fixture(scope="module")
def policy_bytes(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    out = tmp_path_factory.mktemp("pol") / "run"
    train_policy(PolicyConfig(scenario="tiny", obs="pure", timesteps=32, n_envs=2, n_steps=16, batch_size=32,
                              n_epochs=1, eval_episodes=0), out)
    return (out / "policy.safetensors").read_bytes()


def _damage(data: bytes, cut: float, flips: list[tuple[float, int]]) -> bytes:
    out = bytearray(data[: max(0, int(len(data) * cut))])
    for where, value in flips:
        if out:
            out[int(where * (len(out) - 1))] = value
    return bytes(out)


damage_args = (st.floats(0.0, 1.0), st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), max_size=6))


@FUZZ
@given(*damage_args)
def test_a_damaged_recording_reads_its_complete_part_or_fails_clearly(recording: bytes, tmp_path_factory,
                                                                       cut: float, flips) -> None:
    path = tmp_path_factory.mktemp("fuzz") / "ep.mcap"
    path.write_bytes(_damage(recording, cut, flips))
    with time_limit(EXAMPLE_TIME_LIMIT_S), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            episode = read_episode(path)
        except ValueError as exc:
            assert str(path) in str(exc) and "\n" not in str(exc).strip()
            return
        len(episode.tracks), len(episode.steps), len(episode.events)  # the frames decode too


@FUZZ
@given(*damage_args)
def test_a_damaged_policy_file_is_refused_clearly(policy_bytes: bytes, tmp_path_factory, cut: float, flips) -> None:
    path = tmp_path_factory.mktemp("fuzz") / "policy.safetensors"
    data = _damage(policy_bytes, cut, flips)
    path.write_bytes(data)
    with time_limit(EXAMPLE_TIME_LIMIT_S):
        try:
            read_meta(path)
            loaded = load_policy(path)
        except ValueError as exc:
            assert str(path) in str(exc) or "card" in str(exc)
            return
    assert loaded.obs_mode == "pure"  # the damage missed everything that matters (or only a weight's bytes)


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
                           lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner,
                                                                                       max_size=3),
                           max_leaves=6)


def _paths(d: dict, prefix: tuple = ()) -> list[tuple]:
    out = []
    for k, v in d.items():
        out.append((*prefix, k))
        if isinstance(v, dict):
            out += _paths(v, (*prefix, k))
    return out


@FUZZ
@given(st.data())
def test_a_config_with_any_value_replaced_loads_or_fails_with_a_value_error(data) -> None:
    for cls, base in ((ScenarioConfig, paper_scenario().to_dict()), (PolicyConfig, PolicyConfig().to_dict())):
        d = json.loads(json.dumps(base))
        where = data.draw(st.sampled_from(_paths(d)))
        node = d
        for k in where[:-1]:
            node = node[k]
        node[where[-1]] = data.draw(json_values)
        try:
            cls.from_dict(d)
        except ValueError:
            pass
    text = data.draw(st.text(max_size=40))
    try:
        ScenarioConfig.from_json(text)
    except ValueError:
        pass
