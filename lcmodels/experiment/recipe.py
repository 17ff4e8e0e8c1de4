"""Recipes: how a policy of a table row is made, as data.

A recipe is a TOML file (``lcmodels/recipes/<name>.toml``, or any path) naming its stages in order and the
settings of each; ``lc-experiment`` runs it stage by stage, resumably, with the preset's scenario,
evaluation and budget caps::

    name = "hybrid-ppo"            # the file's stem
    version = 1                    # raised when a change alters what the recipe reaches
    row = "ppo-hybrid"             # the table row it fills (lcmodels.presets.ROWS)
    kind = "best"                  # paper (faithful to the paper), best (the project's best), demo, ablation
    order = 1                      # its place among the recipes of its kind (presets, tables)
    optional = false               # true: a preset of its kind runs it only when named (--recipe)
    stages = ["clone", "train"]    # in order, from the training stages: clone, dagger, train, shielded

    [policy]                       # PolicyConfig fields of every stage (not seed, scenario, paths, evaluation)
    algo = "ppo"
    obs = "hybrid"
    window_features = true

    [demos]                        # the demonstrations a clone learns from (recorded once per experiment)
    driver = "oracle"
    episodes = 400

    [clone]                        # behaviour cloning: PolicyConfig fields for this stage
    warm_start_epochs = 20

    [dagger]                       # DAgger rounds from the clone
    rounds = 6
    expert = "oracle"              # or "safety-layer": the followed recipe's policy behind the [safety] layer
    correction_weight = 1.0        # weight of a state whose label differs from the policy's own decision
    balance_actions = true         # rare actions' states count more (1/sqrt of their frequency)

    [train]                        # online RL, from the previous stage's policy when there is one
    timesteps = 1200000
    learning_rate = 3e-5
    freeze_image = true

    [shielded]                     # fine-tuning behind the safety layer (needs [safety] and a stage before it)
    timesteps = 150000             # more PPO steps with the [train] settings; the layer executes each decision
    penalty = 100.0                # raw reward per proposal not executed as proposed (a collision: 500)

    [safety]                       # optional: also evaluate the final policy behind the safety layer
    follow = "pure-ppo"            # the recipe whose policy the imagined futures follow
    horizon_decisions = 32
    samples = 3                    # redrawn futures per candidate decision

A dagger stage whose expert is ``"safety-layer"`` distils a layer into a network: the final policy of the recipe
``safety.follow`` names (same training seed), behind the ``[safety]`` layer, labels the states the student reaches.
Such a stage may come first (``stages = ["dagger"]``): the student is then that policy itself, and no
demonstrations join the labels.

Each stage kind (:mod:`lcmodels.experiment.kinds`) says which table is its own and what it refuses in a recipe.
The presets' lists of recipes are the recipes' ``kind``, ``optional`` and ``order``
(:func:`lcmodels.presets.listed_recipes`). The stage tables override ``[policy]`` for their stage (a ``shielded`` stage trains with ``[train]``'s); the
``[safety]`` table is a :class:`lcsim.planning.SafetyLayerConfig` (blind and perceived unless it says otherwise;
its older key ``horizon`` is read too). ``--set policy.learning_rate=1e-4`` (or ``train.timesteps=...``,
``demos.episodes=...``, ``safety.samples=...``) overrides a value on the command line. The fields whose default
follows the algorithm (``learning_rate``, ``n_steps``) are filled by :meth:`PolicyConfig.of
<lcmodels.policy.config.PolicyConfig.of>` where the recipe leaves them out. Whatever a recipe reached is recorded next to it (``<name>.reached.json``) by ``tools/publish_zoo.py``.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lckit.config import parse_value, read_data_file
from lcmodels.experiment.kinds import KIND, KINDS, TRAINING_STAGES, PolicyStage
from lcmodels.policy.config import PolicyConfig
from lcmodels.policy.names import needs_predictor
from lcmodels.presets import RECIPES_DIR, ROWS
from lcsim.planning.safety import SafetyLayerConfig

RECIPE_KINDS: tuple[str, ...] = ("paper", "best", "demo", "ablation")
EXPERIMENT_FIELDS: tuple[str, ...] = ("seed", "scenario", "warm_start", "init_policy", "eval_episodes", "eval_seed",
                                      "record_eval")  # fmt: skip
"""PolicyConfig fields the experiment sets (the training seed, the preset's scenario and evaluation, the paths
of the previous stages): a recipe that sets one is refused."""
PREDICTOR_SOURCES: tuple[str, ...] = ("learned", "lane-aware")
"""What may fill a recipe's prediction input (:attr:`Recipe.predictor`)."""
TABLES: dict[str, type] = {k.name: k.table for k in KINDS if k.table is not None}
"""The stage kinds' own tables of a recipe, by name, and the type of each (``dict``: PolicyConfig fields)."""
SPECS: dict[str, type] = {**{n: t for n, t in TABLES.items() if t is not dict}, "safety": SafetyLayerConfig}
"""The tables that are a spec (typed fields, bounded budgets), the recipe's safety layer last."""
_NAME = re.compile(r"^[a-z0-9][a-z0-9-]*$")
_POLICY_FIELDS = {f.name: str(f.type) for f in dataclasses.fields(PolicyConfig)}


def _check_table(table: dict[str, Any], where: str) -> None:
    for key, value in table.items():
        if key not in _POLICY_FIELDS:
            raise ValueError(f"{where}: unknown PolicyConfig field {key!r}")
        if key in EXPERIMENT_FIELDS:
            raise ValueError(f"{where}: {key!r} is set by the experiment, not by a recipe")
        if isinstance(value, dict | list):
            raise ValueError(f"{where}.{key}: expected a single value, got {value!r}")


def _check_spec(name: str, spec: Any) -> None:
    """Each field of the spec table ``name`` of its type, counts >= 1 (a seed >= 0), within the spec's ``LIMITS``."""
    for f in dataclasses.fields(spec):
        v = getattr(spec, f.name)
        want = {"int": int, "str": str, "bool": bool, "float": (int, float)}[str(f.type)]
        if not isinstance(v, want) or (want is not bool and isinstance(v, bool)):
            raise ValueError(f"{name}.{f.name} must be of type {f.type}, got {v!r}")
        if want is int and v < (0 if f.name == "seed" else 1):
            raise ValueError(f"{name}.{f.name} must be >= {0 if f.name == 'seed' else 1}, got {v!r}")
        hi = type(spec).LIMITS.get(f.name)
        if want is not str and want is not bool and hi is not None and v > hi:
            raise ValueError(f"{name}.{f.name} must be at most {hi:,}, got {v!r}")


@dataclass(frozen=True, slots=True, kw_only=True)
class Recipe:
    name: str
    version: int = 1
    row: str
    kind: str = "best"
    optional: bool = False
    """A preset of its kind runs it only when named (``--recipe``): a research route, or one that costs hours."""
    order: int = 0
    """Its place among the recipes of its kind in the presets and tables (smaller first, then by name)."""
    label: str = ""
    """What the report calls it (default: the row's label)."""
    description: str = ""
    stages: tuple[str, ...] = ("train",)
    policy: dict[str, Any] = field(default_factory=dict)
    tables: dict[str, Any] = field(default_factory=dict)
    """The stage kinds' own tables (:data:`TABLES`) by name: ``clone`` and ``train`` PolicyConfig fields over
    ``[policy]`` for their stage, ``demos``, ``dagger`` and ``shielded`` their specs (a default one where the file
    has none)."""
    safety: SafetyLayerConfig | None = None
    """The safety layer its final policy is also evaluated behind (and a ``shielded`` stage trains behind)."""
    predictor: str = "learned"
    """What fills the prediction input of a mode that reads it: ``learned`` (the experiment's trained predictor) or
    an analytic base (:data:`PREDICTOR_SOURCES`: ``lane-aware``, the extrapolation along the road the learned model
    corrects, with no correction)."""

    def __post_init__(self) -> None:
        where = f"recipe {self.name!r}"
        if not isinstance(self.name, str) or not _NAME.match(self.name):
            raise ValueError(f"recipe name must be lower-case letters, digits and '-', got {self.name!r}")
        if self.row not in ROWS:
            raise ValueError(f"{where}: row must be one of {', '.join(ROWS)}, got {self.row!r}")
        if self.kind not in RECIPE_KINDS:
            raise ValueError(f"{where}: kind must be one of {', '.join(RECIPE_KINDS)}, got {self.kind!r}")
        for name in ("version", "order"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < (1 if name == "version" else 0):
                raise ValueError(f"{where}: {name} must be an integer >= {1 if name == 'version' else 0}, got {v!r}")
        if not isinstance(self.optional, bool):
            raise ValueError(f"{where}: optional must be true or false, got {self.optional!r}")
        stages = tuple(self.stages)
        if not stages or any(s not in TRAINING_STAGES for s in stages) or list(stages) != sorted(
                set(stages), key=TRAINING_STAGES.index):
            raise ValueError(f"{where}: stages must be some of {', '.join(TRAINING_STAGES)}, each once and in that "
                             f"order, got {list(self.stages)!r}")  # fmt: skip
        object.__setattr__(self, "stages", stages)
        if not isinstance(self.tables, dict) or set(self.tables) - set(TABLES):
            raise ValueError(f"{where}: tables must be some of {', '.join(TABLES)}, got {self.tables!r}")
        object.__setattr__(self, "tables", {n: self.tables.get(n, t()) for n, t in TABLES.items()})
        if self.predictor not in PREDICTOR_SOURCES:
            raise ValueError(f"{where}: predictor must be one of {', '.join(PREDICTOR_SOURCES)}, got {self.predictor!r}")
        if self.predictor != "learned" and not needs_predictor(self.obs):
            raise ValueError(f"{where}: predictor = {self.predictor!r} needs an observation mode with predictions "
                             f"(prediction, hybrid), not {self.obs!r}")
        for name in ("policy", *(n for n, t in TABLES.items() if t is dict)):
            table = self.policy if name == "policy" else self.tables[name]
            if not isinstance(table, dict):
                raise ValueError(f"{where}: [{name}] must be a table, got {table!r}")
            _check_table(table, f"{where} [{name}]")
        try:
            for name in SPECS:
                if (spec := self.spec(name)) is not None:
                    _check_spec(name, spec)
            for kind in KINDS:
                kind.check(self)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        if self.safety is not None and not self.safety.blind:
            raise ValueError(f"{where}: safety.blind must be true: a recipe's safety layer is one a car could have (the "
                             "privileged layer, blind = false, is an upper reference for lc-eval)")  # fmt: skip
        if self.safety is not None and self.safety.follow and not _NAME.match(self.safety.follow):
            raise ValueError(f"{where}: safety.follow must name a recipe, got {self.safety.follow!r}")
        for stage in stages:  # each training stage's PolicyConfig, paths stood in for
            if KIND[stage].settings(self) is None:
                continue
            try:
                self.policy_config(stage, scenario="paper", seed=0, warm_start="demos",
                                   init_policy="previous.safetensors" if stage != stages[0] else "")  # fmt: skip
            except ValueError as exc:
                raise ValueError(f"{where}, stage {stage}: {exc}") from None

    @property
    def final_stage(self) -> str:
        return self.stages[-1]

    @property
    def obs(self) -> str:
        """The observation mode of the recipe's policy (PolicyConfig's default when the recipe sets none)."""
        return str(self.stage_settings(self.final_stage).get("obs", PolicyConfig().obs))

    @property
    def follows(self) -> str | None:
        """The recipe whose final policy (same training seed) the safety layer's imagined futures follow; None when
        the recipe has no layer or its layer follows the policy itself."""
        return self.safety.follow or None if self.safety is not None else None

    def table(self, name: str) -> Any:
        """The table of stage kind ``name`` (:data:`TABLES`): its spec, or the PolicyConfig fields of its stage."""
        return self.tables[name]

    def spec(self, name: str) -> Any:
        """The spec table ``name`` (:data:`SPECS`; ``safety``: the layer, None when the recipe has none)."""
        return self.safety if name == "safety" else self.tables[name]

    def stage_settings(self, stage: str) -> dict[str, Any]:
        """The PolicyConfig fields this recipe gives stage ``stage`` (``[policy]`` then the stage's table; a
        ``shielded`` stage: ``[train]``'s with its own ``timesteps``; a ``dagger`` stage, which trains no config of
        its own: ``[policy]``'s)."""
        settings = KIND[stage].settings(self)
        return dict(self.policy) if settings is None else settings

    def policy_config(self, stage: str, **given: Any) -> PolicyConfig:
        """The :class:`~lcmodels.policy.config.PolicyConfig` of training stage ``stage`` (``clone``, ``train``,
        ``shielded``), with the experiment's fields ``given``: :meth:`PolicyStage.policy_config
        <lcmodels.experiment.kinds.policy.PolicyStage.policy_config>`."""
        kind = KIND.get(stage)
        if not (isinstance(kind, type) and issubclass(kind, PolicyStage)):
            raise ValueError(f"recipe {self.name!r}: a {stage} stage trains no PolicyConfig of its own")
        return kind.policy_config(self, **given)

    def capped(self, caps: dict[str, int] | None) -> Recipe:
        """This recipe with its spec tables' budgets (demonstrations, DAgger, safety layer) lowered to ``caps``
        (policy fields are capped by :meth:`policy_config`)."""
        if not caps:
            return self
        changes: dict[str, Any] = {}
        for name in SPECS:
            spec = self.spec(name)
            if spec is None:
                continue
            lowered = {f.name: min(getattr(spec, f.name), caps[f.name]) for f in dataclasses.fields(spec)
                       if f.name in caps and f.name != "seed" and isinstance(getattr(spec, f.name), int)
                       and not isinstance(getattr(spec, f.name), bool)}  # fmt: skip
            if lowered:
                changes[name] = dataclasses.replace(spec, **lowered)
        safety = changes.pop("safety", self.safety)
        if not changes and safety is self.safety:
            return self
        return dataclasses.replace(self, tables={**self.tables, **changes}, safety=safety)

    # -- files ----------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "version": self.version, "row": self.row, "kind": self.kind}
        if self.optional:  # said only when not the default, as the files say it
            out["optional"] = True
        if self.order:
            out["order"] = self.order
        out |= {"label": self.label, "description": self.description, "stages": list(self.stages),
                "policy": dict(self.policy)}  # fmt: skip
        if self.predictor != "learned":  # said only when not the default: the older records' identities stay
            out["predictor"] = self.predictor
        for name, t in TABLES.items():
            out[name] = dict(self.tables[name]) if t is dict else dataclasses.asdict(self.tables[name])
        if self.safety is not None:
            out["safety"] = dataclasses.asdict(self.safety)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "recipe") -> Recipe:
        if not isinstance(data, dict):
            raise ValueError(f"{where}: expected a table")
        known = ({f.name for f in dataclasses.fields(cls)} - {"tables"}) | set(TABLES)
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {unknown} (keys: {', '.join(sorted(known))})")
        if "name" not in data or "row" not in data:
            raise ValueError(f"{where}: needs 'name' and 'row'")
        kwargs = {k: v for k, v in data.items() if k not in TABLES}
        tables: dict[str, Any] = {}
        for name, table_cls in SPECS.items():
            if name not in data:
                continue
            table = data[name]
            if not isinstance(table, dict):
                raise ValueError(f"{where}: [{name}] must be a table")
            if table_cls is SafetyLayerConfig:
                kwargs[name] = SafetyLayerConfig.from_table(table, where=f"{where}: [safety]")
                continue
            names = {f.name for f in dataclasses.fields(table_cls)}
            bad = sorted(set(table) - names)
            if bad:
                raise ValueError(f"{where}: [{name}] has no key(s) {bad} (keys: {', '.join(sorted(names))})")
            tables[name] = table_cls(**table)
        tables |= {name: data[name] for name, t in TABLES.items() if t is dict and name in data}
        if "stages" in kwargs:
            if not isinstance(kwargs["stages"], list | tuple):
                raise ValueError(f"{where}: stages must be a list, got {kwargs['stages']!r}")
            kwargs["stages"] = tuple(kwargs["stages"])
        for key in ("name", "label", "description", "row", "kind", "predictor"):
            if key in kwargs and not isinstance(kwargs[key], str):
                raise ValueError(f"{where}: {key} must be a string, got {kwargs[key]!r}")
        try:
            return cls(**kwargs, tables=tables)
        except (ValueError, TypeError) as exc:  # TypeError: a value no check expected (a table in a list)
            msg = str(exc)  # "recipe 'NAME'..." from the checks: name the file instead
            msg = re.sub(r"^recipe '[^']*'", where, msg) if msg.startswith("recipe '") else f"{where}: {msg}"
            raise ValueError(msg) from None

    def to_toml(self) -> str:
        from lckit.config import toml_text

        return toml_text(self.to_dict())

    def with_settings(self, settings: Sequence[str]) -> Recipe:
        """This recipe with ``TABLE.KEY=VALUE`` settings (``policy.learning_rate=1e-4``, ``train.timesteps=300000``,
        ``demos.episodes=100``, ``safety.horizon_decisions=32``); values read as the field's type. ``ValueError`` naming
        the setting for an unknown table or key or a bad value."""
        if not settings:
            return self
        data = self.to_dict()
        safety: list[str] = []
        for text in settings:
            key, sep, value = text.partition("=")
            table, dot, name = key.strip().partition(".")
            if not sep or not dot or not name:
                raise ValueError(f"--set {text!r}: expected TABLE.KEY=VALUE (policy.learning_rate=1e-4)")
            value = value.strip()
            if table == "policy" or TABLES.get(table) is dict:
                if name not in _POLICY_FIELDS:
                    raise ValueError(f"--set {text}: PolicyConfig has no field {name!r}")
                data[table][name] = parse_value(value, None, f"--set {text}", _POLICY_FIELDS[name])
            elif table == "safety":  # applied together below (settings that must agree change at once)
                safety.append(text)
            elif table in SPECS:
                spec_cls = SPECS[table]
                spec = self.spec(table)
                names = {f.name: str(f.type) for f in dataclasses.fields(spec_cls)}
                if name not in names:
                    raise ValueError(f"--set {text}: [{table}] has no key {name!r} (keys: {', '.join(sorted(names))})")
                data.setdefault(table, dataclasses.asdict(spec))[name] = parse_value(
                    value, getattr(spec, name), f"--set {text}", names[name])
            else:
                raise ValueError(f"--set {text}: no table {table!r} (tables: policy, {', '.join(TABLES)}, safety)")
        if safety:
            data["safety"] = (self.safety or SafetyLayerConfig()).with_named_settings(safety).to_dict()
        return Recipe.from_dict(data, where=f"recipe {self.name!r} with --set {', '.join(settings)}")


def recipe_names() -> list[str]:
    """The recipes that come with the package."""
    return sorted(p.stem for p in RECIPES_DIR.glob("*.toml"))


def recipe_path(name_or_path: str | os.PathLike[str]) -> Path:
    text = os.fspath(name_or_path)
    if Path(text).suffix in (".toml", ".json"):
        return Path(text)
    path = RECIPES_DIR / f"{text}.toml"
    if not path.is_file():
        raise ValueError(f"unknown recipe {text!r}; choose one of {', '.join(recipe_names())} or a .toml file")
    return path


def load_recipe(name_or_path: str | os.PathLike[str]) -> Recipe:
    """A packaged recipe by name, or a recipe file. ``ValueError`` in one line naming the file and problem."""
    path = recipe_path(name_or_path)
    data = read_data_file(path, "recipe")
    recipe = Recipe.from_dict(data, where=f"recipe {path}")
    if recipe.name != path.stem:
        raise ValueError(f"recipe {path}: name {recipe.name!r} differs from the file's name {path.stem!r}")
    return recipe


__all__ = [
    "EXPERIMENT_FIELDS",
    "PREDICTOR_SOURCES",
    "RECIPES_DIR",
    "RECIPE_KINDS",
    "SPECS",
    "TABLES",
    "Recipe",
    "load_recipe",
    "recipe_names",
    "recipe_path",
]
