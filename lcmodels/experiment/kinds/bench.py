"""``bench``: lc-bench's table of every run the preset's suite measured (the ``suite`` stages), grouped by recipe
(its runs: the training seeds, first listed first), with the paired tests and figures: ``BENCH.md``,
``bench.json``."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds.base import GraphBuilder, Stage, StageKind
from lcmodels.experiment.kinds.suite import REFERENCES, Suite
from lcmodels.experiment.stages import StageContext, StageJob
from lcmodels.fileio import read_json, write_json
from lcmodels.presets import StageResult


@dataclasses.dataclass(frozen=True)
class Bench(StageKind):
    name = "bench"
    group = "references"

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        """After each road's ceiling and floor and every run on the suite, when the preset names one."""
        if not graph.preset.suite:
            return
        ceiling, floor = (StageKey.of(Suite.name, who) for who in REFERENCES)
        runs = [StageKey(r.name, seed, Suite.name) for r, seed in graph.runs()]
        graph.add(Stage(StageKey.of(cls.name), (("ceiling", ceiling), ("floor", floor), *((f"run:{k}", k) for k in runs)),
                        graph.priority("references", 3), cls(), group="references"))  # fmt: skip

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        p = ctx.preset
        path = stage.key.path(ctx.out)
        # the runs by recipe in the preset's order (the first recipe is the paired tests' reference), seed by seed
        keys = [StageKey.parse(role.removeprefix("run:")) for role in got if role.startswith("run:")]
        order = list(dict.fromkeys(k.recipe for k in keys))
        runs = [f"run:{k}" for k in sorted(keys, key=lambda k: (order.index(k.recipe), k.seed))]

        def work(keep: bool, save_wall: Callable[[], None]) -> None:
            from lckit.fileio import write_file
            from lcmodels.bench.figures import figures_markdown, write_figures
            from lcmodels.bench.table import CEILING, FLOOR, suite_markdown, suite_summary
            from lcsim.suite import suite

            cells: dict[tuple[str, str], dict[str, Any]] = {}
            drivers = []
            for role, as_label in (("ceiling", CEILING), ("floor", FLOOR), *((r, None) for r in runs)):
                data = read_json(got[role].path / "suite.json") or {}
                label = as_label or str(data.get("label"))
                for sc, rec in (data.get("cells") or {}).items():
                    cells[(label, sc)] = rec
                if as_label is None:
                    drivers.append((label, str(data.get("group"))))
            seeds = {f"{k.recipe}/seed{k.seed}": k.seed for k in keys}  # the paired tests pair seed with seed
            summary = suite_summary(cells, drivers, suite(p.suite), suite=p.suite,
                                    split=f"validation seed {p.suite_seed}", pair_keys=seeds)  # fmt: skip
            summary["command"] = "lc-experiment --preset " + p.name
            write_figures(summary, path, root=ctx.out)
            write_json(path / "bench.json", summary)
            write_file(path / "BENCH.md", suite_markdown(summary, summary["command"], figures=figures_markdown()),
                       root=ctx.out)  # fmt: skip

        cfg = {"suite": p.suite, "episodes": p.suite_episodes, "seed": p.suite_seed, "runs": [r[4:] for r in runs]}
        inputs = {role: got[role].digest for role in got}
        return StageJob(cfg, inputs, lambda: ["BENCH.md", "bench.json"], work)
