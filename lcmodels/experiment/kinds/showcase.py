"""``showcase``: ``showcase_episodes`` test episodes of the zoo policy with the best test success recorded (MCAP)
in ``DIR/showcase``, and the first as a Rerun file ``DIR/showcase/<episode>.rrd`` (``lc-view`` opens either)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

from lckit.fileio import remove_file
from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds.base import GraphBuilder, Stage, StageKind
from lcmodels.experiment.kinds.zoo import Zoo
from lcmodels.experiment.stages import StageContext, StageJob
from lcmodels.fileio import read_json
from lcmodels.presets import StageResult
from lcmodels.zoo import ZooEntry


@dataclasses.dataclass(frozen=True)
class Showcase(StageKind):
    name = "showcase"
    group = "zoo"

    entries: tuple[ZooEntry, ...] = ()
    """The candidates: the entry of every zoo stage."""

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        """After every zoo stage, when the preset evaluates the zoo and records a showcase."""
        if graph.preset.zoo and graph.zoo and graph.preset.showcase_episodes >= 1:
            evals = tuple((f"zoo:{e.name}", StageKey.of(Zoo.name, e.name)) for e in graph.zoo)
            graph.add(Stage(StageKey.of(cls.name), evals, graph.priority("zoo", 2), cls(tuple(graph.zoo)), group="zoo"))

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        path = stage.key.path(ctx.out)
        p = ctx.preset
        best_success, best = -1.0, None
        for entry in self.entries:
            res = got[f"zoo:{entry.name}"]
            success = float((read_json(res.path / "metrics.json") or {}).get("test", {}).get("success_rate", -1.0))
            if success > best_success:
                best, best_success = (entry, res), success
        assert best is not None
        entry, evaluated = best

        def work(keep: bool, save_wall: Callable[[], None]) -> None:
            from lcdata.viewer.app import convert
            from lcmodels.policy.evaluate import driver_for, evaluate

            for old in path.glob("*"):
                remove_file(old, ctx.out)
            driver, config = driver_for(str(entry.policy), predictor=str(entry.predictor) if entry.predictor else None)
            evaluate(driver, config, episodes=p.showcase_episodes, seed=p.test_seed, out_dir=path,
                     scenario=f"zoo-{entry.name}", overwrite=True)  # fmt: skip
            first = sorted(path.glob("*.mcap"))[0]
            convert([first], first.with_suffix(".rrd"))
            ctx.emit(f"[{stage.key}] {p.showcase_episodes} episodes of zoo:{entry.name} in {path}; open one with "
                     f"lc-view {first.with_suffix('.rrd')}")  # fmt: skip

        def outputs() -> list[str]:
            return sorted(q.name for q in path.glob("*") if q.suffix in (".mcap", ".rrd"))

        cfg = {"zoo": entry.name, "episodes": p.showcase_episodes, "seed": p.test_seed}
        return StageJob(cfg, {"policy": entry.sha256, "eval": evaluated.digest}, outputs, work)
