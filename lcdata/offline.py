"""Offline data first: rebuild a driver's observations from a recording, and replay a recording.

Observations are not trusted from the file; they are recomputed from the recorded tracks by the very
code the environment runs (:meth:`lcsim.core.LaneChangeCore.observe`): the recorded state of step k
and the positions of the H steps before it are put into a one-environment simulator, which is then
observed. :func:`replay` re-simulates an episode from its config, episode seed and recorded actions
and checks that the tracks agree bit for bit.
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from lcdata.reader import Episode, read_episode
from lcsim.config import ScenarioConfig
from lcsim.core import RUNNING, LaneChangeCore
from lcsim.sim import HighwaySim

STATE_COLUMNS = ("x", "y", "yaw", "speed", "accel", "lane", "target_lane", "length", "width")


@dataclass(frozen=True, slots=True)
class TrackArrays:
    """Recorded tracks as dense arrays: ``steps`` (S,) and ``columns[name]`` (S, N), vehicle id = column."""

    steps: np.ndarray
    columns: dict[str, np.ndarray]

    def row(self, step: int) -> int:
        """Index of ``step`` in :attr:`steps` (KeyError when it was not recorded)."""
        i = int(step) - int(self.steps[0]) if len(self.steps) else -1
        if not 0 <= i < len(self.steps):
            raise KeyError(f"step {step} is not in the recording (steps {self.steps[0]}..{self.steps[-1]})")
        return i


def track_arrays(episode: Episode) -> TrackArrays:
    """Pivot ``episode.tracks`` into (S, N) arrays; the recording must hold every step from the first on."""
    tracks = episode.tracks
    steps_all = tracks["step"].to_numpy()
    steps, counts = np.unique(steps_all, return_counts=True)
    if len(steps) == 0:
        raise ValueError(f"{episode.path}: no /vehicles messages")
    n = int(counts[0])
    if (counts != n).any() or not np.array_equal(steps, np.arange(steps[0], steps[0] + len(steps))):
        raise ValueError(f"{episode.path}: /vehicles must hold all {n} vehicles at every consecutive step")
    ids = tracks["vehicle_id"].to_numpy().reshape(-1, n)
    if not (ids == np.arange(n)).all():
        raise ValueError(f"{episode.path}: /vehicles rows are not in vehicle-id order")
    columns = {name: tracks[name].to_numpy().reshape(-1, n) for name in STATE_COLUMNS}
    return TrackArrays(steps, columns)


def episode_config(episode: Episode) -> ScenarioConfig:
    """The :class:`~lcsim.config.ScenarioConfig` stored in the episode's metadata."""
    if not episode.metadata.get("config"):
        raise ValueError(f"{episode.path}: no scenario config in the metadata")
    return ScenarioConfig.from_dict(episode.metadata["config"])


class ObservationRebuilder:
    """Recompute observations of a recorded episode with :meth:`LaneChangeCore.observe`.

    Args:
        episode: a recorded episode (complete or recovered from a ``.partial``).
        config: the scenario (default: the one in the metadata).
    """

    def __init__(self, episode: Episode, config: ScenarioConfig | None = None) -> None:
        self.episode = episode
        self.config = config or episode_config(episode)
        self.core = LaneChangeCore(self.config, 1)
        self.tracks = track_arrays(episode)
        n = self.tracks.columns["x"].shape[1]
        if n != self.core.sim.num_vehicles:
            raise ValueError(f"{episode.path}: {n} vehicles recorded, the config has {self.core.sim.num_vehicles}")

    def observe(self, step: int, *, frozen_steps: int = 0) -> dict[str, np.ndarray]:
        """The observation at simulation step ``step``, as ``LaneChangeEnv`` returns it.

        Args:
            step: a recorded simulation step (a decision step for what the driver saw).
            frozen_steps: simulation steps the episode stayed frozen after ``step`` (the final
                observation of an episode that ended inside a decision period).

        Returns:
            ``current`` (1+K, 9) float32, ``history`` (K, H, 3) float32 and ``image`` (3, S, S) uint8
            when the scenario renders one.
        """
        sim: HighwaySim = self.core.sim
        cols, i = self.tracks.columns, self.tracks.row(step)
        for name in STATE_COLUMNS:
            getattr(sim, name)[0] = cols[name][i]
        h = sim.history_len
        # Oldest first; before the first step the simulator's ring holds the reset positions.
        idx = np.concatenate([np.arange(i - h + 1, i + 1), np.full(frozen_steps, i)])[-h:]
        idx = np.maximum(idx, 0)
        sim.hist[0, :, :, 0] = cols["x"][idx]
        sim.hist[0, :, :, 1] = cols["y"][idx]
        sim.hist_ptr = h - 1
        sim.hist_count[0] = int(step) + 1 + frozen_steps
        # The neighbour index of this state. A traffic vehicle is changing lanes where its target lane is
        # not its lane; where the two agree mid-change, the target adds no lane the body does not touch.
        sim.lc_active[0] = sim.target_lane[0] != sim.lane[0]
        sim.lc_active[0, 0] = False  # the ego's change is ego_lc_active; its target lane is not a member
        sim.rebuild_index()
        return {k: v[0] for k, v in self.core.observe().items()}


def rebuild_observations(episode: Episode, config: ScenarioConfig | None = None,
                         ) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
    """Yield ``(step, observation)`` for every recorded RL decision, in order (what the driver saw, or, with
    ``config``, what a driver observing with that scenario would have seen)."""
    rebuilder = ObservationRebuilder(episode, config)
    for step in episode.steps["step"].to_numpy():
        yield int(step), rebuilder.observe(int(step))


# ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Difference:
    """First place where a replay departs from the recording."""

    step: int
    vehicle_id: int
    """-1 when the difference is not about one vehicle (a missing step, a reward, the outcome)."""
    column: str
    recorded: float | str
    replayed: float | str


@dataclass(frozen=True, slots=True)
class ReplayReport:
    """Result of :func:`replay`."""

    path: pathlib.Path
    matches: bool
    steps_compared: int
    decisions: int
    recorded_outcome: str
    replayed_outcome: str
    first_difference: Difference | None

    def __str__(self) -> str:
        if self.matches:
            return (f"{self.path}: replay matches bit for bit ({self.steps_compared} steps, {self.decisions} "
                    f"decisions, outcome {self.replayed_outcome or 'running'})")  # fmt: skip
        d = self.first_difference
        assert d is not None
        who = f" vehicle {d.vehicle_id}" if d.vehicle_id >= 0 else ""
        return f"{self.path}: replay differs at step {d.step}{who} {d.column}: recorded {d.recorded!r}, replayed {d.replayed!r}"


class _Comparer:
    """Simulation hook comparing every replayed step with the recording."""

    def __init__(self, tracks: TrackArrays) -> None:
        self.tracks = tracks
        self.last = int(tracks.steps[-1])
        self.compared = 0
        self.beyond = 0
        self.first: Difference | None = None

    def __call__(self, sim: HighwaySim) -> None:
        if sim.frozen[0]:
            return
        step = int(sim.step[0])
        if step > self.last:
            self.beyond += 1
            return
        self.compared += 1
        if self.first is not None:
            return
        i = self.tracks.row(step)
        for name in STATE_COLUMNS:
            rec, rep = self.tracks.columns[name][i], np.asarray(getattr(sim, name)[0], dtype=np.float64)
            if rec.dtype.kind == "f":
                diff = rec.view(np.uint64) != rep.view(np.uint64)
            else:
                diff = rec != rep
            if diff.any():
                v = int(np.flatnonzero(diff)[0])
                self.first = Difference(step, v, name, rec[v].item(), rep[v].item())
                return


def replay(path: str | os.PathLike[str], *, config: ScenarioConfig | None = None) -> ReplayReport:
    """Re-simulate a recorded episode from its config, episode seed and actions; compare the tracks.

    Every recorded simulation step is compared bit for bit (all :data:`STATE_COLUMNS` of all vehicles),
    as are the rewards and the outcome. A recovered ``.partial`` file is compared as far as it goes.

    Raises:
        ValueError: the file lacks what a replay needs (config, episode seed).
    """
    episode = read_episode(path)
    meta = episode.metadata
    if "episode_seed" not in meta:
        raise ValueError(f"{episode.path}: no episode_seed in the metadata; only files written by "
                         "lcdata.record_episode can be replayed")  # fmt: skip
    config = config or episode_config(episode)
    tracks = track_arrays(episode)
    steps = episode.steps.sort_values("decision")
    core = LaneChangeCore(config, 1, autopilot_ego=bool(meta.get("autopilot", False)))
    comparer = _Comparer(tracks)
    core.reset([0], [meta["episode_seed"]])
    comparer(core.sim)
    core.sim.hooks.append(comparer)
    outcome, first, decisions = RUNNING, None, 0
    for rec_step, action, reward in zip(steps["step"], steps["action"], steps["reward"], strict=True):
        if outcome != RUNNING:
            first = first or Difference(int(rec_step), -1, "decision", "present", "episode already over")
            break
        result = core.step(np.array([action]))
        decisions += 1
        outcome = str(result.outcome[0])
        got = float(result.reward[0])
        if first is None and np.float64(got).view(np.uint64) != np.float64(reward).view(np.uint64):
            first = Difference(int(rec_step), -1, "reward", float(reward), got)
    recorded_outcome = str(steps["outcome"].iloc[-1]) if len(steps) else RUNNING
    first = comparer.first or first
    if first is None and outcome != recorded_outcome:
        first = Difference(int(core.sim.step[0]), -1, "outcome", recorded_outcome, outcome)
    if first is None and episode.complete and comparer.beyond:
        first = Difference(comparer.last + 1, -1, "step", "absent", "present")
    if first is None and episode.complete and comparer.compared < len(tracks.steps):
        first = Difference(int(core.sim.step[0]) + 1, -1, "step", "present", "absent")
    return ReplayReport(
        path=episode.path, matches=first is None, steps_compared=comparer.compared, decisions=decisions,
        recorded_outcome=recorded_outcome, replayed_outcome=outcome, first_difference=first,
    )  # fmt: skip
