"""lcdata.record / lcdata.offline: round trip, rebuilt observations, bit-exact replay, crash safety."""

from __future__ import annotations

import dataclasses
import pathlib
import signal
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from lcdata import (
    EpisodeRecorder,
    EpisodeWriter,
    ObservationRebuilder,
    TruncatedFileWarning,
    episode_seed,
    read_episode,
    rebuild_observations,
    record_episode,
    replay,
)
from lcdata.offline import STATE_COLUMNS, track_arrays
from lcdata.record import episode_metadata, seed_start_time_ns
from lcdata.writer import EpisodeSink
from lcdata.writer_process import open_writer
from lcsim import kernel
from lcsim.config import ScenarioConfig
from lcsim.core import LaneChangeCore
from lcsim.envs import LaneChangeEnv
from lcsim.registry import make_driver
from lcsim.sim import LOG_STEPS
from tests.conftest import small_config, wait_gone

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_episode_seed_is_the_environments() -> None:
    env = LaneChangeEnv(small_config())
    for seed in (0, 7, 123456):
        env.reset(seed=seed)
        assert int(env.core.seeds[0]) == episode_seed(seed)


@pytest.mark.parametrize("num_envs", [1, 2])
def test_round_trip_tracks_ego_steps_metadata(tmp_path: pathlib.Path, small: ScenarioConfig, num_envs: int) -> None:
    """Record the last env of a batch (or the only one); what the simulator did == what read_episode returns, bit for
    bit. The simulator updates its state arrays in place: the recorder keeps copies of what it has not written yet."""
    core = LaneChangeCore(small, num_envs)
    e = num_envs - 1
    driver = make_driver("random", 3)
    seen: list[dict[str, np.ndarray]] = []

    def collect(sim) -> None:
        if not sim.frozen[e]:
            seen.append({name: np.array(getattr(sim, name)[e]) for name in STATE_COLUMNS}
                        | {"step": sim.step[e].copy(), "off_road": sim.off_road[e].copy()})  # fmt: skip

    meta = episode_metadata(small, 11, driver="random", scenario="test")
    results, actions = [], []
    with EpisodeWriter(tmp_path / "ep.mcap", metadata=meta) as writer:
        recorder = EpisodeRecorder(writer, core, env=e)
        core.reset(list(range(num_envs)), [5, episode_seed(11)][-num_envs:])
        collect(core.sim)
        recorder.attach()
        core.sim.hooks.append(collect)
        obs = core.observe()
        while not recorder.done:
            mask = core.action_mask()
            a = driver(obs, mask, core)
            recorder.before_step(obs, mask, a)
            res = core.step(a)
            recorder.after_step(res)
            results.append(res)
            actions.append(int(a[e]))
            obs = core.observe()
        recorder.detach()
    assert recorder not in core.sim.log_hooks
    ep = read_episode(tmp_path / "ep.mcap")
    assert ep.complete
    tracks = track_arrays(ep)
    np.testing.assert_array_equal(tracks.steps, [s["step"] for s in seen])
    for name in STATE_COLUMNS:
        expected = np.stack([s[name] for s in seen])
        assert tracks.columns[name].tobytes() == expected.astype(tracks.columns[name].dtype).tobytes(), name
    assert (ep.ego["off_road"].to_numpy() == [bool(s["off_road"]) for s in seen]).all()
    steps = ep.steps
    assert steps["action"].tolist() == actions
    assert steps["decision"].tolist() == list(range(len(actions)))
    assert steps["reward"].to_numpy().tobytes() == np.array([r.reward[e] for r in results]).tobytes()
    assert steps["outcome"].iloc[-1] == recorder.outcome != ""
    assert ep.events["kind"].iloc[0] == "episode_start" and "outcome" in set(ep.events["kind"])
    if recorder.outcome == "collision":
        assert len(ep.collisions) == 1 and ep.collisions["step"].iloc[0] == tracks.steps[-1]
    if recorder.outcome == "off_road":
        assert "off_road" in set(ep.events["kind"])
    md = ep.metadata
    assert ScenarioConfig.from_dict(md["config"]) == small
    assert (md["seed"], md["episode_seed"], md["driver"], md["autopilot"]) == (11, episode_seed(11), "random", False)
    assert len(ep.image_steps) == len(actions)


def test_hook_only_recording_writes_every_step(tmp_path: pathlib.Path, small: ScenarioConfig) -> None:
    """Without before_step/after_step the recorder writes the steps of every compiled call as they come (an advance
    longer than one logged call too); attach() refuses a decision under way, detach() writes what it holds."""
    core = LaneChangeCore(small, 1, autopilot_ego=True)
    seen: list[np.ndarray] = []
    with EpisodeWriter(tmp_path / "ep.mcap", metadata={"seed": 1}) as writer:
        recorder = EpisodeRecorder(writer, core)
        core.reset([0], [episode_seed(1)])
        recorder.attach()
        core.sim.log_hooks.append(lambda sim, log, counts: seen.extend(log[0, : counts[0], kernel.LOG_HEAD :].copy()))
        for _ in range(15):
            core.step(np.array([1]))
        core.sim.advance(LOG_STEPS + 10)
        recorder.before_step(core.observe(), core.action_mask(), np.array([1]))
        core.step(np.array([1]))
        with pytest.raises(RuntimeError, match="inside a decision"):
            recorder.attach()  # as after a reset: the decision's steps and view would be lost
        recorder.detach()
        with pytest.raises(RuntimeError, match="before_step"):
            EpisodeRecorder(writer, core).after_step(None)  # type: ignore[arg-type]
    ep = read_episode(tmp_path / "ep.mcap")
    tracks = track_arrays(ep)
    steps = 160 + LOG_STEPS + 10
    np.testing.assert_array_equal(tracks.steps, np.arange(steps + 1))
    assert tracks.columns["x"][1:].tobytes() == np.stack(seen)[:, : small.traffic.num_vehicles + 1].tobytes()
    assert ep.image_steps == [150 + LOG_STEPS + 10] and len(ep.steps) == 0  # the unfinished decision: no /rl/step


class SingleCalls(EpisodeWriter):
    """A writer that makes the recorder's composite calls of the single ones, with the per-message encoders
    (lcdata.encode, SimStepEncoder), as the recorder wrote its files before the compiled decision records."""

    def write_decision(self, *args) -> None:
        EpisodeSink.write_decision(self, *args)

    def _write_log_steps(self, log: np.ndarray, fixed) -> None:
        EpisodeSink._write_log_steps(self, log, fixed)


def _recorded(path: pathlib.Path, config: ScenarioConfig, seed: int, driver, mode: str, autopilot: bool = False,
              scene: bool = True, images: bool = True) -> bytes:  # fmt: skip
    """The file an EpisodeRecorder writes for one episode with ``mode``'s writer (``single``: SingleCalls)."""
    meta = episode_metadata(config, seed, driver="test", autopilot=autopilot)
    kwargs = {"metadata": meta, "start_time_ns": seed_start_time_ns(seed), "chunk_size": 1 << 16}
    writer = SingleCalls(path, **kwargs) if mode == "single" else open_writer(path, mode=mode, **kwargs)
    core = LaneChangeCore(config, 1, autopilot_ego=autopilot)
    with writer:
        recorder = EpisodeRecorder(writer, core, scene=scene, images=images)
        core.reset([0], [episode_seed(seed)])
        recorder.attach()
        obs = core.observe()
        while not recorder.done:
            mask = core.action_mask()
            actions = driver(obs, mask, core)
            recorder.before_step(obs, mask, actions)
            recorder.after_step(core.step(actions))
            obs = core.observe()
        recorder.detach()
    return path.read_bytes()


def _always_right(obs, mask, core) -> np.ndarray:
    return np.zeros(core.num_envs, dtype=np.int64)


def test_compiled_decisions_write_the_bytes_of_the_single_calls(tmp_path: pathlib.Path, small: ScenarioConfig) -> None:
    """The recorder's decisions laid out by one compiled call (and, in the process writer's helper, many at once)
    give byte for byte the file of the per-message encoders, in real episodes with every kind of event: lane changes
    and lane invasions, collisions, leaving the road, the autopilot ego, no image, no scene, small chunks."""
    leave = dataclasses.replace(small, invalid_lane_change="leave_road")
    cases = [(small, seed, "random", {}) for seed in (0, 1, 2)]
    cases += [(leave, seed, "right", {}) for seed in (0, 2)]
    cases += [(small, 3, "keep", {"autopilot": True}), (small, 4, "rule", {"images": False}),
              (small, 5, "rule", {"scene": False})]  # fmt: skip
    kinds: set[str] = set()
    for i, (config, seed, name, options) in enumerate(cases):
        files = {mode: _recorded(tmp_path / mode / f"ep{i}.mcap", config, seed,
                                 _always_right if name == "right" else make_driver(name, seed), mode, **options)
                 for mode in ("single", "inline", "process")}  # fmt: skip
        assert files["inline"] == files["single"] == files["process"], (i, options)
        kinds |= set(read_episode(tmp_path / "inline" / f"ep{i}.mcap").events["kind"])
    assert {"lane_change_start", "lane_change_end", "lane_invasion", "collision", "off_road"} <= kinds


@pytest.mark.parametrize("writer", ["process", "inline"])
def test_every_scene_message_carries_the_lane_markings(tmp_path: pathlib.Path, small: ScenarioConfig,
                                                       writer: str) -> None:  # fmt: skip
    """Foxglove's 3D panel clears on a seek and replays the latest ``/scene`` message: each one must hold the
    road (entity ``lanes``, the same markings every time) next to the vehicles."""
    path = record_episode(small, 4, "rule", tmp_path / "ep.mcap", writer=writer).path
    with path.open("rb") as f:
        scenes = [proto for _, channel, _, proto in make_reader(f, decoder_factories=[DecoderFactory()])
                  .iter_decoded_messages() if channel.topic == "/scene"]  # fmt: skip
    entities = [{e.id: e for e in scene.entities} for scene in scenes]
    assert len(entities) == len(read_episode(path).steps) + 1  # the markings alone first, then one per decision
    assert [sorted(e) for e in entities] == [["lanes"]] + [["lanes", "vehicles"]] * (len(entities) - 1)
    lanes = [e["lanes"] for e in entities]
    assert len(lanes[0].lines) == small.road.num_lanes + 1
    assert all(lane.lines == lanes[0].lines for lane in lanes)
    assert all(len(e["vehicles"].cubes) == small.traffic.num_vehicles + 1 for e in entities[1:])


def test_rebuilt_observations_equal_the_environments(tmp_path: pathlib.Path, small: ScenarioConfig) -> None:
    result = record_episode(small, 5, "rule", tmp_path / "ep.mcap")
    ep = read_episode(result.path)
    env, driver = LaneChangeEnv(small), make_driver("rule", 5)
    obs, info = env.reset(seed=5)
    seen, done = [], False
    while not done:
        seen.append((int(env.core.sim.step[0]), obs))
        a = driver({k: v[None] for k, v in obs.items()}, info["action_mask"][None], env.core)[0]
        obs, _, terminated, truncated, info = env.step(a)
        done = terminated or truncated
    rebuilt = list(rebuild_observations(ep))
    assert [s for s, _ in rebuilt] == [s for s, _ in seen]
    stored = ep.observations()
    for (step, want), (_, got) in zip(seen, rebuilt, strict=True):
        assert want.keys() == got.keys() == {"current", "history", "image"}
        for key in want:
            assert want[key].dtype == got[key].dtype and want[key].tobytes() == got[key].tobytes(), (step, key)
        assert stored[step].tobytes() == want["current"].tobytes()
    # the final observation of an episode that ended inside a decision period (frozen steps)
    end, last = result.steps, int(ep.steps["step"].iloc[-1])
    final = ObservationRebuilder(ep).observe(end, frozen_steps=last + small.steps_per_decision - end)
    assert all(final[k].tobytes() == obs[k].tobytes() for k in obs)


@pytest.mark.parametrize("driver", ["rule", "autopilot"])
def test_replay_is_bit_exact_and_finds_differences(tmp_path: pathlib.Path, small: ScenarioConfig, driver: str) -> None:
    result = record_episode(small, 2, driver, tmp_path / "ep.mcap", images=False)
    report = replay(result.path)
    assert report.matches, str(report)
    assert report.steps_compared == result.steps + 1 and report.decisions == result.decisions
    assert report.replayed_outcome == report.recorded_outcome == result.outcome
    other = dataclasses.replace(small, traffic=dataclasses.replace(small.traffic, speed_kmh=25.0))
    bad = replay(result.path, config=other)
    assert not bad.matches and bad.first_difference is not None
    assert bad.first_difference.step == 0 and bad.first_difference.column == "speed"
    assert "differs at step 0" in str(bad)


CHILD = """
import os, signal, sys, time
from lcdata import EpisodeRecorder, episode_seed
from lcdata.record import episode_metadata
from lcdata.writer_process import open_writer
from lcsim.core import LaneChangeCore
from lcsim.registry import make_driver
from lcsim.sim import LOG_STEPS
from tests.conftest import small_config

cfg = small_config(time_limit_s=200.0, route_length_m=1000.0)
core, driver = LaneChangeCore(cfg, 1), make_driver("rule")
writer = open_writer(sys.argv[1], mode=sys.argv[2], metadata=episode_metadata(cfg, 4, driver="rule"), chunk_size=8192)
recorder = EpisodeRecorder(writer, core)
core.reset([0], [episode_seed(4)])
recorder.attach()
obs = core.observe()
for _ in range(30):
    mask = core.action_mask()
    a = driver(obs, mask, core)
    recorder.before_step(obs, mask, a)
    recorder.after_step(core.step(a))
    obs = core.observe()
if sys.argv[2] == "process":
    writer.message_count  # an answer from the helper: everything sent so far has reached it
    print(writer.writer_pid, flush=True)
else:
    time.sleep(0.5)  # let the writer thread write the finished chunks
os.kill(os.getpid(), signal.SIGKILL)
"""


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_sigkill_leaves_a_recoverable_partial(tmp_path: pathlib.Path, small: ScenarioConfig, mode: str) -> None:
    """SIGKILL of the recording process mid-episode. With the helper process, the helper sees its input
    end, writes out all it was sent and leaves the file ``.partial``: every step recorded is there."""
    other = record_episode(small, 1, "keep", tmp_path / "other.mcap", images=False).path
    before = other.read_bytes()
    target = tmp_path / "killed.mcap"
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(CHILD), str(target), mode], cwd=ROOT, timeout=120,
                          capture_output=True)  # fmt: skip
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    if mode == "process":
        wait_gone(int(proc.stdout.split()[-1]))
    assert not target.exists()
    partial = target.with_name(target.name + ".partial")
    with pytest.warns(TruncatedFileWarning, match="recovered"):
        ep = read_episode(partial)
    assert not ep.complete
    tracks = track_arrays(ep)  # complete chunks only: consecutive steps from 0
    assert tracks.steps[0] == 0 and len(tracks.steps) >= 100
    if mode == "process":  # all 30 decisions of 10 steps reached the helper, and it wrote them all out
        np.testing.assert_array_equal(tracks.steps, np.arange(301))
        assert len(ep.steps) == 30
    assert other.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "killed.mcap.partial", "other.mcap"]  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TruncatedFileWarning)
        report = replay(partial)
    assert report.matches, str(report)


def test_recorder_rejects_bad_env(tmp_path: pathlib.Path, small: ScenarioConfig) -> None:
    core = LaneChangeCore(small, 1)
    with EpisodeWriter(tmp_path / "x.mcap", metadata={}) as writer:
        with pytest.raises(ValueError, match="env must be in"):
            EpisodeRecorder(writer, core, env=1)
        with pytest.raises(RuntimeError, match="before_step"):
            EpisodeRecorder(writer, core).after_step(None)  # type: ignore[arg-type]


def test_replay_needs_an_episode_seed(tmp_path: pathlib.Path) -> None:
    with EpisodeWriter(tmp_path / "x.mcap", metadata={"seed": 1}) as writer:
        writer.write_ego(0, 0.0, speed=1.0, lane=0)
    with pytest.raises(ValueError, match="episode_seed"):
        replay(tmp_path / "x.mcap")
