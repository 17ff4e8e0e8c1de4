"""What the commands share: the one-line error, argument types, the lookahead planner's options."""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Callable


def fail(prog: str, msg: str) -> int:
    """Print ``prog: error: msg`` on stderr (one line, no traceback) and return the exit status 2."""
    print(f"{prog}: error: {' '.join(str(msg).split())}", file=sys.stderr)
    return 2


def int_at_least(minimum: int) -> Callable[[str], int]:
    """An argparse ``type`` accepting integers >= ``minimum`` with a one-line message otherwise."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
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


def _driver_fields(text: str) -> tuple[str, ...]:
    """``--lookahead-known-drivers``: comma-separated :class:`lcsim.traffic.DriverParams` field names."""
    from lcsim.traffic import driver_fields

    try:
        return driver_fields([n.strip() for n in text.split(",") if n.strip()] or [text])
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def add_lookahead_arguments(p: argparse.ArgumentParser) -> None:
    """``--lookahead-horizon``, ``--lookahead-samples``, ``--lookahead-perceived``, ``--lookahead-driver-draws``,
    ``--lookahead-estimate-drivers``, ``--lookahead-known-drivers`` and ``--lookahead-margin``: how the lookahead
    planners imagine (``lc-eval``, ``lc-record`` and the tools that run the same drivers)."""
    p.add_argument("--lookahead-horizon", type=int_at_least(1), default=None,
                   help="lookahead drivers: decisions imagined after each candidate one (default 16, i.e. 8 s)")
    p.add_argument("--lookahead-samples", type=int_at_least(1), default=None,
                   help="lookahead-blind drivers: redrawn futures imagined per candidate decision (default 1)")
    p.add_argument("--lookahead-perceived", action="store_true",
                   help="lookahead-blind drivers: imagine each future from what the ego's sensors show (no traffic "
                   "beyond the scenario's sensing range, each vehicle's unseen desired speed read from its motion): "
                   "the planner needs no privileged state, only the traffic's rules")
    p.add_argument("--lookahead-driver-draws", action="store_true",
                   help="with --lookahead-perceived, human-like traffic: each imagined future draws the unseen "
                   "drivers' own parameters from the traffic's distribution instead of taking the median driver "
                   "(with --lookahead-samples > 1 a decision's survival is its share over plausible drivers)")
    p.add_argument("--lookahead-estimate-drivers", action="store_true",
                   help="with --lookahead-perceived, human-like traffic: infer each vehicle's car-following "
                   "parameters, reaction time and desired speed from its motion while in sight, and imagine it "
                   "with a driver drawn from that estimate instead of the median driver")
    p.add_argument("--lookahead-known-drivers", type=_driver_fields, default=None, metavar="FIELDS",
                   help="with --lookahead-perceived, a privileged diagnostic: the imagined futures keep these driver "
                   "parameters at their true values (comma-separated: time_headway, max_accel, inv_2sqrt_ab, lag, "
                   "lc_inv_duration, eagerness), the ceiling of a planner that would estimate them")
    p.add_argument("--lookahead-margin", type=float, default=None, metavar="M",
                   help="lookahead-blind drivers: imagine the ego M metres longer at its front and back, so that a "
                   "decision survives only with that much more room than contact (default 0)")


def lookahead_options(args: argparse.Namespace) -> dict[str, int | float]:
    """The ``--lookahead-*`` options given (``LookaheadConfig`` fields, for ``driver_for``)."""
    given = {"horizon_decisions": args.lookahead_horizon, "samples": args.lookahead_samples,
             "perceived": args.lookahead_perceived or None, "driver_draws": args.lookahead_driver_draws or None,
             "margin_m": args.lookahead_margin, "known_drivers": args.lookahead_known_drivers,
             "estimate_drivers": args.lookahead_estimate_drivers or None}
    return {k: v for k, v in given.items() if v is not None}


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


def setup_logging(prog: str, verbose: bool) -> None:
    """Show the libraries' log on stderr: their progress (INFO) when ``verbose``, always their warnings."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_CliFormatter(prog))
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, handlers=[handler], force=True)



def zoo_spec(text: str) -> str:
    """argparse type of a driver or policy argument: ``zoo:NAME`` (also ``lookahead-blind:zoo:NAME``) becomes
    the zoo entry's policy file; anything else is returned as given."""
    if "zoo:" not in text:
        return text
    from lcmodels.zoo import resolve_policy_spec

    try:
        return resolve_policy_spec(text)[0]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
