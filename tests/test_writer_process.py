"""lcdata.writer_process: the same bytes as the in-process writer, errors reported, kill safety."""

from __future__ import annotations

import os
import pathlib
import signal

import numpy as np
import pytest

from lcdata import read_episode, record_episode
from lcdata.record import EpisodeRecorder, episode_metadata, episode_seed
from lcdata.writer_process import ProcessEpisodeWriter, WriterProcessError, open_writer, writer_process_pid
from lcsim.config import ScenarioConfig
from lcsim.core import LaneChangeCore
from lcsim.registry import make_driver
from tests.conftest import wait_gone

ROOT = pathlib.Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000


@pytest.mark.parametrize("images", [True, False])
def test_same_bytes_as_the_in_process_writer(tmp_path: pathlib.Path, small: ScenarioConfig, images: bool) -> None:
    files = {}
    for mode in ("process", "thread", "inline"):
        result = record_episode(small, 3, "rule", tmp_path / mode / "ep.mcap", images=images, start_time_ns=T0,
                                writer=mode)  # fmt: skip
        files[mode] = result.path.read_bytes()
        assert result.messages > 0 and result.bytes == len(files[mode])
    assert files["process"] == files["inline"] == files["thread"]
    assert writer_process_pid() is not None


def test_each_call_gives_the_same_bytes(tmp_path: pathlib.Path) -> None:
    """Every writing method, called directly (per step and batched, static and per-step columns; step logs and
    decisions with events, views without a pose or an image, arrays not contiguous and of other types)."""
    rng = np.random.default_rng(0)
    n, k = 5, 4
    ids, length, width = np.arange(n), np.full(n, 4.8), np.full(n, 1.9)
    cols = [rng.normal(size=(k, n)) for _ in range(5)]
    lanes = rng.integers(0, 4, size=(2, k, n))
    ego = np.column_stack([rng.normal(size=k), lanes[0, :, 0], [-1, 2, -1, -1], [-1, -1, 1, -1], [0, 0, 1, 1],
                           rng.normal(size=(k, 3))])  # fmt: skip
    contents = []
    for mode in ("process", "inline"):
        with open_writer(tmp_path / mode / "ep.mcap", mode=mode, metadata={"seed": 3}, start_time_ns=T0) as w:
            w.write_sim_steps(np.arange(k), np.arange(k) * 0.05, (ids, *cols, lanes[0], lanes[1], length, width), ego)
            w.write_sim_step(k, k * 0.05, (ids, *(c[0] for c in cols), lanes[0, 0], lanes[1, 0], length, width),
                             1.5, 2, -1, -1, False, 0.1, 0.2, 0.0)  # fmt: skip
            w.write_vehicles(k + 1, 0.3, ids, *(c[1] for c in cols), lanes[0, 1], lanes[1, 1], length, width)
            w.write_ego(k + 1, 0.3, speed=2.0, lane=1)
            log = _log(k, n, cols, lanes, ego, first=k + 2)
            strided = np.repeat(_log(k, n, cols, lanes, ego, first=2 * k + 2), 2, axis=1)[:, ::2]  # not contiguous
            w.write_sim_log(log, (ids, length, width), False, False)
            w.write_sim_log(strided, (ids.astype(np.int32), length, width), False, False)
            pose = np.stack((cols[0][0], cols[1][0], cols[2][0]))
            image = rng.integers(0, 255, (3, 8, 6), dtype=np.uint8)
            rl = np.array([3, 2, 0, 1, 1, -1.5, -2.5, 0, 1.0, 0, 1, 0, 2], dtype=np.float64)
            for d, (current, view_image, view_pose) in enumerate((
                    (rng.normal(size=(3, 4)).astype(np.float32), image, pose), (rng.normal(size=(2, 2)), None, pose[:, ::-1]),
                    (None, image[:, ::2], None))):  # fmt: skip
                w.write_decision(10 + d, 0.6 + 0.05 * d, view_pose, view_image, _log(k, n, cols, lanes, ego, first=(3 + d) * k + 2),
                                 (ids, length, width), True, True, rl, current)  # fmt: skip
            w.write_view(13, 0.75, pose, (ids, length, width), image)
            w.write_transform(k, 0.2, 1.0, 2.0, 0.3)
            w.write_scene(k, 0.2, ids, cols[0][0], cols[1][0], cols[2][0], length, width)
            w.write_image(k, 0.2, rng.integers(0, 255, (3, 8, 6), dtype=np.uint8))
            w.write_rl_step(k, 0.2, action=2, action_mask=np.array([False, True, True]), reward=-1.5,
                            reward_components={"forward": 1.0, "collision": -2.5}, outcome="collision",
                            terminated=True, decision=7, obs_current=rng.normal(size=(3, 4)))  # fmt: skip
            w.write_prediction(k, 0.2, np.array([1, -1]), rng.normal(size=(2, 3, 2)))
            w.write_collision(k, 0.2, other_id=2, ego_x=1.0, ego_y=2.0, ego_speed=3.0, other_speed=4.0)
            w.write_event(k, 0.2, "note", "text", "debug")
            w.write_lane_markings(0.0, [np.array([[0.0, 0.0], [10.0, 0.0]])], [True])
        contents.append(w.path.read_bytes())
        rng = np.random.default_rng(0)  # the same draws for the second writer
        cols = [rng.normal(size=(k, n)) for _ in range(5)]
        lanes = rng.integers(0, 4, size=(2, k, n))
        ego = np.column_stack([rng.normal(size=k), lanes[0, :, 0], [-1, 2, -1, -1], [-1, -1, 1, -1], [0, 0, 1, 1],
                               rng.normal(size=(k, 3))])  # fmt: skip
    assert contents[0] == contents[1]
    ep = read_episode(tmp_path / "process" / "ep.mcap")
    assert ep.ego["step"].tolist() == list(range(6 * k + 2))
    assert ep.ego["collision_with"].tolist()[:4] == ep.ego["collision_with"].tolist()[-4:] == [-1, 2, -1, -1]
    x = ep.tracks["x"].to_numpy()
    target_lane = ep.tracks["target_lane"].to_numpy()
    for first in (0, k + 2, 2 * k + 2, 3 * k + 2, 4 * k + 2, 5 * k + 2):  # columns; logs, a strided log, decisions
        np.testing.assert_array_equal(x[first * n : (first + k) * n], cols[0].reshape(-1))
        np.testing.assert_array_equal(target_lane[first * n : (first + k) * n], lanes[1].reshape(-1))
    assert (ep.steps["action"] == 2).all() and len(ep.steps) == 4  # three decisions and write_rl_step
    assert "lane_change_end" in set(ep.events["kind"]) and "on_road" in set(ep.events["kind"])


def _log(k: int, n: int, cols: list[np.ndarray], lanes: np.ndarray, ego: np.ndarray, first: int) -> np.ndarray:
    """K step log rows (lcsim.kernel.log_state) of steps ``first``, ... from the test's columns."""
    from lcsim import kernel

    log = np.zeros((k, kernel.log_width(n)))
    log[:, kernel.LOG_STEP], log[:, kernel.LOG_T] = first + np.arange(k), 0.05 * (first + np.arange(k))
    log[:, kernel.LOG_SPEED : kernel.LOG_BRAKE + 1] = ego
    log[:, kernel.LOG_LC_ACTIVE] = [1, 1, 0, 0]
    vehicles = log[:, kernel.LOG_HEAD :].reshape(k, 7, n)
    for j, column in enumerate((*cols, *lanes)):
        vehicles[:, j] = column
    return log


def test_episodes_written_at_once_by_one_helper(tmp_path: pathlib.Path, small: ScenarioConfig) -> None:
    """Two environments of a batch recorded at the same time (interleaved records) equal two inline recordings."""
    seeds = [episode_seed(4), episode_seed(9)]
    contents = {}
    for mode in ("process", "inline"):
        core, driver = LaneChangeCore(small, 2), make_driver("rule", 0)
        writers = [open_writer(tmp_path / mode / f"e{i}.mcap", mode=mode, start_time_ns=T0,
                               metadata=episode_metadata(small, i, driver="rule")) for i in range(2)]  # fmt: skip
        recorders = [EpisodeRecorder(w, core, i) for i, w in enumerate(writers)]
        core.reset([0, 1], seeds)
        for r in recorders:
            r.attach()
        obs = core.observe()
        while not all(r.done for r in recorders):
            mask = core.action_mask()
            actions = driver(obs, mask, core)
            for r in recorders:
                if not r.done:
                    r.before_step(obs, mask, actions)
            result = core.step(actions)
            for r in recorders:
                if r._pending is not None:
                    r.after_step(result)
            obs = core.observe()
        for r, w in zip(recorders, writers, strict=True):
            r.detach()
            w.close()
        contents[mode] = [w.path.read_bytes() for w in writers]
    assert contents["process"] == contents["inline"]
    assert contents["process"][0] != contents["process"][1]


def test_an_error_in_the_helper_is_raised_at_close(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "bad.mcap"
    writer = ProcessEpisodeWriter(path, metadata={"seed": 1})
    writer.write_ego(0, 0.0, speed=1.0, lane=0)
    writer.write_event(0, 0.0, "note", "a bad level", level="loud")  # the in-process writer raises here
    with pytest.raises(RuntimeError, match="level must be one of"):
        writer.close()
    assert not path.exists() and path.with_name("bad.mcap.partial").exists()
    with pytest.raises(RuntimeError, match="closed"):
        writer.write_ego(1, 0.05, speed=1.0, lane=0)
    # the helper goes on serving other episodes
    with ProcessEpisodeWriter(tmp_path / "good.mcap", metadata={"seed": 2}) as good:
        good.write_ego(0, 0.0, speed=1.0, lane=0)
    assert good.message_count == 1 and read_episode(good.path).ego["speed"].tolist() == [1.0]


def test_exception_in_the_with_block_leaves_partial_only(tmp_path: pathlib.Path) -> None:
    path = tmp_path / "ep.mcap"
    with pytest.raises(KeyError, match="boom"), ProcessEpisodeWriter(path, metadata={}) as w:
        w.write_ego(0, 0.0, speed=1.0, lane=0)
        raise KeyError("boom")
    assert not path.exists() and path.with_name("ep.mcap.partial").exists()
    with pytest.raises(FileExistsError):
        ProcessEpisodeWriter(tmp_path / "x.mcap", metadata={}).close()
        ProcessEpisodeWriter(tmp_path / "x.mcap", metadata={})
    with pytest.raises(ValueError, match="writer mode"):
        open_writer(tmp_path / "y.mcap", mode="fast", metadata={})


def test_a_killed_helper_is_reported(tmp_path: pathlib.Path) -> None:
    writer = ProcessEpisodeWriter(tmp_path / "ep.mcap", metadata={})
    writer.write_ego(0, 0.0, speed=1.0, lane=0)
    pid = writer.writer_pid
    os.kill(pid, signal.SIGKILL)
    wait_gone(pid)
    with pytest.raises(WriterProcessError, match=f"pid {pid}"):
        writer.close()
    assert not (tmp_path / "ep.mcap").exists()
    with ProcessEpisodeWriter(tmp_path / "next.mcap", metadata={}) as nxt:  # a new helper is started
        nxt.write_ego(0, 0.0, speed=2.0, lane=1)
    assert nxt.writer_pid != pid and read_episode(nxt.path).ego["lane"].tolist() == [1]


@pytest.mark.parametrize("shared", [True, False])
def test_records_larger_than_a_segment_and_no_shared_memory(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch,
                                                           shared: bool) -> None:  # fmt: skip
    """A record larger than a segment of the shared ring goes through the pipe, and without a memfd every record
    does: the same bytes as the in-process writer either way."""
    from lcdata import writer_process
    from lcsim import kernel

    rng = np.random.default_rng(1)
    n, k = 500, 64  # a step log of 64 steps of 500 vehicles: 2 MB, larger than a segment
    log = rng.normal(size=(k, kernel.log_width(n)))
    log[:, kernel.LOG_STEP], log[:, kernel.LOG_T] = np.arange(k), 0.05 * np.arange(k)
    log[:, kernel.LOG_COLLISION : kernel.LOG_INVASION + 1] = -1
    log[:, kernel.LOG_OFF_ROAD] = log[:, kernel.LOG_LC_ACTIVE] = 0  # no events
    assert log.nbytes > writer_process.SEGMENT_BYTES
    fixed = (np.arange(n), np.full(n, 4.5), np.full(n, 1.8))
    if not shared:
        def no_memfd(*args: object) -> int:
            raise OSError("no memfd here")

        monkeypatch.setattr(writer_process.os, "memfd_create", no_memfd)
        if writer_process._service is not None:
            writer_process._service.shutdown()
        monkeypatch.setattr(writer_process, "_service", None)
    contents = []
    for mode in ("process", "inline"):
        with open_writer(tmp_path / mode / "ep.mcap", mode=mode, metadata={"seed": 1}, start_time_ns=T0) as w:
            for first in (0, k):
                shifted = log.copy()
                shifted[:, kernel.LOG_STEP] += first
                shifted[:, kernel.LOG_T] += 0.05 * first
                w.write_sim_log(shifted, fixed, False, False)
                w.write_event(first, 0.05 * first, "note", "between the large records")
        contents.append(w.path.read_bytes())
    if not shared:
        assert writer_process._service is not None and writer_process._service._ring is None
        writer_process._service.shutdown()
    assert contents[0] == contents[1]
    assert read_episode(tmp_path / "process" / "ep.mcap").ego["step"].tolist() == list(range(2 * k))
