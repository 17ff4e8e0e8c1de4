"""``predictor``: the trajectory predictor trained on the corpus; ``analytic-predictor/<base>``: an analytic base
(:data:`lcmodels.experiment.recipe.PREDICTOR_SOURCES`) a recipe names with ``predictor = "<base>"``, with the
horizons and network of the trained one and nothing to train (a folder of its own: never inside the trained one's,
which a fresh start of that stage empties)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.kinds.base import ANALYTIC_STAGE, GraphBuilder, Stage, StageKind, predictor_key
from lcmodels.experiment.stages import StageContext, StageJob
from lcmodels.presets import Preset, StageResult


@dataclasses.dataclass(frozen=True)
class Predictor(StageKind):
    name = "predictor"
    group = "data"

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        """The trained predictor, after the corpus."""
        corpus = StageKey.of("corpus")
        graph.add(Stage(StageKey.of(cls.name), (("corpus", corpus),), graph.priority("data", 1), cls(), group="data"))

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        return _trained_job(ctx, stage.key, got["corpus"])


@dataclasses.dataclass(frozen=True)
class AnalyticPredictor(StageKind):
    name = ANALYTIC_STAGE
    group = "data"

    @classmethod
    def add(cls, graph: GraphBuilder) -> None:
        """Each analytic base a recipe names, in recipe order: nothing to read, nothing to train."""
        bases = list(dict.fromkeys(r.predictor for r in graph.recipes if r.predictor != "learned"))
        for i, base in enumerate(bases, 1):
            graph.add(Stage(predictor_key(base), priority=graph.priority("data", 1, i), kind=cls(),
                            group="data"))  # fmt: skip

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        return _analytic_job(ctx, stage.key)


def predictor_config(preset: Preset, threads: int) -> Any:
    """The :class:`lcmodels.predictor.TrainConfig` of ``preset``'s predictor stage."""
    from lcmodels.predictor import PredictorConfig, TrainConfig

    p = preset
    return TrainConfig(
        model=PredictorConfig(d_model=p.predictor_d_model, num_heads=p.predictor_heads,
                              num_layers=p.predictor_layers, ff_dim=p.predictor_ff_dim),
        stride=p.predictor_stride, max_epochs=p.predictor_epochs, time_limit_s=p.predictor_time_limit_s,
        max_train_windows=p.predictor_max_train_windows, num_threads=threads, progress=False,
        tensorboard=p.predictor_tensorboard,
    )  # fmt: skip


def _trained_job(ctx: StageContext, key: StageKey, corpus: StageResult) -> StageJob:
    tc = predictor_config(ctx.preset, ctx.threads)
    path = key.path(ctx.out)

    def work(keep: bool, save_wall: Callable[[], None]) -> None:
        from lcdata.corpus import load_tracks
        from lcmodels.predictor import train_predictor

        m = train_predictor(load_tracks(corpus.path), tc, path)
        ctx.emit(f"[{key}] test ADE {m['model']['ade']:.4f} m FDE {m['model']['fde']:.4f} m "
                 f"(constant velocity {m['constant_velocity']['ade']:.4f} / "
                 f"{m['constant_velocity']['fde']:.4f})")  # fmt: skip

    cfg = {k: v for k, v in dataclasses.asdict(tc).items() if k not in ("progress", "num_threads")}
    return StageJob(cfg, {"corpus": corpus.digest}, lambda: ["predictor.pt", "metrics.json"], work,
                    upgrade=stored_predictor_config)


def _analytic_job(ctx: StageContext, key: StageKey) -> StageJob:
    """``predictor.pt`` of the analytic base ``key.part`` (:func:`lcmodels.predictor.analytic_model`) with the
    horizons and network of the preset's trained predictor: nothing to train, a policy reads it as it reads that."""
    model = dataclasses.replace(predictor_config(ctx.preset, ctx.threads).model, base=key.part)
    path = key.path(ctx.out)

    def work(keep: bool, save_wall: Callable[[], None]) -> None:
        from lcmodels.predictor import analytic_model, save_model

        save_model(analytic_model(model), path / "predictor.pt", extra={"analytic": key.part})

    return StageJob({"analytic": key.part, "model": dataclasses.asdict(model)}, {}, lambda: ["predictor.pt"], work)


def stored_predictor_config(data: dict[str, Any]) -> dict[str, Any]:
    """A predictor stage's recorded config in today's form: a model field added since reads as a checkpoint
    without it does (:meth:`lcmodels.predictor.PredictorConfig.from_dict`), so the model it trained is the same."""
    from lcmodels.predictor import PredictorConfig

    model = data.get("model")
    if not isinstance(model, dict):
        return data
    try:
        return data | {"model": dataclasses.asdict(PredictorConfig.from_dict(model))}
    except (TypeError, ValueError):
        return data
