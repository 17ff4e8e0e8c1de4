"""What the stages that train a policy with :mod:`lcmodels.policy.train` share (``clone``, ``train``,
``shielded``): the stage's PolicyConfig from its recipe, and its run directory as the stage's work."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

from lckit.fileio import make_folder, remove_tree
from lcmodels.experiment.kinds.base import Stage, StageKind
from lcmodels.experiment.stages import StageContext, StageJob
from lcmodels.fileio import POLICY_FILE
from lcmodels.policy.config import PolicyConfig
from lcmodels.policy.names import needs_predictor
from lcmodels.presets import StageResult, previous_policy


def resumable_policy_change(prior: dict[str, Any], now: dict[str, Any]) -> bool:
    """A policy run can continue under ``now``: only evaluation settings or a larger budget differ."""
    free = ("timesteps", "checkpoint_every", "eval_episodes", "eval_seed", "eval_batch", "record_eval")
    if any(prior.get(k) != now.get(k) for k in now if k not in free):
        return False
    timesteps = prior.get("timesteps", 0)
    return isinstance(timesteps, int) and timesteps <= int(now["timesteps"])


def stored_stage_config(data: dict[str, Any]) -> dict[str, Any]:
    """A policy stage's recorded config in today's form (:func:`lcmodels.policy.train.stored_config`), the
    shielded stage's ``shield`` table kept as it is."""
    from lcmodels.policy.train import stored_config

    if "shield" not in data:
        return stored_config(data)
    return stored_config({k: v for k, v in data.items() if k != "shield"}) | {"shield": data["shield"]}


@dataclasses.dataclass(frozen=True)
class PolicyStage(StageKind):
    """A recipe's stage that trains a policy: an ``lcmodels.policy.train`` run directory. ``got``: ``predictor``
    (when the policy reads predictions), ``demos`` (a clone), ``previous`` (the recipe's stage before) and what
    :meth:`layer` reads."""

    trains = True
    in_recipe = True
    online: ClassVar[bool] = True
    """It takes online RL steps from the previous stage's policy (else none: ``timesteps`` 0)."""
    warm_starts: ClassVar[bool] = False
    """It learns from the recipe's demonstrations (behaviour cloning)."""

    @classmethod
    def settings(cls, recipe: Any) -> dict[str, Any]:
        """``[policy]``, then the stage's own table."""
        return {**recipe.policy, **recipe.table(cls.name)}

    @classmethod
    def policy_config(cls, recipe: Any, *, scenario: str, seed: int, warm_start: str = "", init_policy: str = "",
                      eval_episodes: int = 200, eval_seed: int = 0, record_eval: bool = False,
                      caps: dict[str, int] | None = None) -> PolicyConfig:  # fmt: skip
        """The stage's :class:`~lcmodels.policy.config.PolicyConfig`: its settings; for a stage that trains online,
        the fields whose default follows the algorithm filled by :meth:`PolicyConfig.of
        <lcmodels.policy.config.PolicyConfig.of>` (fine-tuning when it starts from a previous stage's policy);
        then ``caps``, which lower integer fields to at most the given values (the tiny and quick presets'
        budgets; ``n_envs`` never below one environment a training road)."""
        settings = cls.settings(recipe)
        assert settings is not None
        if not cls.online:
            settings["timesteps"] = 0
        data = {**settings, "seed": seed, "scenario": scenario, "warm_start": warm_start if cls.warm_starts else "",
                "init_policy": init_policy if cls.online else "", "eval_episodes": eval_episodes,
                "eval_seed": eval_seed, "record_eval": record_eval}  # fmt: skip
        if cls.online:
            cfg = PolicyConfig.of(data, fine_tune=bool(init_policy))
        else:  # no online steps: the rate and rollout length go unused, left as stored
            cfg = PolicyConfig.from_dict(data, stored=False)
        lowered = {key: cap for key, cap in (caps or {}).items() if isinstance(current := getattr(cfg, key, None), int)
                   and not isinstance(current, bool) and current > cap}  # fmt: skip
        if "n_envs" in lowered:  # never below one environment a training road
            lowered["n_envs"] = max(lowered["n_envs"], len(cfg.road_names()))
        return dataclasses.replace(cfg, **lowered) if lowered else cfg

    def layer(self, recipe: Any, got: Mapping[str, StageResult]) -> tuple[Any, dict[str, Any]]:
        """The safety layer the stage trains behind (a :class:`lcsim.planning.SafetyLayerConfig` whose imagined
        futures follow a policy file; None: none) and its settings as the stage records them."""
        return None, {}

    def job(self, ctx: StageContext, stage: Stage, got: Mapping[str, StageResult]) -> StageJob:
        key = stage.key
        recipe = stage.recipe
        seed = key.seed
        assert seed is not None
        predictor, previous = got.get("predictor"), got.get("previous")
        demos = got.get("demos") if self.warm_starts else None
        path = key.path(ctx.out)
        init = str(previous_policy(previous)) if previous is not None and self.online else ""
        cfg = self.policy_config(recipe, scenario=ctx.preset.scenario, seed=seed,
                                 warm_start=str(demos.path.resolve()) if demos is not None else "",
                                 init_policy=init, eval_episodes=0, caps=ctx.preset.cap_dict)  # fmt: skip
        inputs: dict[str, str] = {}
        pred_path = None
        if needs_predictor(cfg.obs):
            assert predictor is not None
            inputs["predictor"] = predictor.digest
            pred_path = predictor.path / "predictor.pt"
        if cfg.warm_start:
            assert demos is not None
            inputs["demos"] = demos.digest
        if cfg.init_policy:
            assert previous is not None
            inputs["init_policy"] = previous.digest
        layer, shield_cfg = self.layer(recipe, got)
        if layer is not None:
            inputs["follow"] = got["follow"].digest
        shown = [0]

        def show(row: dict[str, Any]) -> None:
            t = int(row["timesteps"])  # about 8 lines per run, whatever the algorithm's log interval
            if t < cfg.timesteps and t - shown[0] < cfg.timesteps / 8:
                return
            shown[0] = t
            ctx.emit(f"[{key}] step {t}/{cfg.timesteps} success {row['success_rate']:.2f} "
                     f"collision {row['collision_rate']:.2f} return {row['mean_return']:.1f}")

        def work(keep: bool, save_wall: Callable[[], None]) -> float:
            from lcmodels.policy.plan import resolve
            from lcmodels.policy.train import train_run

            plan = resolve(cfg, predictor=pred_path, layer=layer, penalty=float(shield_cfg.get("penalty", 0.0)))
            try:
                res = train_run(plan, path, progress=show)
            except ValueError as exc:  # the directory holds another run (e.g. moved --out): start over
                if "another configuration" not in str(exc):
                    raise
                remove_tree(path, ctx.out)
                make_folder(path, ctx.out)
                res = train_run(plan, path, progress=show)
            return res.wall_s

        stage_cfg = cfg.to_dict() | {"warm_start": "demos" if cfg.warm_start else "",
                                     "init_policy": "previous" if cfg.init_policy else ""}  # fmt: skip
        if shield_cfg:
            stage_cfg["shield"] = shield_cfg
        outputs = [POLICY_FILE, "metrics.json"] + (["progress.csv"] if cfg.timesteps > 0 else [])
        return StageJob(stage_cfg, inputs, lambda: outputs, work, resumable=resumable_policy_change,
                        upgrade=stored_stage_config)  # fmt: skip
