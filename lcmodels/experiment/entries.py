"""An experiment's final policies as zoo entries: the card of what an ``lc-experiment`` directory measured for a
recipe (its figures, its safety layer's, the command and commit that trained it), and its publication in the zoo
(:mod:`lcmodels.zoo`, which knows nothing of experiments)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.recipe import load_recipe
from lcmodels.experiment.store import read_record
from lcmodels.fileio import read_json
from lcmodels.presets import INVOCATIONS, StageResult, previous_policy
from lcmodels.zoo import ZooEntry, publish_entry, weights_sha256


def final_policy(run: str | os.PathLike[str], recipe_name: str, seed: int) -> Path:
    """The policy file the last training stage of ``recipe_name`` (training seed ``seed``) of the
    ``lc-experiment`` directory ``run`` ended with; ``ValueError`` when it is missing."""
    recipe = load_recipe(recipe_name)
    key = StageKey(recipe.name, seed, recipe.final_stage)
    rec = read_record(run, key) or {}
    policy = previous_policy(StageResult(key.name, "skipped", key.path(run), 0.0, outputs=rec.get("outputs", {})))
    if not policy.is_file():
        raise ValueError(f"{policy} does not exist: finish the experiment first")
    return policy


def experiment_card(run: str | os.PathLike[str], recipe_name: str, *, seed: int = 0,
                    commit: str = "") -> tuple[dict[str, Any], Path, bool]:
    """What the ``lc-experiment`` directory ``run`` measured for ``recipe_name`` (training seed ``seed``; ``commit``:
    the code's, where the invocation that trained it did not record its own): the
    card of its final policy (recipe, commit, training time, validation figures and the experiment's held-out
    ones (``heldout``: its *test* split, validation episodes in the benchmark's sense), the safety layer's when
    run, the experiment's command; the sealed test figures come from the ledger, ``tools/publish_ledger.py``), the policy file, and whether it reads predictions. ``ValueError``
    when the recipe's evaluation or its policy is missing."""
    run = Path(run)
    recipe = load_recipe(recipe_name)
    evaluation = StageKey(recipe.name, seed, "eval").path(run)
    ev = read_json(evaluation / "metrics.json")
    if not ev or "test" not in ev:
        raise ValueError(f"{evaluation} holds no evaluation: finish the experiment first")
    policy = final_policy(run, recipe_name, seed)
    walls = [float((read_record(run, StageKey(recipe.name, seed, st)) or {}).get("wall_s", 0.0)) for st in recipe.stages]
    meta = read_json(policy.parent / "policy.card.json") or {}
    needs = str(meta.get("obs_mode", "")) in ("prediction", "hybrid")
    experiment = read_json(run / "experiment.json") or {}

    def figures(summary: dict[str, Any]) -> dict[str, Any]:
        keep = ("episodes", "eval_seed", "success_rate", "success_rate_ci95", "collision_rate", "collision_rate_ci95",
                "timeout_rate", "mean_return", "planner_overrides", "planner_choices")
        return {k: summary[k] for k in keep if k in summary}

    safety = read_json(StageKey(recipe.name, seed, "safety").path(run) / "metrics.json")
    follow = None
    if safety and "test" in safety and recipe.safety is not None and recipe.safety.follow:
        # the policy the layer's imagined futures followed: the zoo must ship the same one for the figure to hold
        follow = {"recipe": recipe.safety.follow, "training_seed": seed,
                  "weights_sha256": weights_sha256(final_policy(run, recipe.safety.follow, seed))}
    card = {
        "recipe": recipe.name, "recipe_version": recipe.version, "row": recipe.row, "kind": recipe.kind,
        "description": recipe.description, "training_seed": seed, "commit": commit,
        "training_wall_s": round(sum(walls), 1), "stages_wall_s": dict(zip(recipe.stages, walls, strict=True)),
        "heldout": figures(ev["test"]), "validation": {k: figures(v) for k, v in ev.get("val", {}).items()},
        "safety_layer": ({"heldout": figures(safety["test"]), "config": safety.get("config", {})}
                         | ({"follow": follow} if follow else {}) if safety and "test" in safety else None),
        "experiment_command": experiment.get("command", ""), "preset": (experiment.get("preset") or {}).get("name"),
    }  # fmt: skip
    made = _invocation_of(run, StageKey(recipe.name, seed, recipe.stages[-1]))
    if made is not None:  # a directory several commands filled: the one that trained this recipe's policy
        card["experiment_command"] = made.get("command", card["experiment_command"])
        if made.get("commit"):
            card["commit"] = made["commit"] + ("+changes" if made.get("dirty") else "")
    return card, policy, needs


def _invocation_of(run: Path, key: Any) -> dict[str, Any] | None:
    """The entry of ``run``'s ``invocations.json`` that computed stage ``key`` (the last one started before the
    stage finished), None when either record is missing."""

    finished = (read_record(run, key) or {}).get("finished")
    entries = read_json(run / INVOCATIONS)
    if not isinstance(finished, str) or not isinstance(entries, list):
        return None
    before = [e for e in entries if isinstance(e, dict) and isinstance(e.get("started"), str)
              and e["started"] <= finished]  # fmt: skip (ISO times of one clock: they sort as strings)
    return before[-1] if before else None


def publish_from_experiment(run: str | os.PathLike[str], recipe_name: str, *, seed: int = 0, name: str | None = None,
                            root: str | os.PathLike[str] | None = None, commit: str = "",
                            overwrite: bool = False) -> ZooEntry:  # fmt: skip
    """Publish the final policy of ``recipe_name`` (training seed ``seed``) of the ``lc-experiment`` directory
    ``run`` as zoo entry ``name`` (default: the recipe's name), with a card of its recipe, commit, training
    time, validation and test figures (and the safety layer's, when run), the experiment's command
    (:func:`experiment_card`), and the outcomes of :data:`~lcmodels.policy.evaluate.CHECK_EPISODES` test episodes re-run now."""
    from lcmodels.policy.evaluate import check_episodes  # (torch: loaded only to publish)

    card, policy, needs = experiment_card(run, recipe_name, seed=seed, commit=commit)
    test_seed = int(card["heldout"].get("eval_seed", 0))
    card["check"] = {"eval_seed": test_seed, "episodes": check_episodes(policy, seed=test_seed)}
    return publish_entry(policy, name or card["recipe"], predictor=Path(run) / "predictor" / "predictor.pt" if needs
                         else None, card=card, root=root, overwrite=overwrite)  # fmt: skip


__all__ = ["experiment_card", "final_policy", "publish_from_experiment"]
