"""The stage graph of an experiment, built whole before anything runs: every stage of the preset and its recipes,
each naming the stages it reads.

::

    corpus ──► predictor ──────────────────────────────► every stage whose policy reads predictions
               predictor/<base> (analytic: no training) ──► the stages of a recipe with predictor = <base>
    demos/<key> ──► <recipe>/seed<k>/clone ──► dagger ──► train ──► shielded ──► eval
                                                                        └──────► safety
    <followed recipe>/seed<k>/<its final stage> ───────► shielded, safety, a dagger stage the layer labels
    <recipe>/seed<k>/<final> ──► suite ─┐   suite/oracle, suite/rule ──► bench (the preset's suite: lc-bench's
                                        └────────────────────────────►  table and figures of every run)
    rule, oracle    zoo/<entry>, zoo-safety/<entry>    zoo/* ──► showcase

A recipe's ``shielded`` and ``safety`` stages read the final stage of the recipe its safety layer follows (same
training seed), and so does a ``dagger`` stage whose expert is that policy behind the layer (when it comes first,
it starts from that policy). Recipes whose layers follow each other in a loop are refused in one line (:class:`GraphCycle`), as
are stages that would wait on each other. Plans, dry runs and the stages the report reads are queries of the
graph.
"""

from __future__ import annotations

import heapq
from collections.abc import Container, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.layer import follows, has_layer
from lcmodels.presets import ORACLE_KEY, RULE_KEY, Preset, demos_key
from lcmodels.recipe import DemoSpec, Recipe

GROUPS = ("data", "recipes", "references", "zoo")
"""The groups of stages, in the order a runner prefers them when several are ready: the corpus, predictor and
demonstrations; the recipes' stages; the rule-based driver and the oracle (after the recipes: the oracle's search
is slower than some training runs); the zoo."""
TRAINING_STAGES = ("clone", "dagger", "train", "shielded")


class GraphCycle(ValueError):
    """Recipes whose safety layers follow each other in a loop, or stages that wait on each other."""


@dataclass(frozen=True)
class Stage:
    """One stage: its key, the stages it reads by role, and what it is made from."""

    key: StageKey
    needs: tuple[tuple[str, StageKey], ...] = ()
    """``(role, key)`` of each stage it reads: ``corpus``, ``predictor``, ``demos``, ``previous`` (the recipe's
    stage before), ``follow`` (the final stage of the recipe the safety layer follows), ``policy`` (the stage whose
    policy is evaluated), ``zoo:<entry>`` (the showcase's candidates)."""
    group: str = "recipes"
    priority: tuple[int, ...] = ()
    """Among ready stages the runner starts the smallest first."""
    recipe: Recipe | None = None
    demos: DemoSpec | None = None
    zoo: Any = None
    """The :class:`lcmodels.zoo.ZooEntry` of a ``zoo`` or ``zoo-safety`` stage; the showcase's candidates."""
    follow_zoo: Any = None
    """The zoo entry a ``zoo-safety`` stage's layer follows (None: the policy itself)."""

    @property
    def trains(self) -> bool:
        """A training stage (clone, dagger, train, shielded): one process of its own when stages run at once."""
        return self.key.recipe is not None and self.key.stage in TRAINING_STAGES


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
        f = follows(r)
        if f and f not in {x.name for x in out}:
            out.append(load(f))
    return out


def check_follows(recipes: Sequence[Recipe]) -> None:
    """:class:`GraphCycle` when the recipes' safety layers follow each other in a loop (a layer may follow its
    own recipe): the followed policies of a loop would have no first one to train."""
    graph = {r.name: f for r in recipes if (f := follows(r)) and f != r.name}
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
            f = follows(r)
            if f in n and n[f] < n[r.name]:
                n[f], changed = n[r.name], True
    return n


def recipe_ranks(recipes: Sequence[Recipe]) -> dict[str, int]:
    """The order in which the runner prefers the recipes' stages: the policies a safety layer follows first,
    then the recipes whose layer follows them (a chain by its depth), then the rest. A followed policy is then
    trained by the time the recipe that follows it reaches its shielded and safety stages."""
    graph = {r.name: f for r in recipes if (f := follows(r))}

    def depth(name: str) -> int:
        chain = [name]
        while (nxt := graph.get(chain[-1])) and nxt not in chain:
            chain.append(nxt)
        return len(chain) - 1

    involved = set(graph) | set(graph.values())
    last = 1 + max((depth(n) for n in involved if n in {r.name for r in recipes}), default=0)
    return {r.name: depth(r.name) if r.name in involved or has_layer(r) else last for r in recipes}


def build_graph(preset: Preset, recipes: Sequence[Recipe], seeds: Mapping[str, int],
                zoo: Sequence[Any] = ()) -> StageGraph:  # fmt: skip
    """The stages of ``preset`` with ``recipes`` (capped, every followed recipe among them), ``seeds`` training
    seeds each, and the ``zoo`` entries to evaluate (with ``preset.zoo``). :class:`GraphCycle` for a cycle."""
    from lcmodels.policy.obs import needs_predictor

    check_follows(recipes)
    stages: dict[StageKey, Stage] = {}

    def add(st: Stage) -> StageKey:
        stages[st.key] = st
        return st.key

    def prio(group: str, *rest: int) -> tuple[int, ...]:
        return (GROUPS.index(group), *rest)

    corpus = add(Stage(StageKey.of("corpus"), group="data", priority=prio("data", 0)))
    predictor = add(Stage(StageKey.of("predictor"), (("corpus", corpus),), "data", prio("data", 1)))
    bases: dict[str, StageKey] = {}

    def predictor_of(r: Recipe) -> StageKey:
        """The predictor stage a recipe's prediction input reads: the trained one, or an analytic base's."""
        if r.predictor == "learned":
            return predictor
        if r.predictor not in bases:
            bases[r.predictor] = add(Stage(StageKey.of("predictor", r.predictor), group="data",
                                           priority=prio("data", 1, len(bases) + 1)))  # fmt: skip
        return bases[r.predictor]

    demos: dict[str, StageKey] = {}
    for r in recipes:
        if "clone" in r.stages and (k := demos_key(r.demos)) not in demos:
            demos[k] = add(Stage(StageKey.of("demos", k), group="data", priority=prio("data", 2, len(demos)),
                                 demos=r.demos))  # fmt: skip
    rank = recipe_ranks(recipes)
    suite_runs: list[StageKey] = []
    names = {r.name for r in recipes}
    for r in recipes:
        if (f := follows(r)) and f not in names:
            raise ValueError(f"recipe {r.name!r}: its safety layer follows {f!r}, which the experiment does not run")
    for seed in range(max(seeds.values(), default=0)):
        for i, r in enumerate(recipes):
            if seed >= seeds[r.name]:
                continue
            pred = (("predictor", predictor_of(r)),) if needs_predictor(r.obs) else ()
            f = follows(r)
            follow = (("follow", StageKey(f, seed, _final(recipes, f))),) if f else ()
            previous: tuple[tuple[str, StageKey], ...] = ()
            for j, st in enumerate(r.stages):
                needs = list(pred)
                if st == "clone" or (st == "dagger" and "clone" in r.stages):
                    needs.append(("demos", demos[demos_key(r.demos)]))
                needs += previous
                if st == "shielded" or (st == "dagger" and r.dagger.expert == "safety-layer"):
                    needs += follow  # the layer's follower: the policy behind it (and a first dagger's student)
                key = add(Stage(StageKey(r.name, seed, st), tuple(needs), "recipes", prio("recipes", rank[r.name], seed, i, j),
                                recipe=r))  # fmt: skip
                previous = (("previous", key),)
            final = (("policy", previous[0][1]),)
            n = len(r.stages)
            add(Stage(StageKey(r.name, seed, "eval"), (*pred, *final), "recipes",
                      prio("recipes", rank[r.name], seed, i, n), recipe=r))  # fmt: skip
            if has_layer(r):
                add(Stage(StageKey(r.name, seed, "safety"), (*pred, *final, *follow), "recipes",
                          prio("recipes", rank[r.name], seed, i, n + 1), recipe=r))  # fmt: skip
            if preset.suite:
                suite_runs.append(add(Stage(StageKey(r.name, seed, "suite"), (*pred, *final), "recipes",
                                            prio("recipes", rank[r.name], seed, i, n + 2), recipe=r)))  # fmt: skip
    if preset.suite:  # every final policy on the suite's roads, next to each road's ceiling and floor
        ends = [add(Stage(StageKey.of("suite", who), group="references", priority=prio("references", 2, j)))
                for j, who in enumerate((ORACLE_KEY, RULE_KEY))]
        add(Stage(StageKey.of("bench"), (("ceiling", ends[0]), ("floor", ends[1]),
                                         *((f"run:{k}", k) for k in suite_runs)),
                  group="references", priority=prio("references", 3)))  # fmt: skip
    add(Stage(StageKey.of(RULE_KEY), group="references", priority=prio("references", 0)))
    if preset.oracle:
        add(Stage(StageKey.of(ORACLE_KEY), group="references", priority=prio("references", 1)))
    if preset.zoo:
        _zoo_stages(add, prio, zoo, preset.showcase_episodes)
    return StageGraph(stages, list(recipes), dict(seeds))


def _final(recipes: Sequence[Recipe], name: str) -> str:
    return next(r.final_stage for r in recipes if r.name == name)


def _zoo_stages(add: Any, prio: Any, entries: Sequence[Any], showcase_episodes: int) -> None:
    """Every zoo entry on the test episodes, and behind its safety layer where its card has one and the zoo holds
    the policy it follows; then the showcase of the best one."""
    from lcmodels.experiment.layer import card_lookahead
    from lcmodels.recipe import load_recipe

    by_name = {e.name: e for e in entries}
    evals = []
    for i, entry in enumerate(entries):
        evals.append((f"zoo:{entry.name}", add(Stage(StageKey.of("zoo", entry.name), group="zoo",
                                                     priority=prio("zoo", 0, i), zoo=entry))))  # fmt: skip
    for i, entry in enumerate(entries):
        if card_lookahead(entry.card) is None:
            continue
        try:
            recipe = load_recipe(str(entry.card.get("recipe", "")))
        except ValueError:
            continue
        f = follows(recipe)
        if not has_layer(recipe) or (f and f not in by_name):
            continue
        add(Stage(StageKey.of("zoo-safety", entry.name), group="zoo", priority=prio("zoo", 1, i), zoo=entry,
                  follow_zoo=by_name[f] if f else None))  # fmt: skip
    if evals and showcase_episodes >= 1:
        add(Stage(StageKey.of("showcase"), tuple(evals), "zoo", prio("zoo", 2), zoo=tuple(entries)))
