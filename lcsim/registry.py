"""The names a user gives: scenarios and drivers, one registry each, used by the gym ids and every command.

Scenarios: :data:`SCENARIOS` (``paper``, ``light``, ``tiny``, ``corpus``); :func:`scenario` also takes the
path of a scenario file, a TOML or JSON table of :class:`~lcsim.config.ScenarioConfig` fields (missing
fields keep their defaults; a misspelt one is an error naming it)::

    # my-scenario.toml
    route_length_m = 400.0
    [traffic]
    num_vehicles = 60

Drivers: :data:`DRIVER_NAMES` for :func:`make_driver`. The words that name a policy or a driver behind the safety
layer are the commands' (:mod:`lcmodels.policy.driverspec`); ``lookahead`` and ``lookahead-blind`` stay names here
because recordings made by name (a worker process, a Ray task) build them from this registry.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from lckit.config import read_data_file
from lcsim.config import (
    ScenarioConfig,
    corpus_scenario,
    light_scenario,
    paper_scenario,
    tiny_scenario,
)
from lcsim.drivers import Driver, KeepLaneDriver, RandomDriver, RuleBasedDriver
from lcsim.planning import PRIVILEGED, LookaheadDriver, OracleDriver, SafetyLayerConfig
from lcsim.suite import SUITE_SCENARIOS

SCENARIOS: dict[str, Callable[[], ScenarioConfig]] = {
    "paper": paper_scenario,
    "light": light_scenario,
    "tiny": tiny_scenario,
    "corpus": corpus_scenario,
    **{name: s.make for name, s in SUITE_SCENARIOS.items() if name != "paper"},
}
"""Every named scenario: the paper's task (100 vehicles, 600 m), a light one (30 vehicles, 300 m), a tiny one
for tests (8 vehicles, 150 m), the trajectory corpus (20 autopilot vehicles, 2000 steps, no image), and the
benchmark suite's variants of the paper's road (:mod:`lcsim.suite`: ``three-lane``, ``dense``, ...)."""
TASK_SCENARIOS: tuple[str, ...] = ("paper", "light", "tiny", *(n for n in SUITE_SCENARIOS if n != "paper"))
"""The named scenarios with the ego's lane-change task (the corpus scenario records traffic only)."""
SCENARIO_FILE_SUFFIXES = (".toml", ".json")


def scenario(name_or_file: str | Path) -> ScenarioConfig:
    """The scenario of a registered name or of a scenario file (``.toml`` or ``.json``).

    Raises:
        ValueError: an unknown name, a missing or unreadable file, or a field the config refuses (named).
    """
    text = str(name_or_file)
    if text in SCENARIOS:
        return SCENARIOS[text]()
    path = Path(text)
    if path.suffix not in SCENARIO_FILE_SUFFIXES:
        raise ValueError(f"unknown scenario {text!r}: choose {', '.join(SCENARIOS)} or a scenario file "
                         f"({' / '.join(SCENARIO_FILE_SUFFIXES)})")
    try:
        return ScenarioConfig.from_dict(read_data_file(path, "scenario file"), stored=False)
    except ValueError as exc:
        raise ValueError(str(exc) if str(path) in str(exc) else f"scenario file {path}: {exc}") from None


def scenario_label(name_or_file: str | Path) -> str:
    """The name a scenario goes by in file names and metadata: its registry name, or a file's stem."""
    text = str(name_or_file)
    return text if text in SCENARIOS else Path(text).stem


_FACTORIES: dict[str, Callable[[int], Driver]] = {
    "rule": lambda seed: RuleBasedDriver(),
    "lookahead": lambda seed: LookaheadDriver(PRIVILEGED),  # the rule-based driver behind a privileged layer
    "lookahead-blind": lambda seed: LookaheadDriver(SafetyLayerConfig(perceived=False)),  # and behind a blind one
    "oracle": lambda seed: OracleDriver(),
    "keep": lambda seed: KeepLaneDriver(),
    "random": RandomDriver,
}
DRIVER_NAMES = tuple(_FACTORIES)
"""Names :func:`make_driver` accepts."""
def make_driver(name: str, seed: int = 0) -> Driver:
    """A driver by name (``autopilot`` is a simulator mode, not a policy); ``seed`` seeds ``random``."""
    factory = _FACTORIES.get(name)
    if factory is None:
        raise ValueError(f"unknown driver {name!r}; choose {', '.join(DRIVER_NAMES)}")
    return factory(seed)
