"""What the commands share: the one-line error, argument types, the safety layer's options, older flags."""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from lcsim.planning import SafetyLayerConfig


def fail(prog: str, msg: str) -> int:
    """Print ``prog: error: msg`` on stderr (one line, no traceback) and return the exit status 2."""
    print(f"{prog}: error: {' '.join(str(msg).split())}", file=sys.stderr)
    return 2


def int_at_least(minimum: int, at_most: int | None = None) -> Callable[[str], int]:
    """An argparse ``type`` accepting integers >= ``minimum`` (and <= ``at_most``, if given) with a one-line
    message otherwise."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        if at_most is not None and value > at_most:
            raise argparse.ArgumentTypeError(f"must be <= {at_most}, got {value}")
        return value

    parse.__name__ = f"int>={minimum}"
    return parse


positive_int = int_at_least(1)
non_negative_int = int_at_least(0)


def positive_float(text: str) -> float:
    """An argparse ``type`` accepting finite numbers > 0 with a one-line message otherwise."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def float_in(low: float, high: float) -> Callable[[str], float]:
    """An argparse ``type`` accepting finite numbers in ``[low, high]`` with a one-line message otherwise."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not low <= value <= high:  # NaN too
            raise argparse.ArgumentTypeError(f"must be in [{low:g}, {high:g}], got {text}")
        return value

    parse.__name__ = f"float in [{low:g}, {high:g}]"
    return parse


class _SetAlias(argparse.Action):
    """An older flag that now is a setting: appends ``KEY=VALUE`` (``KEY=true`` for a flag without a value) to
    the ``--set`` list, in command-line order."""

    def __init__(self, option_strings: list[str], dest: str, key: str, **kwargs: object) -> None:
        self.key = key
        super().__init__(option_strings, dest, **kwargs)  # type: ignore[arg-type]

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> None:  # fmt: skip
        value = "true" if self.nargs == 0 else f"[{', '.join(values)}]" if isinstance(values, list) else str(values)
        setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), f"{self.key}={value}"])


class _Gone(argparse.Action):
    """An older flag whose option left the command: a one-line error naming where it went."""

    def __init__(self, option_strings: list[str], dest: str, where: str, **kwargs: object) -> None:
        self.where = where
        super().__init__(option_strings, dest, **kwargs)  # type: ignore[arg-type]

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> None:  # fmt: skip
        parser.error(f"{option_string} {self.where}")


def add_setting_aliases(p: argparse.ArgumentParser | argparse._ArgumentGroup, aliases: dict[str, str],
                        flags: tuple[str, ...] = (), lists: tuple[str, ...] = ()) -> None:  # fmt: skip
    """Older flags that are settings now (``--batch`` for ``--set batch=...``), hidden from ``--help``: each
    appends to ``--set``'s list (``dest="settings"``), ``flags`` without a value (``=true``), ``lists`` with one
    or more (a JSON list)."""
    for flag, key in aliases.items():
        nargs = 0 if flag in flags else "+" if flag in lists else None
        p.add_argument(flag, dest="settings", action=_SetAlias, key=key, nargs=nargs, help=argparse.SUPPRESS)


RESEARCH_FLAGS = ("--lookahead-driver-draws", "--lookahead-estimate-drivers", "--lookahead-known-drivers",
                  "--lookahead-margin")  # fmt: skip
"""Older flags of the safety layer's research options (``experiments/imagined_drivers`` runs them)."""
SAFETY_ALIASES = {"--lookahead-horizon": "safety.horizon_decisions", "--lookahead-samples": "safety.samples",
                  "--lookahead-perceived": "safety.perceived"}  # fmt: skip
"""The safety layer's older flags and the settings they are."""


def add_safety_layer_arguments(p: argparse.ArgumentParser, *, with_set: bool = True) -> None:
    """``--follow DRIVER`` and ``--set safety.KEY=VALUE`` (unless the command's own ``--set`` takes them,
    ``with_set=False``): the safety layer of a driver spec ``safety-layer:DRIVER`` (``lc-eval``, ``lc-bench``,
    ``lc-record``, ``lc-dagger``). The older ``--lookahead-*`` flags stay accepted, hidden."""
    g = p.add_argument_group("the safety layer (for a driver safety-layer:DRIVER)")
    g.add_argument("--follow", metavar="DRIVER", default=None, type=zoo_spec,
                   help="who drives on in the safety layer's imagined futures: a built-in driver, a policy file or "
                   "zoo:NAME that does not read the image (default: the driver behind the layer itself); lets the "
                   "layer guard a policy that reads the image (safety.follow)")
    if with_set:
        g.add_argument("--set", dest="settings", action="append", default=[], metavar="safety.KEY=VALUE",
                       type=_safety_setting,
                       help="a setting of the safety layer (repeatable): horizon_decisions (16), samples (1), "
                       "perceived (true), blind (true; false: a privileged layer that sees the traffic's coming random "
                       "draws, an upper reference)")
    g.add_argument("--lookahead-follow", dest="follow", type=zoo_spec, help=argparse.SUPPRESS)
    add_setting_aliases(g, SAFETY_ALIASES, flags=("--lookahead-perceived",))
    for flag in RESEARCH_FLAGS:
        g.add_argument(flag, action=_Gone, nargs="?", help=argparse.SUPPRESS,
                       where="was a research option of the safety layer: python -m "
                       "experiments.imagined_drivers.imagined_drivers runs it")  # fmt: skip


def _safety_setting(text: str) -> str:
    """argparse type of a command's ``--set`` that takes the safety layer's settings only."""
    if not text.strip().startswith("safety."):
        raise argparse.ArgumentTypeError(f"{text!r}: this command takes the safety layer's settings only "
                                         "(safety.KEY=VALUE)")  # fmt: skip
    return text


def safety_settings(settings: list[str]) -> tuple[list[str], list[str]]:
    """``--set`` settings split into the safety layer's (``safety.KEY=VALUE``) and the others."""
    mine = [s for s in settings if s.strip().startswith("safety.")]
    return mine, [s for s in settings if not s.strip().startswith("safety.")]


def safety_layer_from_args(spec: str, args: argparse.Namespace,
                           table: dict[str, object] | None = None) -> SafetyLayerConfig | None:  # fmt: skip
    """The safety layer the driver ``spec`` drives behind (``None``: none): the settings its spelling means
    (:func:`lcmodels.policy.driverspec.split_safety_layer`), then the ``[safety]`` ``table`` of a config file, then
    ``--follow``, then each ``--set safety.KEY=VALUE`` in order. ``ValueError`` in one line for settings given
    for a driver behind no layer, or a setting the layer refuses."""
    from lcmodels.policy.driverspec import safety_layer_of, split_safety_layer

    mine, _ = safety_settings(getattr(args, "settings", None) or [])
    follow = getattr(args, "follow", None)
    if split_safety_layer(spec)[1] is None:
        if table or follow or mine:
            given = ", ".join([*(["[safety] table"] if table else []), *(["--follow"] if follow else []), *mine])
            raise ValueError(f"{given}: settings of the safety layer, and {spec} drives behind none (name it "
                             f"safety-layer:{spec})")  # fmt: skip
        return None
    layer = safety_layer_of(spec, table or None, follow, where="[safety]")
    assert layer is not None
    return layer.with_named_settings(mine) if mine else layer


def given_safety_settings(args: argparse.Namespace) -> dict[str, object]:
    """The safety layer's settings the command line gave (``--set safety.KEY=VALUE`` and the older flags), each
    by its field's name with the value read as its type, the last one given winning (what a recording's flags
    keep, so that a rerun of the same command resumes it)."""
    from lckit.config import field_type, parse_value
    from lcsim.planning import SafetyLayerConfig
    from lcsim.planning.safety import LEGACY_KEYS

    mine, _ = safety_settings(getattr(args, "settings", None) or [])
    layer = SafetyLayerConfig()
    given: dict[str, object] = {}
    for text in mine:
        key, _, value = text.partition("=")
        name = LEGACY_KEYS.get(key.strip().removeprefix("safety."), key.strip().removeprefix("safety."))
        if hasattr(layer, name):
            given[name] = parse_value(value.strip(), getattr(layer, name), f"--set {text}", field_type(layer, name))
    return given


def add_executor_arguments(p: argparse.ArgumentParser | argparse._ArgumentGroup, ray_does: str,
                           local_does: str = "this machine") -> None:
    """``--executor {local,ray}`` and ``--ray-address``: where a command's independent work runs
    (:mod:`lcdata.executors`); ``ray_does`` says what becomes a Ray task."""
    from lcdata.executors import EXECUTORS

    p.add_argument("--executor", choices=EXECUTORS, default="local",
                   help=f"local (default: {local_does}) or ray: {ray_does}; the same results. Needs "
                   'pip install -e ".[ray]"')
    p.add_argument("--ray-address", default=None,
                   help="a running Ray cluster (ray start --head prints it; default RAY_ADDRESS, else a local "
                   "instance started for the run); the nodes write the files: --out on storage every node sees")


class _CliFormatter(logging.Formatter):
    """The library's log lines as a command shows them: progress as it is, a warning as ``prog: warning: ...``."""

    def __init__(self, prog: str) -> None:
        super().__init__("%(message)s")
        self.prog = prog

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return f"{self.prog}: {record.levelname.lower()}: {text}" if record.levelno >= logging.WARNING else text


class _StderrHandler(logging.StreamHandler):
    """A handler on whatever ``sys.stderr`` is when a record comes: a command run in-process after another (tests,
    a notebook) never writes to the stream an earlier one was given, which may be closed by then."""

    @property  # type: ignore[override]
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def setup_logging(prog: str, verbose: bool) -> None:
    """Show the libraries' log on stderr: their progress (INFO) when ``verbose``, always their warnings."""
    handler = _StderrHandler()
    handler.setFormatter(_CliFormatter(prog))
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, handlers=[handler], force=True)


def zoo_spec(text: str) -> str:
    """argparse type of a driver or policy argument: ``zoo:NAME`` (also ``safety-layer:zoo:NAME``) becomes the zoo
    entry's policy file; anything else is returned as given."""
    if "zoo:" not in text:
        return text
    from lcmodels.policy.driverspec import resolve_policy_spec

    try:
        return resolve_policy_spec(text)[0]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
