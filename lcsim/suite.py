"""The benchmark's scenario suite and its sealed test episodes.

A suite is a named list of scenarios, each a variant of the paper's road along one dimension a user of
this field would test a lane-change policy on: lane count, traffic density, traffic and ego speed, the
spread of the traffic's speeds, and the traffic's driving style. Every suite scenario is also a registered
scenario name (``lc-eval rule --scenario three-lane``), and every one keeps the paper's observation shapes
(8 neighbours, 10 history steps, a 120x120 image), so a policy trained on one can be evaluated on all.

Seeds. Episode ``i`` is the episode ``reset(seed=u)`` gives for a *user seed* ``u``:

- training draws from user seeds below :data:`VALIDATION_SEED_BASE`;
- validation is evaluation seed ``S`` (``lc-eval --seed S``, ``lc-bench --seed S``):
  ``u = VALIDATION_SEED_BASE + S * SEED_STRIDE + i`` with ``0 <= S < MAX_VALIDATION_SEED``;
- the **sealed test episodes** of a suite scenario are ``u = SEALED_SEED_BASE + block * SEALED_BLOCK + i``
  (``block`` is the scenario's own, fixed forever). They lie above every validation seed, no command but
  the benchmark's final evaluation runs them (``lc-record`` and ``lc-eval`` refuse them), and that path
  appends every result to the committed ledger.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from lcsim.config import ScenarioConfig, paper_scenario

VALIDATION_SEED_BASE = 1_000_000_000
"""The first user seed of the validation episodes (evaluation seed 0, episode 0)."""
SEED_STRIDE = 100_000
"""User seeds per evaluation seed (the most episodes one evaluation seed has)."""
MAX_VALIDATION_SEED = 20_000
"""Evaluation seeds are below this, so that validation never reaches the sealed test seeds."""
SEALED_SEED_BASE = VALIDATION_SEED_BASE + MAX_VALIDATION_SEED * SEED_STRIDE
"""The first sealed test user seed (3,000,000,000)."""
SEALED_BLOCK = 1_000_000
"""User seeds per suite scenario in the sealed range."""
SEALED_SEED_END = SEALED_SEED_BASE + 1000 * SEALED_BLOCK
"""One past the last sealed user seed (below 2**32, what numpy's seeding takes)."""


OBSERVATION_FIELDS = ("neighbour_selection", "sensing_range_m")
"""The fields of :class:`~lcsim.config.ScenarioConfig` that say how the ego's sensors pick and see what they
show rather than what the world is: a policy keeps its own when it drives on another road
(:func:`observed_by`). The fields that set the observation's shapes (``num_neighbours``, ``history_steps``,
``observe_acceleration``, the image's size) come from the road it drives on and must match the policy's."""


def observed_by(world: ScenarioConfig, sensors: ScenarioConfig) -> ScenarioConfig:
    """``world`` (road, traffic, ego, route, reward) observed as ``sensors`` observes (its
    :data:`OBSERVATION_FIELDS`): the scenario a policy trained on ``sensors`` drives in on ``world``'s road."""
    return dataclasses.replace(world, **{f: getattr(sensors, f) for f in OBSERVATION_FIELDS})


def is_sealed(user_seed: int) -> bool:
    """Whether ``user_seed`` is one of the sealed test episodes' (only the benchmark's final path runs these)."""
    return SEALED_SEED_BASE <= int(user_seed) < SEALED_SEED_END


def check_unsealed(user_seeds: Iterable[int], *, sealed: bool = False) -> None:
    """``ValueError`` in one line when ``user_seeds`` reach the sealed test episodes, unless ``sealed``: the
    explicit leave that only the benchmark's final path gives (``lcmodels.bench.run.bench_cell`` with ``final``,
    which appends what it measures to the ledger, and ``lc-bench --verify``, which replays the ledger's own
    episodes). Every library path that runs episodes from user seeds asks here."""
    if sealed:
        return
    found = next((int(u) for u in user_seeds if is_sealed(u)), None)
    if found is not None:
        raise ValueError(f"user seed {found} is one of the benchmark's sealed test episodes ({SEALED_SEED_BASE} to "
                         f"{SEALED_SEED_END - 1}), which only lc-bench --final runs; choose others")


@dataclass(frozen=True, slots=True, kw_only=True)
class SuiteScenario:
    """One scenario of the benchmark suite."""

    name: str
    """Its registry name."""
    block: int
    """Its block of sealed test seeds (fixed forever: changing it would unseal nothing and reseal others)."""
    test_episodes: int
    """How many sealed test episodes its final evaluation runs."""
    what: str
    """What it tests, in a few words."""
    make: Callable[[], ScenarioConfig]

    def sealed_seeds(self, episodes: int | None = None) -> list[int]:
        """The user seeds of its first ``episodes`` (default: all :attr:`test_episodes`) sealed test episodes."""
        n = self.test_episodes if episodes is None else episodes
        if not 0 < n <= SEALED_BLOCK:
            raise ValueError(f"sealed episodes must be in 1..{SEALED_BLOCK}, got {n}")
        start = SEALED_SEED_BASE + self.block * SEALED_BLOCK
        return list(range(start, start + n))


def _variant(*, lanes: int | None = None, vehicles: int | None = None, traffic: dict | None = None,
             ego: dict | None = None, **fields: object) -> Callable[[], ScenarioConfig]:
    """A factory of the paper scenario with the given changes."""

    def make() -> ScenarioConfig:
        base = paper_scenario()
        road = base.road if lanes is None else dataclasses.replace(base.road, num_lanes=lanes)
        tr = dict(traffic or {})
        if vehicles is not None:
            tr["num_vehicles"] = vehicles
        return dataclasses.replace(
            base, road=road, traffic=dataclasses.replace(base.traffic, **tr),
            ego=dataclasses.replace(base.ego, **(ego or {})), **fields)  # type: ignore[arg-type]

    return make


_SCENARIOS = (
    SuiteScenario(name="paper", block=0, test_episodes=2000, make=paper_scenario,
                  what="the paper's road: 4 lanes, 100 vehicles at ~24 km/h, ego targets 30 km/h"),
    SuiteScenario(name="three-lane", block=1, test_episodes=500, make=_variant(lanes=3, vehicles=75),
                  what="3 lanes, the paper's density per lane (75 vehicles)"),
    SuiteScenario(name="five-lane", block=2, test_episodes=500, make=_variant(lanes=5, vehicles=125),
                  what="5 lanes, the paper's density per lane (125 vehicles)"),
    SuiteScenario(name="dense", block=3, test_episodes=500, make=_variant(vehicles=140),
                  what="4 lanes, 40% more vehicles (140)"),
    SuiteScenario(name="fast", block=4, test_episodes=500,
                  make=_variant(traffic={"speed_kmh": 50.0, "speed_spread_kmh": 4.0},
                                ego={"target_speed_kmh": 60.0, "initial_speed_kmh": 60.0},
                                route_length_m=1200.0),
                  what="traffic at ~50 km/h, ego targets 60 km/h over 1.2 km in the same 75 s"),
    SuiteScenario(name="spread", block=5, test_episodes=500,
                  make=_variant(traffic={"speed_spread_kmh": 6.0}),
                  what="the traffic's desired speeds spread 3x wider (6 km/h)"),
    SuiteScenario(name="exact-idm", block=6, test_episodes=500,
                  make=_variant(traffic={"human_like": False}),
                  what="every driver the exact IDM with the same parameters (no noise, lag or wander)"),
)

SUITE_SCENARIOS: dict[str, SuiteScenario] = {s.name: s for s in _SCENARIOS}
"""Every suite scenario by name."""
SUITES: dict[str, tuple[str, ...]] = {
    "highway": tuple(SUITE_SCENARIOS),
    "paper": ("paper",),
}
"""The named suites: ``highway`` (every scenario above), ``paper`` (the paper's road alone)."""
DEFAULT_SUITE = "highway"


def suite(name: str) -> list[SuiteScenario]:
    """The scenarios of suite ``name``. ``ValueError`` naming the suites for an unknown one."""
    if name not in SUITES:
        raise ValueError(f"unknown suite {name!r}; choose {', '.join(SUITES)}")
    return [SUITE_SCENARIOS[n] for n in SUITES[name]]


MAX_DRAWN_ROADS = 1024
"""The most roads :func:`drawn_roads` draws at once."""


def drawn_roads(count: int, seed: int) -> tuple[ScenarioConfig, ...]:
    """``count`` roads drawn from ``seed`` across the suite's dimensions, each dimension on its own, none of them
    a suite scenario: 3 to 5 lanes; 22 to 36 vehicles a lane (the paper 25, ``dense`` 35); traffic at 22 to 52
    km/h with the ego's target 18-27% above it and a route it covers in 96% of the 75 s (the paper: 24, 30 km/h
    and 600 m; ``fast``: 50, 60 km/h and 1200 m); desired speeds spread by 1.5 to 6.5 km/h (the paper 2,
    ``spread`` 6); the human-like traffic four times in five, else every driver the exact IDM. What training on
    them teaches can be measured on the suite's roads, which it never drove. The same count and seed give the
    same roads (with this version of the code)."""
    if not 0 < count <= MAX_DRAWN_ROADS:
        raise ValueError(f"drawn roads: the count must be in 1..{MAX_DRAWN_ROADS}, got {count}")
    rng = np.random.default_rng([int(seed), 0x0AD5])
    base = paper_scenario()
    roads = []
    for _ in range(count):
        lanes = int(rng.integers(3, 6))
        vehicles = round(lanes * rng.uniform(22.0, 36.0))
        speed = float(rng.uniform(22.0, 52.0))
        target = round(speed * float(rng.uniform(1.18, 1.27)), 2)
        spread = float(rng.uniform(1.5, 6.5))
        human = bool(rng.random() < 0.8)
        roads.append(dataclasses.replace(
            base, road=dataclasses.replace(base.road, num_lanes=lanes),
            traffic=dataclasses.replace(base.traffic, num_vehicles=vehicles, speed_kmh=round(speed, 2),
                                        speed_spread_kmh=round(spread, 2), human_like=human),
            ego=dataclasses.replace(base.ego, target_speed_kmh=target, initial_speed_kmh=target),
            route_length_m=round(0.96 * target / 3.6 * base.time_limit_s, 1)))  # fmt: skip
    return tuple(roads)


def _check_blocks() -> None:
    blocks = [s.block for s in _SCENARIOS]
    assert len(set(blocks)) == len(blocks), "two suite scenarios share a block of sealed seeds"
    assert all(SEALED_SEED_BASE + (b + 1) * SEALED_BLOCK <= SEALED_SEED_END for b in blocks)


_check_blocks()

__all__ = [
    "DEFAULT_SUITE",
    "MAX_DRAWN_ROADS",
    "MAX_VALIDATION_SEED",
    "OBSERVATION_FIELDS",
    "SEALED_SEED_BASE",
    "SEED_STRIDE",
    "SUITES",
    "SUITE_SCENARIOS",
    "VALIDATION_SEED_BASE",
    "SuiteScenario",
    "check_unsealed",
    "drawn_roads",
    "is_sealed",
    "observed_by",
    "suite",
]
