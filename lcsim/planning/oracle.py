"""An omniscient search for a winning sequence of decisions: what the scenario allows any policy.

:func:`search_episode` runs the episode of one seed forward in the simulator itself and searches the
tree of decisions (right / keep / left at each decision) depth first for a sequence that reaches the
end of the route without a collision or leaving the road. It sees the exact future, including the
traffic's random lane changes and how the traffic reacts to the ego, so:

- a sequence it finds is a proof that the episode can be won: :func:`replay` drives it from a fresh
  reset and must end in ``success`` (the search checks this itself);
- an episode where it finds none is one that (almost certainly) no policy can win, however good.

The tree has 3^144 leaves, so the search merges states: two branches that reach decision ``k`` with
the ego in the same (target) lane, the same time since its last lane change started (counted up to
``memory_decisions``) and the same direction of that change are taken to be the same state, and only
the first one is expanded. The ego cannot brake, so its longitudinal state hardly depends on the path;
what a merge can hide is a difference in the traffic the ego's earlier moves caused (a follower that
braked for it). A larger ``memory_decisions`` merges less and searches more; the episodes the search
gives up on can be checked again with a larger one (``lc-eval oracle --bound --memory``).

Branches are tried in the order the rule-based driver would choose (its action first, then keep, then
left, then right), so an episode the rule-based driver wins costs one simulation per decision.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from lcsim.config import ScenarioConfig
from lcsim.core import KEEP, LEFT, RIGHT, RUNNING, SUCCESS, LaneChangeCore
from lcsim.drivers import RuleBasedDriver
from lcsim.planning.perception import imagined_copy

_ORDER = (KEEP, LEFT, RIGHT)


@dataclass(slots=True)
class SearchResult:
    """What :func:`search_episode` found for one episode seed."""

    seed: int
    """The episode (simulator) seed."""
    winnable: bool | None
    """True: ``actions`` wins the episode. False: every branch of the merged tree ends in a collision or off
    the road. None: the search stopped at ``max_nodes`` first."""
    actions: list[int] = field(default_factory=list)
    """A winning sequence of decisions; when there is none, the branch that stayed alive longest."""
    ego_xy: list[tuple[float, float]] = field(default_factory=list)
    """The ego's (x, y) before each decision of ``actions`` (how :class:`OracleDriver` checks it is on the plan)."""
    nodes: int = 0
    """Decisions simulated."""
    deepest: int = 0
    """The furthest decision any branch reached alive."""
    outcomes: dict[str, int] = field(default_factory=dict)
    """How the pruned branches ended (collision, off_road, timeout), counted."""


def search_episode(config: ScenarioConfig, seed: int, *, memory_decisions: int = 8,
                   max_nodes: int = 200_000) -> SearchResult:
    """Search the decisions of the single episode ``seed`` for a winning sequence (see the module doc).

    Args:
        config: the scenario (rendering is switched off for the search; it does not affect the dynamics).
        seed: the episode seed (``LaneChangeCore.reset`` seed, as :func:`lcdata.record.episode_seed` gives).
        memory_decisions: decisions since the ego's last lane change after which that change is forgotten
            when merging states (>= 1; more merges less).
        max_nodes: stop undecided after simulating this many decisions.
    """
    if config.render_image:
        config = dataclasses.replace(config, render_image=False)
    root = LaneChangeCore(config, 1)
    root.reset([0], [int(seed)])
    return search_from(root, memory_decisions=memory_decisions, max_nodes=max_nodes)


def search_from(start: LaneChangeCore, *, memory_decisions: int = 8, max_nodes: int = 200_000) -> SearchResult:
    """:func:`search_episode` from the current state of a single-environment core, which is left untouched.

    The decisions found are counted from this state. A lane change already under way counts as just
    started when states are merged.
    """
    if not isinstance(memory_decisions, int) or memory_decisions < 1:
        raise ValueError(f"memory_decisions must be an int >= 1, got {memory_decisions!r}")
    if max_nodes < 1:
        raise ValueError(f"max_nodes must be >= 1, got {max_nodes!r}")
    if start.num_envs != 1:
        raise ValueError(f"the search runs on a single-environment core, got {start.num_envs} environments")
    rule = RuleBasedDriver()
    result = SearchResult(seed=int(start.seeds[0]), winnable=False)
    if start.outcome[0] != RUNNING:
        result.winnable = start.outcome[0] == SUCCESS
        return result
    root = imagined_copy(start)
    sim = root.sim
    changing = bool(sim.ego_lc_active[0])
    since0 = 0 if changing else memory_decisions
    dir0 = int(np.sign(sim.target_lane[0, 0] - sim.lane[0, 0])) if changing else 0
    # A node: (core at decision k, decisions since the ego's last change started, its direction, actions
    # still to try); stack[k] is at decision k, path[k] the action taken from it, xs[k] its ego (x, y).
    stack: list[tuple[LaneChangeCore, int, int, list[int]]] = [(root, since0, dir0, _candidates(root, rule))]
    path: list[int] = []
    xs = [_ego_xy(root, 0)]
    seen: set[tuple[int, int, int, int]] = set()
    while stack:
        core, since, direction, todo = stack[-1]
        k = len(stack) - 1
        if not todo:
            stack.pop()
            xs.pop()
            if path:
                path.pop()
            continue
        action = todo.pop(0)
        child = imagined_copy(core) if todo else core  # the last branch may take the parent itself
        changes = action != KEEP and not bool(child.sim.ego_lc_active[0])
        child.step(np.array([action]))
        result.nodes += 1
        outcome = str(child.outcome[0])
        if outcome == SUCCESS:
            result.winnable, result.deepest = True, k + 1
            result.actions, result.ego_xy = [*path, action], list(xs)
            return result
        if outcome != RUNNING:
            result.outcomes[outcome] = result.outcomes.get(outcome, 0) + 1
            continue
        if changes:
            since_c, dir_c = 0, 1 if action == LEFT else -1
        else:
            since_c = min(since + 1, memory_decisions)
            dir_c = direction if since_c < memory_decisions else 0
        key = (k + 1, int(child.sim.target_lane[0, 0]), since_c, dir_c)
        if key in seen:
            continue
        seen.add(key)
        if k + 1 > result.deepest:  # the longest-surviving branch so far
            result.deepest, result.actions, result.ego_xy = k + 1, [*path, action], list(xs)
        if result.nodes >= max_nodes:
            result.winnable = None
            return result
        stack.append((child, since_c, dir_c, _candidates(child, rule)))
        path.append(action)
        xs.append(_ego_xy(child, 0))
    return result


def _ego_xy(core: LaneChangeCore, env: int) -> tuple[float, float]:
    return float(core.sim.x[env, 0]), float(core.sim.y[env, 0])


def _candidates(core: LaneChangeCore, rule: RuleBasedDriver) -> list[int]:
    """The actions to try at this decision, the rule-based driver's first."""
    mask = core.action_mask()
    allowed = [a for a in _ORDER if mask[0, a]]
    first = int(rule({}, mask, core)[0])
    return [first, *(a for a in allowed if a != first)]


class OracleDriver:
    """Drives every episode along the decisions :func:`search_episode` finds for its seed.

    A privileged reference, not a policy: it plans each episode once, with the exact future, when it
    first sees it (``lc-eval oracle --bound`` reports the search's CPU time per episode), then plays the plan;
    where no winning plan exists it plays the branch that stayed alive longest, then the rule-based
    driver. It only drives episodes from
    their reset (it checks the ego is where the plan put it, and says so otherwise), which is how
    ``lc-eval`` and ``lc-record`` use a driver. Its recordings are demonstrations for ``--warm-start``.
    """

    name = "oracle"

    def __init__(self, *, memory_decisions: int = 8, max_nodes: int = 200_000) -> None:
        self.memory_decisions, self.max_nodes = memory_decisions, max_nodes
        self.rule = RuleBasedDriver()
        self.plans: dict[tuple[ScenarioConfig, int], SearchResult] = {}

    def plan(self, config: ScenarioConfig, seed: int) -> SearchResult:
        """The (cached) search result for episode ``seed`` of ``config``."""
        key = (config, int(seed))
        if key not in self.plans:
            self.plans[key] = search_episode(config, seed, memory_decisions=self.memory_decisions,
                                             max_nodes=self.max_nodes)
        return self.plans[key]

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        mask = np.asarray(action_mask, dtype=bool).reshape(-1, 3)
        actions = self.rule(obs, mask, core)
        per = core.config.steps_per_decision
        for i in np.flatnonzero(core.outcome == RUNNING):
            plan = self.plan(core.config, int(core.seeds[i]))
            k, rest = divmod(int(core.sim.step[i]), per)
            if k >= len(plan.actions):
                continue
            if rest or _ego_xy(core, i) != plan.ego_xy[k]:
                raise RuntimeError(f"environment {i} (seed {int(core.seeds[i])}) is not where the oracle's plan put "
                                   "its ego at this decision; the oracle drives episodes from their reset only")
            actions[i] = plan.actions[k]
        return actions


def replay(config: ScenarioConfig, seed: int, actions: list[int]) -> str:
    """The outcome of driving ``actions`` from a fresh reset of episode ``seed`` ("" if it is still running)."""
    core = LaneChangeCore(config, 1)
    core.reset([0], [int(seed)])
    for action in actions:
        if core.outcome[0] != RUNNING:
            break
        core.step(np.array([action]))
    return str(core.outcome[0])


__all__ = ["OracleDriver", "SearchResult", "replay", "search_episode", "search_from"]
