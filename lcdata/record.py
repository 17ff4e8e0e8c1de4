"""Record simulated episodes to MCAP: a per-step recorder any driver loop can use, and whole episodes.

:class:`EpisodeRecorder` is a ``HighwaySim.log_hooks`` entry for one environment index. It records
``/vehicles`` and ``/ego/state`` (plus ``/ego/collision`` and ``/log`` events) of every simulation
step, and, when the driver loop calls :meth:`~EpisodeRecorder.before_step` and
:meth:`~EpisodeRecorder.after_step` around ``core.step``, ``/tf``, ``/scene``, the bird's-eye image
and ``/rl/step`` at the decision rate. The simulator logs the steps of a decision in its compiled call
(no Python per step) and the recorder hands them to the writer as one block, so memory stays flat however
long the run::

    core = LaneChangeCore(config, num_envs)
    with EpisodeWriter(path, metadata=episode_metadata(config, seed, ...)) as writer:
        recorder = EpisodeRecorder(writer, core, env=0)
        core.reset([0], [episode_seed(seed)])
        recorder.attach()                      # writes step 0, registers the hook
        obs = core.observe()
        while not recorder.done:
            mask = core.action_mask()
            actions = driver(obs, mask, core)
            recorder.before_step(obs, mask, actions)
            result = core.step(actions)        # the hook records every simulation step
            recorder.after_step(result)
            obs = core.observe()
        recorder.detach()

:func:`record_episode` does exactly that for one seed and one driver.
"""

from __future__ import annotations

import logging
import os
import pathlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lcdata.corpus import from_frame
from lcdata.executors import EXECUTORS, ray_map
from lcdata.writer import MAX_START_TIME_NS, OUTCOME_CODES, EpisodeWriter, package_version
from lcdata.writer_process import WRITER_MODES, ProcessEpisodeWriter, open_writer
from lckit.pool import WorkerPool
from lcsim import kernel
from lcsim.config import ScenarioConfig
from lcsim.core import KEEP, RUNNING, SUCCESS, LaneChangeCore, StepResult
from lcsim.drivers import Driver
from lcsim.envs import episode_seed as lcsim_episode_seed
from lcsim.episodes import EpisodeHook, run_episodes
from lcsim.planning import DecisionReport
from lcsim.planning.report import check_imagined_paths
from lcsim.registry import DRIVER_NAMES, make_driver
from lcsim.sim import HighwaySim

log = logging.getLogger(__name__)

DRIVERS = ("autopilot", *DRIVER_NAMES)
"""Driver names :func:`record_episode` accepts (``autopilot``: the ego is driven by the traffic autopilot)."""


SEED_EPOCH_NS = 1_704_067_200 * 1_000_000_000
"""2024-01-01T00:00:00Z: the time origin of seed-derived start times (:func:`seed_start_time_ns`)."""


MAX_USER_SEED = (MAX_START_TIME_NS - SEED_EPOCH_NS) // 1_000_000_000
"""The largest user seed a recording takes: the last whose seed-derived start time an MCAP file can hold."""


def seed_start_time_ns(seed: int) -> int:
    """The default time of ``t = 0`` in the file of the episode with user seed ``seed``: :data:`SEED_EPOCH_NS`
    plus ``seed`` seconds. Derived from the seed, not the clock, so that the same command writes the same
    bytes; distinct seeds get distinct, ordered start times."""
    return SEED_EPOCH_NS + int(seed) * 1_000_000_000


def episode_seed(seed: int) -> int:
    """The episode seed ``LaneChangeEnv.reset(seed=seed)`` derives (it fully determines the episode)."""
    return lcsim_episode_seed(int(seed))


def episode_filename(scenario: str, driver: str, seed: int) -> str:
    """Deterministic file name of an episode, e.g. ``lane-change_rule_s0000123.mcap``."""
    return f"{scenario or 'episode'}_{driver}_s{int(seed):07d}.mcap"


class EpisodeRecorder:
    """Write environment ``env`` of ``core`` to ``writer`` (see the module docstring for the loop).

    Args:
        writer: an open :class:`~lcdata.writer.EpisodeWriter` or
            :class:`~lcdata.writer_process.ProcessEpisodeWriter`.
        core: the :class:`~lcsim.core.LaneChangeCore` being stepped (any number of environments).
        env: index of the environment to record.
        images: write the observation's bird's-eye image (when it has one) at every decision.
        scene: write ``/tf`` and ``/scene`` (vehicles and lane markings) at every decision.
    """

    def __init__(
        self, writer: EpisodeWriter | ProcessEpisodeWriter, core: LaneChangeCore, env: int = 0, *, images: bool = True,
        scene: bool = True,
    ) -> None:
        if not 0 <= env < core.num_envs:
            raise ValueError(f"env must be in [0, {core.num_envs}), got {env}")
        self.writer, self.core, self.env = writer, core, env
        self.images, self.scene = images, scene
        self.done = False
        self.decisions = 0
        self.total_reward = 0.0
        self.outcome = RUNNING
        self._lc_active = False
        self._off_road = False
        self._pending: tuple[int, float, int, np.ndarray, np.ndarray] | None = None  # the decision under way
        self._view: tuple[np.ndarray | None, np.ndarray | None] | None = None  # its pose and image, not yet written
        self._stash: np.ndarray | None = None  # its steps, as the simulator logged them, not yet written
        self._fixed: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # ids, length, width of the episode

    # -- life cycle -------------------------------------------------------------------------------
    def attach(self) -> None:
        """Record the state right after ``core.reset`` (step 0) and register the log hook."""
        sim, e = self.core.sim, self.env
        if self._pending is not None:
            raise RuntimeError("attach() inside a decision: call after_step() before a reset")
        self.done, self.decisions, self.total_reward, self.outcome = False, 0, 0.0, RUNNING
        row = sim.log_row(e)
        self._lc_active, self._off_road = bool(row[kernel.LOG_LC_ACTIVE]), bool(row[kernel.LOG_OFF_ROAD])
        self._fixed = (sim.ids, sim.length[e].copy(), sim.width[e].copy())
        t0 = float(row[kernel.LOG_T])
        if self.scene:
            self._write_lane_markings(t0)
        self.writer.write_event(int(row[kernel.LOG_STEP]), t0, "episode_start",
                                f"env {e}, episode seed {int(self.core.seeds[e])}")  # fmt: skip
        self._write_log(row[None])  # step 0
        if self not in sim.log_hooks:
            sim.log_hooks.append(self)

    def detach(self) -> None:
        """Write what is held back and stop recording (remove the log hook). Safe to call twice."""
        self._flush()
        if self in self.core.sim.log_hooks:
            self.core.sim.log_hooks.remove(self)

    # -- per compiled call of the simulator (the log hook) ----------------------------------------------
    def __call__(self, sim: HighwaySim, log: np.ndarray, counts: np.ndarray) -> None:
        # Runs after every compiled call of the simulator with the rows of the steps it ran. Inside a decision the
        # rows wait for after_step, which writes the whole decision in one call (the simulator reuses its log at its
        # next call: a second call inside the decision writes them first); otherwise the writer copies them now.
        k = counts.item(self.env)
        if not k or self.done:
            return
        rows = log[self.env, :k]
        if self._pending is not None and self._stash is None:
            self._stash = rows
            return
        self._flush()
        self._write_log(rows)

    def _write_log(self, rows: np.ndarray) -> None:
        assert self._fixed is not None
        self.writer.write_sim_log(rows, self._fixed, self._off_road, self._lc_active)
        self._track(rows)

    def _track(self, rows: np.ndarray) -> None:
        """The ego's state after ``rows`` (the events of the next rows are relative to it)."""
        if len(rows):
            last = rows[-1]
            self._off_road = last.item(kernel.LOG_OFF_ROAD) != 0
            self._lc_active = last.item(kernel.LOG_LC_ACTIVE) != 0

    def _flush(self) -> None:
        """Write what the decision under way holds back: its view and its steps."""
        if self._view is not None:
            assert self._pending is not None and self._fixed is not None
            (pose, image), self._view = self._view, None
            self.writer.write_view(self._pending[0], self._pending[1], pose, self._fixed, image)
        if self._stash is not None:
            rows, self._stash = self._stash, None
            self._write_log(rows)

    # -- per decision -----------------------------------------------------------------------------
    def before_step(self, obs: Mapping[str, np.ndarray], action_mask: np.ndarray, actions: np.ndarray) -> None:
        """Call just before ``core.step(actions)``: ``/tf``, ``/scene`` and the image of this decision (written
        with the rest of the decision by :meth:`after_step`).

        Args:
            obs: the batched observation of all environments (``core.observe()``), e.g. ``current`` (E, 9, 9); it
                must stay as it is until :meth:`after_step` (the next ``core.observe()`` makes a new one).
            action_mask: (E, 3) bool. actions: (E,) int.
        """
        self._flush()
        sim, e = self.core.sim, self.env
        step, t = sim.step.item(e), sim.t_s.item(e)
        image = obs["image"][e] if self.images and "image" in obs else None
        pose = sim.vf[kernel.X : kernel.YAW + 1, e].copy() if self.scene else None  # x, y, yaw
        self._view = (pose, image) if pose is not None or image is not None else None
        self._pending = (step, t, actions, action_mask, obs["current"][e])

    def write_predictions(self, predictions: np.ndarray) -> None:
        """``/prediction`` for this decision from the policy's ``(K, F, 2)`` ego-frame predictions.

        Slot k is the observation's k-th neighbour slot (``core.neighbours``); call it between
        :meth:`before_step` and ``core.step``. Positions are written in the world frame.
        """
        self._flush()
        sim, e = self.core.sim, self.env
        nb = self.core.neighbours(np.array([e]))[0]
        ids = np.where(nb >= 0, np.asarray(sim.ids)[np.maximum(nb, 0)], -1)
        origin = np.array([sim.x[e, 0], sim.y[e, 0]])
        xy = from_frame(np.asarray(predictions, dtype=np.float64), origin, sim.yaw[e, 0])
        self.writer.write_prediction(int(sim.step[e]), float(sim.t_s[e]), ids, xy)

    def write_planner_decision(self, report: DecisionReport) -> None:
        """``/planner/decision`` for this decision from a planning driver's report of the batch
        (:attr:`lcsim.planning.LookaheadDriver.last_report`), when the planner had a choice in this environment (none
        is written otherwise); call between :meth:`before_step` and ``core.step``."""
        e = self.env
        if not report.choice[e]:
            return
        self._flush()
        sim = self.core.sim
        self.writer.write_planner_decision(
            int(sim.step[e]), float(sim.t_s[e]), decision=self.decisions, scores=report.scores[e],
            proposed=int(report.proposed[e]), executed=int(report.executed[e]), overridden=bool(report.overridden[e]),
            paths=None if report.paths is None else report.paths.of(e),
        )  # fmt: skip

    def after_step(self, result: StepResult) -> None:
        """Call right after ``core.step``: writes the decision (its view, its steps, ``/rl/step``) and the outcome
        event when the episode ends."""
        if self._pending is None:
            raise RuntimeError("after_step() without before_step()")
        step, t, actions, action_mask, current = self._pending
        e = self.env
        outcome = str(result.outcome[e])
        reward = result.reward.item(e)
        c = result.components
        mask = np.asarray(action_mask).reshape(-1, 3)[e].tolist()
        rl = (self.decisions, np.asarray(actions).item(e), *mask, reward, c["collision"].item(e), c["off_road"].item(e),
              c["forward"].item(e), c["success"].item(e), result.terminated.item(e), result.truncated.item(e),
              OUTCOME_CODES[outcome])  # fmt: skip
        pose, image = self._view if self._view is not None else (None, None)
        rows = self._stash if self._stash is not None else self._no_steps
        assert self._fixed is not None
        self.writer.write_decision(step, t, pose, image, rows, self._fixed, self._off_road, self._lc_active, rl,
                                   current)  # fmt: skip
        self._pending, self._view, self._stash = None, None, None
        self._track(rows)
        self.decisions += 1
        self.total_reward += reward
        if outcome != RUNNING:
            sim = self.core.sim
            end_step, end_t = int(sim.step[e]), float(sim.t_s[e])
            level = "info" if outcome == SUCCESS else "warning"
            self.writer.write_event(end_step, end_t, "outcome", outcome, level)
            self.outcome, self.done = outcome, True

    @property
    def _no_steps(self) -> np.ndarray:
        return np.zeros((0, kernel.log_width(self.core.sim.num_vehicles)))

    def _write_lane_markings(self, t_s: float) -> None:
        cfg = self.core.config
        x0 = -cfg.traffic.spawn_behind_m - 50.0
        x1 = cfg.route_length_m + cfg.traffic.spawn_ahead_m + 50.0
        marks = self.core.sim.road.markings()
        lines = [np.array([[x0, y], [x1, y]]) for y, _ in marks]
        self.writer.write_lane_markings(t_s, lines, [kind == 0 for _, kind in marks])


# ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class RecordResult:
    """What :func:`record_episode` wrote."""

    path: pathlib.Path
    outcome: str
    seed: int
    episode_seed: int
    steps: int
    """Simulation steps recorded after step 0."""
    decisions: int
    total_reward: float
    messages: int
    bytes: int


def _keep_driver(obs: Mapping[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
    return np.full(core.num_envs, KEEP, dtype=np.int64)


def resolve_driver(driver: str | Driver, seed: int) -> tuple[Any, bool, str, str]:
    """``(callable, autopilot_ego, name, description)`` for a driver name or a driver object."""
    if isinstance(driver, str):
        if driver == "autopilot":
            return _keep_driver, True, "autopilot", "autopilot: the ego is driven by the traffic autopilot"
        if driver not in DRIVERS:
            raise ValueError(f"unknown driver {driver!r}; choose one of {', '.join(DRIVERS)}")
        driver = make_driver(driver, seed)
    name = str(getattr(driver, "name", type(driver).__name__))
    config = getattr(driver, "config", None)
    desc = f"{name}: {type(driver).__module__}.{type(driver).__qualname__}"
    if config is not None:
        desc += f" {config!r}"
    if name == "random":
        desc += f" (seed {seed})"
    return driver, False, name, desc


def keep_imagined_paths(driver: Any, futures: int) -> None:
    """Ask a planning driver to keep the ego's path in ``futures`` imagined futures per candidate (its
    ``imagined_paths``; 0 asks nothing of any driver). ``ValueError`` for a driver that imagines none, or a number out
    of ``[0, lcsim.planning.MAX_IMAGINED_FUTURES]``."""
    futures = check_imagined_paths(futures)
    if not futures:
        return
    if not hasattr(driver, "imagined_paths"):
        name = getattr(driver, "name", type(driver).__name__)
        raise ValueError(f"imagined paths: the driver {name} imagines no futures (a driver behind the safety layer "
                         "does)")  # fmt: skip
    driver.imagined_paths = futures


_CONFIG_JSON: dict[int, tuple[ScenarioConfig, str]] = {}  # config_json's, by the id of configs it keeps alive


def config_json(config: ScenarioConfig) -> str:
    """``config.to_json()``, remembered for the last few config objects (a recorder of many episodes with one
    config asks for it every episode; configs are frozen)."""
    cached = _CONFIG_JSON.get(id(config))
    if cached is not None and cached[0] is config:
        return cached[1]
    if len(_CONFIG_JSON) >= 8:
        _CONFIG_JSON.clear()
    text = config.to_json()
    _CONFIG_JSON[id(config)] = (config, text)
    return text


def episode_metadata(config: ScenarioConfig, seed: int, *, driver: str, driver_description: str = "",
                     scenario: str = "", autopilot: bool = False) -> dict[str, Any]:  # fmt: skip
    """The metadata record of an episode: full config JSON, user and episode seeds, driver, version."""
    return {
        "config": config_json(config), "seed": int(seed), "episode_seed": str(episode_seed(seed)),
        "driver": driver, "driver_description": driver_description or driver, "scenario": scenario,
        "autopilot": bool(autopilot), "version": package_version(),
        "steps_per_decision": config.steps_per_decision,
    }  # fmt: skip


def record_episode(
    config: ScenarioConfig,
    seed: int,
    driver: str | Driver,
    path: str | os.PathLike[str],
    *,
    scenario: str = "",
    overwrite: bool = False,
    images: bool = True,
    start_time_ns: int | None = None,
    writer: str = "process",
    imagined_paths: int = 0,
) -> RecordResult:
    """Run one episode (``LaneChangeEnv.reset(seed=seed)`` semantics) and write it to ``path``.

    Args:
        config: the scenario.
        seed: user seed; the episode seed is derived from it as the gymnasium environment does.
        driver: ``autopilot``, ``rule``, ``keep``, ``random`` or a driver object
            (``driver(obs, action_mask, core) -> actions (E,)``).
        path: the ``.mcap`` file (written as ``.partial`` and renamed at the end).
        scenario: scenario name stored in the metadata.
        overwrite: replace an existing file instead of raising ``FileExistsError``.
        images: record the bird's-eye image at every decision (when the scenario renders one).
        start_time_ns: time of ``t = 0`` in the file (default: :func:`seed_start_time_ns`, so that the
            same episode gives the same bytes).
        writer: where the file is encoded and written (:data:`lcdata.writer_process.WRITER_MODES`):
            ``process`` (default: a helper process on another core, see
            :class:`~lcdata.writer_process.ProcessEpisodeWriter`), ``thread`` or ``inline``. Same bytes.
        imagined_paths: for a planning driver (the safety layer), the imagined futures per candidate whose ego path
            ``/planner/decision`` holds (0, default: none; :func:`keep_imagined_paths`). The decisions are the same.

    Returns:
        A :class:`RecordResult` with the final path and the outcome.
    """
    policy, autopilot, name, desc = resolve_driver(driver, seed)
    keep_imagined_paths(policy, imagined_paths)
    fixed = start_time_ns
    hook = RecordingHook(
        lambda u: pathlib.Path(path),
        lambda u: episode_metadata(config, u, driver=name, driver_description=desc, scenario=scenario,
                                   autopilot=autopilot),
        overwrite=overwrite, images=images, writer=writer,
        start_time_of=lambda u: seed_start_time_ns(u) if fixed is None else fixed,
    )  # fmt: skip
    run_episodes(policy, config, [seed], batch=1, hooks=[hook], autopilot_ego=autopilot)
    result = hook.finished[0]
    log.info("%s: %s after %d decisions", result.path, result.outcome, result.decisions)
    return result


class RecordingHook(EpisodeHook):
    """Records every episode of :func:`lcsim.episodes.run_episodes` to its own MCAP file (an
    :class:`EpisodeRecorder` per environment), with the predictions a policy driver saw and what a planning driver
    scored at each decision where it had a choice (``last_report``: ``/planner/decision``).

    Args:
        path_of: the file of the episode with a user seed.
        metadata_of: its metadata record (:func:`episode_metadata`).
        writer: :data:`lcdata.writer_process.WRITER_MODES` (the files are the same).
        start_time_of: its ``t = 0`` (default :func:`seed_start_time_ns`).

    :attr:`finished` gets a :class:`RecordResult` per episode written; a batch that fails leaves its
    files as ``.partial``.
    """

    def __init__(self, path_of: Callable[[int], pathlib.Path], metadata_of: Callable[[int], dict[str, Any]], *,
                 overwrite: bool = False, images: bool = True, writer: str = "thread",
                 start_time_of: Callable[[int], int] = seed_start_time_ns) -> None:
        self.path_of, self.metadata_of, self.start_time_of = path_of, metadata_of, start_time_of
        self.overwrite, self.images, self.writer = overwrite, images, writer
        self.finished: list[RecordResult] = []
        self._writers: list[Any] = []
        self._recorders: list[EpisodeRecorder] = []
        self._seeds: list[int] = []
        self._driver: Any = None

    def start(self, core: LaneChangeCore, user_seeds: Sequence[int], driver: Any) -> None:
        self._driver, self._seeds, self._writers, self._recorders = driver, list(user_seeds), [], []
        try:
            for i, u in enumerate(self._seeds):
                w = open_writer(self.path_of(u), mode=self.writer, metadata=self.metadata_of(u),
                                overwrite=self.overwrite, start_time_ns=self.start_time_of(u))
                self._writers.append(w)
                rec = EpisodeRecorder(w, core, i, images=self.images)
                rec.attach()
                self._recorders.append(rec)
        except BaseException:
            self.end(core, failed=True)
            raise

    def before_step(self, core: LaneChangeCore, obs: dict[str, np.ndarray], mask: np.ndarray, actions: np.ndarray,
                    running: np.ndarray) -> None:
        predictions = getattr(self._driver, "last_prediction", None)  # what a policy driver saw, if any
        report = getattr(self._driver, "last_report", None)  # what a planning driver scored, if it is one
        for i, recorder in enumerate(self._recorders):
            if running[i]:
                recorder.before_step(obs, mask, actions)
                if predictions is not None:
                    recorder.write_predictions(predictions[i])
                if isinstance(report, DecisionReport):
                    recorder.write_planner_decision(report)

    def after_step(self, core: LaneChangeCore, result: StepResult, running: np.ndarray) -> None:
        for i, recorder in enumerate(self._recorders):
            if running[i]:
                recorder.after_step(result)

    def end(self, core: LaneChangeCore, failed: bool) -> None:
        for rec in self._recorders:
            rec.detach()
        for i, w in enumerate(self._writers):
            if failed or i >= len(self._recorders):
                w.abort()
                continue
            w.close()
            rec, u = self._recorders[i], self._seeds[i]
            self.finished.append(RecordResult(
                path=w.path, outcome=rec.outcome, seed=u, episode_seed=int(core.seeds[i]),
                steps=int(core.sim.step[i]), decisions=rec.decisions, total_reward=rec.total_reward,
                messages=w.message_count, bytes=w.path.stat().st_size,
            ))  # fmt: skip
        self._writers, self._recorders = [], []


def _record_one(config_json: str, seed: int, driver: str | Driver, path: str, scenario: str, overwrite: bool,
                images: bool, writer: str, start_time_ns: int | None, imagined_paths: int = 0) -> RecordResult:  # fmt: skip
    """Worker entry point (module level so that a process pool can pickle it)."""
    config = ScenarioConfig.from_json(config_json)
    return record_episode(config, seed, driver, path, scenario=scenario, overwrite=overwrite, images=images,
                          writer=writer, start_time_ns=start_time_ns, imagined_paths=imagined_paths)  # fmt: skip


def iter_record_episodes(
    config: ScenarioConfig,
    seeds: Sequence[int],
    driver: str | Driver,
    out_dir: str | os.PathLike[str],
    *,
    scenario: str = "",
    workers: int = 1,
    overwrite: bool = False,
    images: bool = True,
    writer: str | None = None,
    skip_existing: bool = False,
    start_time_ns: int | None = None,
    executor: str = "local",
    imagined_paths: int = 0,
) -> Iterator[RecordResult]:
    """Record one episode per seed into ``out_dir`` (file names from :func:`episode_filename`).

    Results come in completion order. With ``workers > 1`` episodes run in that many processes;
    every episode depends only on its seed, so the files do not depend on ``workers``.
    Existing files raise ``FileExistsError`` before anything runs unless ``overwrite``.
    ``writer``: as in :func:`record_episode`; by default ``process`` with one worker (the writer
    takes an idle core) and ``thread`` with several (the cores are taken; a helper process per
    worker would cost more CPU in all). ``skip_existing``: leave the finished files there as they are and
    record only the missing episodes (a resumed run). ``start_time_ns``: every file's ``t = 0`` (default:
    derived from each seed, :func:`seed_start_time_ns`). Worker processes (:class:`lckit.pool.WorkerPool`) die
    with this process: a killed run leaves no orphan writing on. ``executor="ray"``
    records each episode as a Ray task in the open :func:`lcdata.executors.ray_session` (a driver name only:
    an object is not shipped); the files are the same. ``imagined_paths``: as in :func:`record_episode`.
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if writer is None:
        writer = "process" if workers == 1 else "thread"
    if writer not in WRITER_MODES:
        raise ValueError(f"writer must be one of {', '.join(WRITER_MODES)}, got {writer!r}")
    out = pathlib.Path(out_dir)
    name = driver if isinstance(driver, str) else resolve_driver(driver, 0)[2]
    paths = [out / episode_filename(scenario, name, s) for s in seeds]
    existing = [p for p in paths if p.exists()]
    if existing and not overwrite and not skip_existing:
        raise FileExistsError(f"{len(existing)} of {len(paths)} episode files already exist in {out} "
                              f"(e.g. {existing[0].name}); pass overwrite=True to replace them")  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    if imagined_paths:  # a driver that imagines nothing is refused before anything is written
        keep_imagined_paths(resolve_driver(driver, 0)[0], imagined_paths)
    args = [(config.to_json(), int(s), driver, str(p), scenario, overwrite, images, writer, start_time_ns,
             imagined_paths) for s, p in zip(seeds, paths, strict=True) if overwrite or not p.exists()]  # fmt: skip
    if executor == "ray":
        if not isinstance(driver, str):
            raise ValueError("a driver object is not shipped to Ray tasks: record it with the local executor")
        yield from ray_map(_record_one, args, num_cpus=1)
        return
    if executor != "local":
        raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, got {executor!r}")
    if workers == 1 or len(args) <= 1:
        for a in args:
            yield _record_one(*a)
        return
    with WorkerPool(min(workers, len(args))) as pool:  # spawned: no fork of a process that may hold writer threads
        yield from pool.map(_record_one, args, star=True, ordered=False)


def record_episodes(config: ScenarioConfig, seeds: Sequence[int], driver: str | Driver,
                    out_dir: str | os.PathLike[str], **kwargs: Any) -> list[RecordResult]:  # fmt: skip
    """:func:`iter_record_episodes`, collected and sorted by seed."""
    return sorted(iter_record_episodes(config, seeds, driver, out_dir, **kwargs), key=lambda r: r.seed)
