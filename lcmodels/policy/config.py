"""The configuration of a policy training run (:class:`PolicyConfig`) and the scenarios a policy trains in.

Kept apart from the training loop so that the policy file loader can rebuild a network from a stored
config without importing training. A config is data: constructing one reads no file (the scenario file it may
name is read once, when a run resolves it: :func:`lcmodels.policy.plan.resolve`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from lckit.config import JsonConfig, check_field, check_limits, require_non_negative, require_positive
from lcmodels.policy.names import (
    ALGORITHMS,
    IMAGE_NETS,
    OBS_MODES,
    SENSOR_ENCODERS,
    ObsMode,
    scenario_for_mode,
)
from lcsim.config import NEIGHBOUR_SELECTIONS, ScenarioConfig
from lcsim.registry import SCENARIO_FILE_SUFFIXES, TASK_SCENARIOS, scenario
from lcsim.suite import MAX_DRAWN_ROADS, MAX_VALIDATION_SEED, SEED_STRIDE, SUITES, drawn_roads

_LEARNING_RATES = {"ppo": 3e-4, "a2c": 7e-4, "dqn": 1e-4}
FINE_TUNE_LEARNING_RATES = {"ppo": 3e-5}
"""PPO from a warm start or an initial policy learns at a tenth of its default rate: from the same clone, PPO
at 3e-4 lost held-out success and at 3e-5 gained it (docs/results/lanes/NOTE.md); PPO from DAgger at 3e-5 gave
the project's best policy (docs/results/contact). A2C and DQN were not compared that way and keep their rates."""


_DRAWN = "drawn:"
"""``train_roads`` of roads drawn across the suite's dimensions: ``drawn:N``."""

_ROLLOUT_STEPS = {"a2c": 8}
"""PPO / A2C rollout length per environment where it is not PolicyConfig's default (A2C's own default)."""


def _field_default(cls: type, name: str) -> Any:
    return next(f.default for f in dataclasses.fields(cls) if f.name == name)


def default_learning_rate(algo: str, fine_tune: bool = False) -> float:
    """The learning rate a run gets when none is given: per algorithm, or :data:`FINE_TUNE_LEARNING_RATES`
    when it continues from a warm start or an initial policy (``fine_tune``)."""
    if algo not in _LEARNING_RATES:
        raise ValueError(f"unknown algorithm {algo!r}; choose one of {', '.join(_LEARNING_RATES)}")
    return FINE_TUNE_LEARNING_RATES.get(algo, _LEARNING_RATES[algo]) if fine_tune else _LEARNING_RATES[algo]


_V = TypeVar("_V", "AlgorithmView", "ObservationView", "RunView")

MAX_TIMESTEPS = 1_000_000_000
"""The most online decisions a run may ask for (a billion decisions: 15 years of driving at 2 per second)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class AlgorithmView:
    """What the learning algorithm reads of a :class:`PolicyConfig` (:attr:`PolicyConfig.algorithm`):
    stable-baselines3's hyper-parameters."""

    algo: str
    learning_rate: float
    gamma: float
    n_steps: int
    batch_size: int
    n_epochs: int
    ent_coef: float
    buffer_size: int
    learning_starts: int
    exploration_fraction: float
    target_update_interval: int


@dataclass(frozen=True, slots=True, kw_only=True)
class ObservationView:
    """What the policy sees and how its network reads it (:attr:`PolicyConfig.observation`): the mode, the
    scenario's view of the traffic, the features extractor's branches."""

    obs: str
    neighbours: str
    slots: int
    accel_features: bool
    image_net: str
    image_features: int
    contact_features: bool
    window_features: bool
    sensor_encoder: str


@dataclass(frozen=True, slots=True, kw_only=True)
class RunView:
    """The run around them (:attr:`PolicyConfig.run`): where and how long it trains, its seed, the learner's
    reward shaping, checkpoints, evaluation, and what it starts from."""

    scenario: str
    train_roads: str
    timesteps: int
    n_envs: int
    seed: int
    reward_scale: float
    collision_weight: float
    checkpoint_every: int
    eval_episodes: int
    eval_seed: int
    eval_batch: int
    record_eval: bool
    warm_start: str
    warm_start_epochs: int
    init_policy: str
    freeze_image: bool


@dataclass(frozen=True, slots=True, kw_only=True)
class PolicyConfig(JsonConfig):
    """Everything that defines a policy training run (stored in ``run.json``, flat: the stage records, policy cards
    and ledger keys written so far hold it so). Its parts serve different readers: :attr:`algorithm`,
    :attr:`observation` and :attr:`run` are typed views of them."""

    LEGACY_DEFAULTS: ClassVar[dict[str, Any]] = {"contact_features": False, "freeze_image": False}
    LIMITS: ClassVar[dict[str, float]] = {
        "timesteps": MAX_TIMESTEPS, "n_envs": 1_024, "slots": 64, "image_features": 1_024,
        "learning_rate": 1.0, "n_steps": 100_000, "batch_size": 1_000_000, "n_epochs": 1_000,
        "ent_coef": 10.0, "reward_scale": 1_000.0, "collision_weight": 1_000.0, "buffer_size": 10_000_000,
        "learning_starts": MAX_TIMESTEPS, "target_update_interval": MAX_TIMESTEPS,
        "checkpoint_every": MAX_TIMESTEPS, "eval_episodes": SEED_STRIDE, "eval_seed": MAX_VALIDATION_SEED - 1,
        "eval_batch": 10_000, "warm_start_epochs": 10_000,
    }  # fmt: skip
    """Plausible upper bounds, checked before anything is built or written: a run of 999999 environments, a
    replay buffer of 1e12 transitions or 1e23 decisions is a slip, not a plan. ``eval_episodes`` and
    ``eval_seed`` as evaluation takes them (:func:`lcmodels.policy.evaluate.eval_user_seeds`)."""

    algo: str = "ppo"
    obs: str = "hybrid"
    scenario: str = "paper"
    train_roads: str = ""
    """The roads training drives ('' = ``scenario`` alone): a benchmark suite's name (``highway``: every road of
    :mod:`lcsim.suite`), registered scenario names joined by commas, or ``drawn:N``: N roads drawn from the training
    seed across the suite's dimensions (:func:`lcsim.suite.drawn_roads`, none of them a suite road). The
    environments are split among them in blocks (:class:`lcsim.sb3.MixedRoadsSB3VecEnv`), each road seen with this
    config's view; every road must give ``scenario``'s observation shapes. The policy's card keeps ``scenario``."""
    timesteps: int = 100_000
    """Online decisions (environment steps summed over environments); 0 with a warm start gives the
    behaviour-cloned policy itself."""
    n_envs: int = 16
    seed: int = 0
    neighbours: str = "lanes"
    """Which vehicles the observation shows (``ScenarioConfig.neighbour_selection``): ``lanes`` or ``nearest``."""
    slots: int = 8
    """How many (``ScenarioConfig.num_neighbours``): the paper's 8, or with ``lanes`` up to 16, the slots
    after the eighth a wider view (:data:`lcsim.config.LANE_SLOTS`). The predictor, which has no slot
    embedding, predicts each shown vehicle with the others as context, however many."""
    image_net: str = "compact"
    image_features: int = 10
    contact_features: bool = True
    """The sensor branch also gets each slot's time to contact, gap and proximity
    (``lcmodels.policy.extractor.ContactFeatures``). A clone of the oracle in ``pure`` mode wins more held-out
    episodes with them (docs/results/contact). Runs stored before the option existed read as off."""
    window_features: bool = False
    """The sensor branch also gets, per side lane, when over the next 16 s the ego could change into it,
    against when its own leader traps it (``lcmodels.policy.extractor.WindowFeatures``; lane slots only)."""
    sensor_encoder: str = "mlp"
    """How the sensor branch reads the vehicles: ``mlp`` (the slots' rows flattened) or ``attention`` (the ego
    attends to the set of sensed vehicles: ``lcmodels.policy.extractor.EgoAttention``)."""
    accel_features: bool = False
    """The observation also shows each vehicle's acceleration (``ScenarioConfig.observe_acceleration``), and
    with ``window_features`` the sensor branch also looks at the side lanes with those accelerations kept."""
    learning_rate: float = _LEARNING_RATES["ppo"]
    gamma: float = 0.95
    """0.95 (a 10 s horizon at 2 decisions/s): PPO on ``pure`` observations learned far sooner with it and no
    entropy bonus than with 0.99 and 0.01."""
    n_steps: int = 128
    """PPO / A2C rollout length per environment (A2C default 8, filled by :meth:`of`)."""
    batch_size: int = 256
    n_epochs: int = 10
    ent_coef: float = 0.0
    reward_scale: float = 0.01
    """Rewards handed to the learner are scaled by this (returns in the logs are unscaled)."""
    collision_weight: float = 1.0
    """The learner's collision reward is this many times the scenario's (training shaping: the logged and
    evaluated returns keep the paper's reward)."""
    buffer_size: int = 50_000
    """DQN replay buffer (transitions)."""
    learning_starts: int = 2_000
    exploration_fraction: float = 0.3
    target_update_interval: int = 2_000
    checkpoint_every: int = 20_000
    eval_episodes: int = 200
    eval_seed: int = 0
    eval_batch: int = 20
    record_eval: bool = True
    warm_start: str = ""
    """Directory of recorded MCAP episodes to pretrain on ('' = none)."""
    warm_start_epochs: int = 10
    init_policy: str = ""
    """A ``policy.safetensors`` (a behaviour-cloned run's, a DAgger round's) whose weights start the online
    training ('' = none): same algorithm, observation mode, predictor, scenario and network as this run."""
    freeze_image: bool = False
    """With ``init_policy`` in the ``image`` and ``hybrid`` modes: the image branch keeps the initial
    policy's weights and runs once per step in the observation wrapper, so the rollout buffer holds its
    features instead of the image and the update epochs never run the network (several times the online
    steps per minute in ``hybrid`` mode). ``policy.safetensors`` is a plain policy of the mode, image branch
    included; ``checkpoints/latest.json`` is in the training form, for resuming only."""

    def __post_init__(self) -> None:
        check_limits(self)
        check_field(self.algo in ALGORITHMS, self, "algo", f"must be one of {', '.join(ALGORITHMS)}", self.algo)
        check_field(self.obs in OBS_MODES, self, "obs", f"must be one of {', '.join(OBS_MODES)}", self.obs)
        check_field(self.scenario in TASK_SCENARIOS or Path(self.scenario).suffix in SCENARIO_FILE_SUFFIXES, self,
               "scenario", f"must be one of {', '.join(TASK_SCENARIOS)} or a scenario file", self.scenario)
        drawn = self._drawn_count()
        roads = self.road_names()
        check_field(drawn != 0 and (drawn is not None or all(r in TASK_SCENARIOS for r in roads)), self,
                    "train_roads", f"must be a suite ({', '.join(SUITES)}), scenario names joined by commas "
                    f"({', '.join(TASK_SCENARIOS)}) or drawn:N with N in 1..{MAX_DRAWN_ROADS}",
                    self.train_roads)  # fmt: skip
        check_field(len(roads) <= self.n_envs, self, "train_roads",
                    f"names {len(roads)} roads, more than n_envs {self.n_envs} (one environment a road at least)",
                    self.train_roads)  # fmt: skip
        check_field(self.neighbours in NEIGHBOUR_SELECTIONS, self, "neighbours",
               f"must be one of {', '.join(NEIGHBOUR_SELECTIONS)}", self.neighbours)
        check_field(not self.window_features or self.neighbours == "lanes", self, "window_features",
               "needs neighbours='lanes' (which vehicle is in which lane)", self.window_features)
        check_field(self.sensor_encoder in SENSOR_ENCODERS, self, "sensor_encoder",
                    f"must be one of {', '.join(SENSOR_ENCODERS)}", self.sensor_encoder)
        check_field(self.image_net in IMAGE_NETS, self, "image_net", f"must be one of {', '.join(IMAGE_NETS)}",
               self.image_net)  # fmt: skip
        require_positive(self, "n_envs", "image_features", "learning_rate", "n_steps", "batch_size",
                  "n_epochs", "reward_scale", "collision_weight", "buffer_size", "target_update_interval",
                  "checkpoint_every", "eval_batch", "warm_start_epochs")
        require_non_negative(self, "timesteps", "ent_coef", "learning_starts", "eval_episodes", "seed", "eval_seed")
        check_field(not (self.warm_start and self.init_policy), self, "init_policy",
               "cannot be combined with warm_start (clone first, then start from that run's policy.safetensors)",
               self.init_policy)  # fmt: skip
        check_field(not self.freeze_image or bool(self.init_policy), self, "freeze_image",
               "needs init_policy (a policy whose image branch is trained already)", self.freeze_image)
        check_field(not self.freeze_image or ObsMode.of(self.obs).reads_image, self, "freeze_image",
               f"needs an observation mode with the image (image, hybrid), not {self.obs!r}", self.freeze_image)
        check_field(self.timesteps > 0 or bool(self.warm_start), self, "timesteps",
               "must be > 0 without a warm start (0 with one: behaviour cloning only)", self.timesteps)  # fmt: skip
        check_field(self.algo != "ppo" or self.batch_size > 1, self, "batch_size", "must be > 1 for ppo",
                    self.batch_size)
        check_field(0 < self.gamma <= 1, self, "gamma", "must be in (0, 1]", self.gamma)
        check_field(0 < self.exploration_fraction <= 1, self, "exploration_fraction", "must be in (0, 1]",
               self.exploration_fraction)  # fmt: skip
        check_field(self.seed < 1_000_000, self, "seed", "must be < 1000000 (keeps training seeds off evaluation's)",
               self.seed)  # fmt: skip
        try:  # slots (and neighbours) as a scenario validates them: the view fits any scenario or none
            self.scenario_config(ScenarioConfig())
        except ValueError as exc:
            raise ValueError(f"PolicyConfig.slots {self.slots} does not fit the scenario: {exc}") from None

    @property
    def algorithm(self) -> AlgorithmView:
        """What the learning algorithm reads."""
        return _view(AlgorithmView, self)

    @property
    def observation(self) -> ObservationView:
        """What the policy sees and how its network reads it."""
        return _view(ObservationView, self)

    @property
    def run(self) -> RunView:
        """The run around them."""
        return _view(RunView, self)

    @classmethod
    def of(cls, given: dict[str, Any], settings: Sequence[str] = (), *, fine_tune: bool | None = None) -> PolicyConfig:
        """The config of the fields ``given`` (a file's, a recipe's, the flags'), then the ``KEY=VALUE``
        ``settings`` in order, with each field whose default follows the algorithm and that neither gives filled
        here, the one place that fills them: ``learning_rate`` (:func:`default_learning_rate`, fine-tuning when
        ``fine_tune``, by default when the run starts from a warm start or an initial policy) and ``n_steps``
        (A2C 8, else 128). ``ValueError`` naming the problem."""
        final = cls.from_dict(given, stored=False).with_settings(settings)
        chosen = set(given) | {s.partition("=")[0].strip() for s in settings}
        if fine_tune is None:
            fine_tune = bool(final.warm_start or final.init_policy)
        filled = {"learning_rate": default_learning_rate(final.algo, fine_tune),
                  "n_steps": _ROLLOUT_STEPS.get(final.algo, _field_default(cls, "n_steps"))}  # fmt: skip
        filled = {k: v for k, v in filled.items() if k not in chosen}
        return dataclasses.replace(final, **filled) if filled else final

    @classmethod
    def from_card(cls, data: dict[str, Any], scenario: ScenarioConfig) -> PolicyConfig:
        """The training config a policy card stores (``train_config``), its view checked against the scenario the
        card stores too (``scenario``), never the scenario file its ``scenario`` field names: a policy trained
        with ``--scenario my.toml`` loads from any folder, the file there or not. ``ValueError`` as
        :meth:`from_dict`."""
        cfg = cls.from_dict(data)
        cfg.scenario_config(scenario)
        return cfg

    def _drawn_count(self) -> int | None:
        """N of ``drawn:N`` (0 for a bad N); None for other roads."""
        if not self.train_roads.startswith(_DRAWN):
            return None
        n = self.train_roads[len(_DRAWN):]
        return int(n) if n.isdigit() and 0 < int(n) <= MAX_DRAWN_ROADS else 0

    def road_names(self) -> tuple[str, ...]:
        """The names of :attr:`train_roads`' roads (empty: ``scenario`` alone; ``drawn-K`` for drawn roads)."""
        drawn = self._drawn_count()
        if drawn is not None:
            return tuple(f"drawn-{k}" for k in range(drawn))
        if self.train_roads in SUITES:
            return SUITES[self.train_roads]
        return tuple(r.strip() for r in self.train_roads.split(",") if r.strip())

    def road_configs(self) -> tuple[ScenarioConfig, ...]:
        """The roads :attr:`train_roads` names, with this config's view (empty: ``scenario`` alone, which
        :func:`lcmodels.policy.plan.resolve` reads). Registered names and drawn roads: no file is read."""
        drawn = self._drawn_count()
        if drawn:
            return tuple(self.scenario_config(r) for r in drawn_roads(drawn, self.seed))
        return tuple(self.scenario_config(scenario(n)) for n in self.road_names())

    def scenario_config(self, base: ScenarioConfig) -> ScenarioConfig:
        """``base`` (the scenario :attr:`scenario` names, as a run resolved it) with this config's view of the
        traffic: what the policy sees."""
        base = dataclasses.replace(base, neighbour_selection=self.neighbours, num_neighbours=self.slots,
                                   observe_acceleration=self.accel_features)
        return scenario_for_mode(base, self.obs)


def _view(cls: type[_V], cfg: PolicyConfig) -> _V:
    return cls(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(cls)})
