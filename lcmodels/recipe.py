"""Recipes: how a policy of a table row is made, as data.

A recipe is a TOML file (``lcmodels/recipes/<name>.toml``, or any path) naming its stages in order and the
settings of each; ``lc-experiment`` runs it stage by stage, resumably, with the preset's scenario,
evaluation and budget caps::

    name = "hybrid-ppo"            # the file's stem
    version = 1                    # raised when a change alters what the recipe reaches
    row = "ppo-hybrid"             # the table row it fills (lcmodels.presets.ROWS)
    kind = "best"                  # paper (faithful to the paper), best (the project's best), demo, ablation
    stages = ["clone", "train"]    # in order, from: clone, dagger, train, shielded

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

The stage tables override ``[policy]`` for their stage (a ``shielded`` stage trains with ``[train]``'s); the
``[safety]`` table is a :class:`lcsim.planning.SafetyLayerConfig` (blind and perceived unless it says otherwise;
its older key ``horizon`` is read too). ``--set policy.learning_rate=1e-4`` (or ``train.timesteps=...``,
``demos.episodes=...``, ``safety.samples=...``) overrides a value on the command line. The fields whose default
follows the algorithm (``learning_rate``, ``n_steps``) are filled by :meth:`PolicyConfig.of
<lcmodels.policy.config.PolicyConfig.of>` where the recipe leaves them out. Whatever a recipe reached is recorded next to it (``<name>.reached.json``) by ``tools/publish_zoo.py``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from lckit.config import parse_value, read_data_file
from lcsim.planning.safety import SafetyLayerConfig

RECIPES_DIR = Path(__file__).parent / "recipes"
STAGE_KINDS: tuple[str, ...] = ("clone", "dagger", "train", "shielded")
RECIPE_KINDS: tuple[str, ...] = ("paper", "best", "demo", "ablation")
EXPERIMENT_FIELDS: tuple[str, ...] = ("seed", "scenario", "warm_start", "init_policy", "eval_episodes", "eval_seed",
                                      "record_eval")  # fmt: skip
"""PolicyConfig fields the experiment sets (the training seed, the preset's scenario and evaluation, the paths
of the previous stages): a recipe that sets one is refused."""
_NAME = re.compile(r"^[a-z0-9][a-z0-9-]*$")


def _policy_fields() -> dict[str, str]:
    from lcmodels.policy.config import PolicyConfig

    return {f.name: str(f.type) for f in dataclasses.fields(PolicyConfig)}


def _check_table(table: dict[str, Any], where: str) -> None:
    fields = _policy_fields()
    for key, value in table.items():
        if key not in fields:
            raise ValueError(f"{where}: unknown PolicyConfig field {key!r}")
        if key in EXPERIMENT_FIELDS:
            raise ValueError(f"{where}: {key!r} is set by the experiment, not by a recipe")
        if isinstance(value, dict | list):
            raise ValueError(f"{where}.{key}: expected a single value, got {value!r}")


@dataclass(frozen=True, slots=True, kw_only=True)
class DemoSpec:
    LIMITS: ClassVar[dict[str, int]] = {"episodes": 100_000, "seed": 100_000_000}

    driver: str = "oracle"
    """Who drives the demonstrations (an lcsim driver name)."""
    episodes: int = 400
    seed: int = 5000
    """First user seed (the demonstrations' seeds are kept apart from training's and evaluation's)."""


DAGGER_EXPERTS: tuple[str, ...] = ("oracle", "safety-layer")
"""Who labels a recipe's DAgger states: the oracle (sees the future), or the final policy of the recipe the
``[safety]`` layer follows, behind that layer."""


@dataclass(frozen=True, slots=True, kw_only=True)
class DaggerSpec:
    LIMITS: ClassVar[dict[str, float]] = {"rounds": 1_000, "episodes": 100_000, "epochs": 10_000, "seed": 100_000_000,
                                          "correction_weight": 1_000.0}  # fmt: skip

    rounds: int = 2
    episodes: int = 100
    """Episodes the policy drives per round."""
    epochs: int = 10
    seed: int = 100_000
    expert: str = "oracle"
    """One of :data:`DAGGER_EXPERTS`."""
    labels: str = "plan"
    correction_weight: float = 1.0
    """Training weight of a labelled state whose label differs from the student's own decision there, against 1
    (:func:`lcmodels.policy.dagger.dagger`)."""
    balance_actions: bool = True
    """Weight each state by the inverse square root of its label's frequency, as cloning does; False: alike."""


@dataclass(frozen=True, slots=True, kw_only=True)
class ShieldedSpec:
    LIMITS: ClassVar[dict[str, float]] = {"timesteps": 1_000_000_000, "penalty": 1_000_000.0}

    timesteps: int = 150_000
    """PPO steps behind the safety layer, from the previous stage's policy with the ``[train]`` settings."""
    penalty: float = 100.0
    """Raw reward taken per proposal not executed as proposed (:mod:`lcmodels.policy.shield`; a collision costs
    500)."""


PREDICTOR_SOURCES: tuple[str, ...] = ("learned", "lane-aware")
"""What may fill a recipe's prediction input (:attr:`Recipe.predictor`)."""

_SPECS: dict[str, type] = {"demos": DemoSpec, "dagger": DaggerSpec, "shielded": ShieldedSpec, "safety": SafetyLayerConfig}
_STAGE_TABLES = ("clone", "train")


@dataclass(frozen=True, slots=True, kw_only=True)
class Recipe:
    name: str
    version: int = 1
    row: str
    kind: str = "best"
    label: str = ""
    """What the report calls it (default: the row's label)."""
    description: str = ""
    stages: tuple[str, ...] = ("train",)
    policy: dict[str, Any] = field(default_factory=dict)
    clone: dict[str, Any] = field(default_factory=dict)
    train: dict[str, Any] = field(default_factory=dict)
    demos: DemoSpec = DemoSpec()
    dagger: DaggerSpec = DaggerSpec()
    shielded: ShieldedSpec = ShieldedSpec()
    safety: SafetyLayerConfig | None = None
    """The safety layer its final policy is also evaluated behind (and a ``shielded`` stage trains behind)."""
    predictor: str = "learned"
    """What fills the prediction input of a mode that reads it: ``learned`` (the experiment's trained predictor) or
    an analytic base (:data:`PREDICTOR_SOURCES`: ``lane-aware``, the extrapolation along the road the learned model
    corrects, with no correction)."""

    def __post_init__(self) -> None:
        from lcmodels.presets import ROWS

        where = f"recipe {self.name!r}"
        if not isinstance(self.name, str) or not _NAME.match(self.name):
            raise ValueError(f"recipe name must be lower-case letters, digits and '-', got {self.name!r}")
        if self.row not in ROWS:
            raise ValueError(f"{where}: row must be one of {', '.join(ROWS)}, got {self.row!r}")
        if self.kind not in RECIPE_KINDS:
            raise ValueError(f"{where}: kind must be one of {', '.join(RECIPE_KINDS)}, got {self.kind!r}")
        if not isinstance(self.version, int) or isinstance(self.version, bool) or self.version < 1:
            raise ValueError(f"{where}: version must be an integer >= 1, got {self.version!r}")
        stages = tuple(self.stages)
        if not stages or any(s not in STAGE_KINDS for s in stages) or list(stages) != sorted(
                set(stages), key=STAGE_KINDS.index):
            raise ValueError(f"{where}: stages must be some of {', '.join(STAGE_KINDS)}, each once and in that "
                             f"order, got {list(self.stages)!r}")  # fmt: skip
        from lcmodels.policy.names import needs_predictor

        if self.predictor not in PREDICTOR_SOURCES:
            raise ValueError(f"{where}: predictor must be one of {', '.join(PREDICTOR_SOURCES)}, got {self.predictor!r}")
        if self.predictor != "learned" and not needs_predictor(self.obs):
            raise ValueError(f"{where}: predictor = {self.predictor!r} needs an observation mode with predictions "
                             f"(prediction, hybrid), not {self.obs!r}")
        if self.dagger.expert not in DAGGER_EXPERTS:
            raise ValueError(f"{where}: dagger.expert must be one of {', '.join(DAGGER_EXPERTS)}, "
                             f"got {self.dagger.expert!r}")  # fmt: skip
        distils = self.dagger.expert == "safety-layer"
        if "dagger" in stages and distils and (self.safety is None or not self.safety.follow
                                               or self.safety.follow == self.name):
            raise ValueError(f"{where}: dagger.expert = \"safety-layer\" needs a [safety] table naming the recipe "
                             "whose policy is the expert behind it (safety.follow, another recipe)")
        if "dagger" in stages and "clone" not in stages and not distils:
            raise ValueError(f"{where}: a dagger stage needs a clone stage before it (or the safety layer as its "
                             "expert, starting from the policy it follows)")
        if "shielded" in stages and (stages[0] == "shielded" or self.safety is None or not self.safety.follow):
            raise ValueError(f"{where}: a shielded stage needs a stage before it and a [safety] table naming the "
                             "recipe its imagined futures follow (safety.follow)")
        for name in ("policy", *_STAGE_TABLES):
            table = getattr(self, name)
            if not isinstance(table, dict):
                raise ValueError(f"{where}: [{name}] must be a table, got {table!r}")
            _check_table(table, f"{where} [{name}]")
        for name, cls in _SPECS.items():
            spec = getattr(self, name)
            if spec is not None:
                for f in dataclasses.fields(cls):
                    v = getattr(spec, f.name)
                    want = {"int": int, "str": str, "bool": bool, "float": (int, float)}[str(f.type)]
                    if not isinstance(v, want) or (want is not bool and isinstance(v, bool)):
                        raise ValueError(f"{where}: {name}.{f.name} must be of type {f.type}, got {v!r}")
                    if want is int and v < (0 if f.name == "seed" else 1):
                        raise ValueError(f"{where}: {name}.{f.name} must be >= {0 if f.name == 'seed' else 1}, "
                                         f"got {v!r}")
                    hi = cls.LIMITS.get(f.name)
                    if want is not str and want is not bool and hi is not None and v > hi:
                        raise ValueError(f"{where}: {name}.{f.name} must be at most {hi:,}, got {v!r}")
        if not (math.isfinite(self.dagger.correction_weight) and self.dagger.correction_weight > 0):
            raise ValueError(f"{where}: dagger.correction_weight must be > 0, got {self.dagger.correction_weight!r}")
        if not math.isfinite(self.shielded.penalty) or self.shielded.penalty < 0:
            raise ValueError(f"{where}: shielded.penalty must be >= 0, got {self.shielded.penalty!r}")
        if "shielded" in stages and self.safety is not None and self.safety.follow == self.name:
            raise ValueError(f"{where}: a shielded stage's safety layer cannot follow the recipe itself "
                             "(safety.follow)")
        from lcsim.registry import DRIVER_NAMES

        if "clone" in stages and self.demos.driver not in DRIVER_NAMES:
            raise ValueError(f"{where}: demos.driver must be one of {', '.join(DRIVER_NAMES)}, "
                             f"got {self.demos.driver!r}")  # fmt: skip
        if self.dagger.labels not in ("plan", "winning"):
            raise ValueError(f"{where}: dagger.labels must be plan or winning, got {self.dagger.labels!r}")
        if self.safety is not None and not self.safety.blind:
            raise ValueError(f"{where}: safety.blind must be true: a recipe's safety layer is one a car could have (the "
                             "privileged layer, blind = false, is an upper reference for lc-eval)")  # fmt: skip
        if self.safety is not None and self.safety.follow and not _NAME.match(self.safety.follow):
            raise ValueError(f"{where}: safety.follow must name a recipe, got {self.safety.follow!r}")
        for stage in (s for s in stages if s != "dagger"):  # each training stage's PolicyConfig, paths stood in for
            try:
                self.policy_config(stage, scenario="paper", seed=0, warm_start="demos" if stage == "clone" else "",
                                   init_policy="previous.safetensors" if stage != stages[0] else "")  # fmt: skip
            except ValueError as exc:
                raise ValueError(f"{where}, stage {stage}: {exc}") from None
        object.__setattr__(self, "stages", stages)

    @property
    def final_stage(self) -> str:
        return self.stages[-1]

    @property
    def obs(self) -> str:
        """The observation mode of the recipe's policy (PolicyConfig's default when the recipe sets none)."""
        from lcmodels.policy.config import PolicyConfig

        return str(self.stage_settings(self.final_stage).get("obs", PolicyConfig().obs))

    def stage_settings(self, stage: str) -> dict[str, Any]:
        """The PolicyConfig fields this recipe gives stage ``stage`` (``[policy]`` then the stage's table; a
        ``shielded`` stage: ``[train]``'s with its own ``timesteps``)."""
        if stage == "shielded":
            return {**self.policy, **self.train, "timesteps": self.shielded.timesteps}
        return {**self.policy, **(getattr(self, stage) if stage in _STAGE_TABLES else {})}

    def policy_config(self, stage: str, *, scenario: str, seed: int, warm_start: str = "", init_policy: str = "",
                      eval_episodes: int = 200, eval_seed: int = 0, record_eval: bool = False,
                      caps: dict[str, int] | None = None) -> Any:  # fmt: skip
        """The :class:`~lcmodels.policy.config.PolicyConfig` of stage ``clone`` or ``train`` (a dagger stage
        trains with its clone's): its settings; for a stage that trains online, the fields whose default follows
        the algorithm filled by :meth:`PolicyConfig.of <lcmodels.policy.config.PolicyConfig.of>` (fine-tuning when
        it starts from a previous stage's policy); then ``caps``, which lower integer fields to at most the given
        values (the tiny and quick presets' budgets; ``n_envs`` never below one environment a training road)."""
        from lcmodels.policy.config import PolicyConfig

        settings = self.stage_settings(stage)
        if stage in ("clone", "dagger"):
            settings["timesteps"] = 0
        data = {**settings, "seed": seed, "scenario": scenario, "warm_start": warm_start if stage == "clone" else "",
                "init_policy": init_policy if stage in ("train", "shielded") else "", "eval_episodes": eval_episodes,
                "eval_seed": eval_seed, "record_eval": record_eval}  # fmt: skip
        if stage in ("clone", "dagger"):  # no online steps: the rate and rollout length go unused, left as stored
            cfg = PolicyConfig.from_dict(data, stored=False)
        else:
            cfg = PolicyConfig.of(data, fine_tune=bool(init_policy))
        lowered = {key: cap for key, cap in (caps or {}).items() if isinstance(current := getattr(cfg, key, None), int)
                   and not isinstance(current, bool) and current > cap}  # fmt: skip
        if "n_envs" in lowered:  # never below one environment a training road
            lowered["n_envs"] = max(lowered["n_envs"], len(cfg.road_names()))
        return dataclasses.replace(cfg, **lowered) if lowered else cfg

    def capped(self, caps: dict[str, int] | None) -> Recipe:
        """This recipe with its demonstrations, DAgger and safety budgets lowered to ``caps`` (policy fields
        are capped by :meth:`policy_config`)."""
        if not caps:
            return self
        changes: dict[str, Any] = {}
        for name in _SPECS:
            spec = getattr(self, name)
            if spec is None:
                continue
            lowered = {f.name: min(getattr(spec, f.name), caps[f.name]) for f in dataclasses.fields(spec)
                       if f.name in caps and f.name != "seed" and isinstance(getattr(spec, f.name), int)
                       and not isinstance(getattr(spec, f.name), bool)}  # fmt: skip
            if lowered:
                changes[name] = dataclasses.replace(spec, **lowered)
        return dataclasses.replace(self, **changes) if changes else self

    # -- files ----------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "version": self.version, "row": self.row, "kind": self.kind,
                               "label": self.label, "description": self.description, "stages": list(self.stages),
                               "policy": dict(self.policy)}  # fmt: skip
        if self.predictor != "learned":  # said only when not the default: the older records' identities stay
            out["predictor"] = self.predictor
        for name in _STAGE_TABLES:
            out[name] = dict(getattr(self, name))
        for name in _SPECS:
            spec = getattr(self, name)
            if spec is not None:
                out[name] = dataclasses.asdict(spec)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "recipe") -> Recipe:
        if not isinstance(data, dict):
            raise ValueError(f"{where}: expected a table")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {unknown} (keys: {', '.join(sorted(known))})")
        if "name" not in data or "row" not in data:
            raise ValueError(f"{where}: needs 'name' and 'row'")
        kwargs = dict(data)
        for name, spec_cls in _SPECS.items():
            if name in kwargs:
                table = kwargs[name]
                if not isinstance(table, dict):
                    raise ValueError(f"{where}: [{name}] must be a table")
                if spec_cls is SafetyLayerConfig:
                    kwargs[name] = SafetyLayerConfig.from_table(table, where=f"{where}: [safety]")
                    continue
                names = {f.name for f in dataclasses.fields(spec_cls)}
                bad = sorted(set(table) - names)
                if bad:
                    raise ValueError(f"{where}: [{name}] has no key(s) {bad} (keys: {', '.join(sorted(names))})")
                kwargs[name] = spec_cls(**table)
        if "stages" in kwargs:
            if not isinstance(kwargs["stages"], list | tuple):
                raise ValueError(f"{where}: stages must be a list, got {kwargs['stages']!r}")
            kwargs["stages"] = tuple(kwargs["stages"])
        for key in ("name", "label", "description", "row", "kind", "predictor"):
            if key in kwargs and not isinstance(kwargs[key], str):
                raise ValueError(f"{where}: {key} must be a string, got {kwargs[key]!r}")
        try:
            return cls(**kwargs)
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
        fields = _policy_fields()
        safety: list[str] = []
        for text in settings:
            key, sep, value = text.partition("=")
            table, dot, name = key.strip().partition(".")
            if not sep or not dot or not name:
                raise ValueError(f"--set {text!r}: expected TABLE.KEY=VALUE (policy.learning_rate=1e-4)")
            value = value.strip()
            if table in ("policy", *_STAGE_TABLES):
                if name not in fields:
                    raise ValueError(f"--set {text}: PolicyConfig has no field {name!r}")
                data[table][name] = parse_value(value, None, f"--set {text}", fields[name])
            elif table == "safety":  # applied together below (settings that must agree change at once)
                safety.append(text)
            elif table in _SPECS:
                spec_cls = _SPECS[table]
                spec = getattr(self, table) or spec_cls()
                names = {f.name: str(f.type) for f in dataclasses.fields(spec_cls)}
                if name not in names:
                    raise ValueError(f"--set {text}: [{table}] has no key {name!r} (keys: {', '.join(sorted(names))})")
                data.setdefault(table, dataclasses.asdict(spec))[name] = parse_value(
                    value, getattr(spec, name), f"--set {text}", names[name])
            else:
                raise ValueError(f"--set {text}: no table {table!r} (tables: policy, clone, train, demos, dagger, "
                                 "shielded, safety)")  # fmt: skip
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
    "DAGGER_EXPERTS",
    "EXPERIMENT_FIELDS",
    "RECIPES_DIR",
    "RECIPE_KINDS",
    "STAGE_KINDS",
    "DaggerSpec",
    "DemoSpec",
    "Recipe",
    "ShieldedSpec",
    "load_recipe",
    "recipe_names",
    "recipe_path",
]
