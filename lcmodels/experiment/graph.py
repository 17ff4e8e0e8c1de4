"""The stage graph of an experiment, built whole before anything runs: every stage of the preset and its recipes,
each naming the stages it reads.

::

    corpus ──► predictor ──────────────────────────────► every stage whose policy reads predictions
    analytic-predictor/<base> (no training) ──► the stages of a recipe with predictor = <base>
    demos/<key> ──► <recipe>/seed<k>/clone ──► dagger ──► train ──► shielded ──► eval
                                                                        └──────► safety
    <followed recipe>/seed<k>/<its final stage> ───────► shielded, safety, a dagger stage the layer labels
    <recipe>/seed<k>/<final> ──► suite ─┐   suite/oracle, suite/rule ──► bench (the preset's suite: lc-bench's
                                        └────────────────────────────►  table and figures of every run)
    rule, oracle    zoo/<entry>, zoo-safety/<entry>    zoo/* ──► showcase

A recipe's ``shielded`` and ``safety`` stages read the final stage of the recipe its safety layer follows (same
training seed), and so does a ``dagger`` stage whose expert is that policy behind the layer (when it comes first,
it starts from that policy). Each kind of stage (:mod:`lcmodels.experiment.kinds`) adds its own stages and says
what each reads. Recipes whose layers follow each other in a loop are refused in one line (:class:`GraphCycle`),
as are stages that would wait on each other. Plans, dry runs and the stages the report reads are queries of the
graph.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Container, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds import KINDS, GraphBuilder, Stage
from lcmodels.experiment.recipe import Recipe, load_recipe
from lcmodels.presets import Preset


class GraphCycle(ValueError):
    """Recipes whose safety layers follow each other in a loop, or stages that wait on each other."""


@dataclass
class StageGraph:
    """The stages in a topological order (the runner's preferred one), and queries of them."""

    stages: dict[StageKey, Stage]
    recipes: list[Recipe] = field(default_factory=list)
    seeds: dict[str, int] = field(default_factory=dict)
    """Training seeds of each recipe."""

    def __post_init__(self) -> None:
        for st in self.stages.values():
            for _, k in st.needs:
                if k not in self.stages:
                    raise ValueError(f"stage {st.key} needs {k}, which the experiment does not have")
        self._dependents: dict[StageKey, list[StageKey]] = {k: [] for k in self.stages}
        for st in self.stages.values():
            for k in self.needed(st.key):
                self._dependents[k].append(st.key)
        self.stages = {k: self.stages[k] for k in self._topological()}

    # -- queries -----------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[Stage]:
        return iter(self.stages.values())

    def __len__(self) -> int:
        return len(self.stages)

    def __contains__(self, key: object) -> bool:
        return key in self.stages

    def __getitem__(self, key: StageKey) -> Stage:
        return self.stages[key]

    def keys(self) -> list[StageKey]:
        """Every stage, in topological order (the order a runner with one process does them)."""
        return list(self.stages)

    def needed(self, key: StageKey) -> list[StageKey]:
        """The stages ``key`` reads (each once)."""
        return list(dict.fromkeys(k for _, k in self.stages[key].needs))

    def dependents(self, key: StageKey) -> list[StageKey]:
        """The stages that read ``key``."""
        return list(self._dependents[key])

    def upstream(self, key: StageKey) -> set[StageKey]:
        """Every stage ``key`` waits for, directly or not."""
        seen: set[StageKey] = set()
        todo = self.needed(key)
        while todo:
            k = todo.pop()
            if k not in seen:
                seen.add(k)
                todo += self.needed(k)
        return seen

    def ready(self, finished: Container[StageKey], started: Container[StageKey] = ()) -> list[StageKey]:
        """The stages not ``started`` nor ``finished`` whose needs are all ``finished``, best first."""
        out = [k for k, st in self.stages.items() if k not in finished and k not in started
               and all(n in finished for _, n in st.needs)]  # fmt: skip
        return sorted(out, key=lambda k: self.stages[k].priority)

    def finals(self) -> list[StageKey]:
        """The final training stage of every recipe and training seed (whose policies the tables and the ledger
        speak of), recipe by recipe."""
        return [StageKey(r.name, s, r.final_stage) for r in self.recipes for s in range(self.seeds.get(r.name, 0))
                if StageKey(r.name, s, r.final_stage) in self.stages]  # fmt: skip

    # -- order -------------------------------------------------------------------------------------
    def _topological(self) -> list[StageKey]:
        """Kahn's order, the ready stage of smallest priority first; :class:`GraphCycle` naming one cycle."""
        waiting = {k: len(self.needed(k)) for k in self.stages}
        index = {k: i for i, k in enumerate(self.stages)}
        heap = [(self.stages[k].priority, index[k], k) for k, n in waiting.items() if n == 0]
        heapq.heapify(heap)
        order: list[StageKey] = []
        while heap:
            _, _, k = heapq.heappop(heap)
            order.append(k)
            for d in self._dependents[k]:
                waiting[d] -= 1
                if waiting[d] == 0:
                    heapq.heappush(heap, (self.stages[d].priority, index[d], d))
        if len(order) < len(self.stages):
            left = [k for k in self.stages if waiting[k] > 0]
            cycle = " -> ".join(map(str, _a_cycle(self, left)))
            raise GraphCycle(f"the stages wait on each other in a cycle, {cycle} (each waits for the final policy of "
                             "the recipe its safety layer follows: safety.follow)")
        return order


def _a_cycle(graph: StageGraph, left: Sequence[StageKey]) -> list[StageKey]:
    """One cycle among the stages ``left`` (which hold at least one), first stage repeated at the end."""
    among = set(left)
    path: list[StageKey] = [left[0]]
    seen = {left[0]: 0}
    while True:
        nxt = next(k for k in graph.needed(path[-1]) if k in among)  # every stage left waits on one left
        if nxt in seen:
            cycle = path[seen[nxt] :]
            return [*cycle, cycle[0]]  # each waits for the next
        seen[nxt] = len(path)
        path.append(nxt)


# ------------------------------------------------------------------------------------------------- recipes
def follow_closure(recipes: Sequence[Recipe], load: Any) -> list[Recipe]:
    """``recipes`` and every recipe a safety layer follows that they leave out (``load(name)`` reads one), a
    follower's own follower too."""
    out = list(recipes)
    for r in out:  # grows as it goes
        f = r.follows
        if f and f not in {x.name for x in out}:
            out.append(load(f))
    return out


def check_follows(recipes: Sequence[Recipe]) -> None:
    """:class:`GraphCycle` when the recipes' safety layers follow each other in a loop (a layer may follow its
    own recipe): the followed policies of a loop would have no first one to train."""
    graph = {r.name: f for r in recipes if (f := r.follows) and f != r.name}
    for name in graph:
        chain = [name]
        while (nxt := graph.get(chain[-1])) and nxt not in chain:
            chain.append(nxt)
        if nxt == name:
            raise GraphCycle(f"the safety layers' followers form a loop: {' -> '.join([*chain, name])} (safety.follow)")


def recipe_seeds(recipes: Sequence[Recipe], seeds: int, asked: Mapping[str, int]) -> dict[str, int]:
    """Training seeds of each recipe: ``seeds``, or more where ``asked`` says, and a followed recipe as many as
    the recipes whose safety layers follow it (same seed, same follower)."""
    n = {r.name: max(seeds, asked.get(r.name, 1)) for r in recipes}
    changed = True
    while changed:  # a fixed point: a chain of followers passes its count down (loops included)
        changed = False
        for r in recipes:
            f = r.follows
            if f in n and n[f] < n[r.name]:
                n[f], changed = n[r.name], True
    return n


def recipe_ranks(recipes: Sequence[Recipe]) -> dict[str, int]:
    """The order in which the runner prefers the recipes' stages: the policies a safety layer follows first,
    then the recipes whose layer follows them (a chain by its depth), then the rest. A followed policy is then
    trained by the time the recipe that follows it reaches its shielded and safety stages."""
    graph = {r.name: f for r in recipes if (f := r.follows)}

    def depth(name: str) -> int:
        chain = [name]
        while (nxt := graph.get(chain[-1])) and nxt not in chain:
            chain.append(nxt)
        return len(chain) - 1

    involved = set(graph) | set(graph.values())
    last = 1 + max((depth(n) for n in involved if n in {r.name for r in recipes}), default=0)
    return {r.name: depth(r.name) if r.name in involved or r.safety is not None else last for r in recipes}


def build_graph(preset: Preset, recipes: Sequence[Recipe], seeds: Mapping[str, int], zoo: Sequence[Any] = (),
                load: Callable[[str], Recipe] = load_recipe) -> StageGraph:  # fmt: skip
    """The stages of ``preset`` with ``recipes`` (capped, every followed recipe among them), ``seeds`` training
    seeds each, and the ``zoo`` entries to evaluate (with ``preset.zoo``; ``load`` reads the recipe a zoo card
    names): each kind of stage (:data:`lcmodels.experiment.kinds.KINDS`) adds its own. :class:`GraphCycle` for a
    cycle."""
    check_follows(recipes)
    names = {r.name for r in recipes}
    for r in recipes:
        if (f := r.follows) and f not in names:
            raise ValueError(f"recipe {r.name!r}: its safety layer follows {f!r}, which the experiment does not run")
    builder = GraphBuilder(preset, list(recipes), dict(seeds), recipe_ranks(recipes), KINDS, zoo, load)
    for kind in KINDS:
        kind.add(builder)
    return StageGraph(builder.stages, list(recipes), dict(seeds))
