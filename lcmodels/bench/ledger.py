"""The ledger of sealed test evaluations: one JSON line per evaluation, appended, never rewritten.

Every evaluation on the sealed test episodes (:mod:`lcsim.suite`) appends one entry: what was evaluated (its
identity: a policy's weights digest, recipe and training seed; a built-in driver's name; a safety layer's
policy, follower and settings), where (suite scenario and the digest of its config), on which episodes,
when and at which commit, and what happened in every episode (``outcomes``, one letter each, so that two
entries on the same episodes can be compared pairwise). An entry is found again by its ``key``, the digest
of identity, scenario and episodes: a policy already measured is not measured again, and a policy whose
weights changed gets a new key and a new line beside the old one, so re-rolls stay visible.

The file is append-only (``tests/test_ledger.py`` holds its history to that) and nothing stored in a line is
trusted: :func:`read_ledger` re-derives every line's key from its identity, scenario digest and episodes, and its
counts, rates and Wilson intervals from its outcome letters, refuses a line whose stored ones disagree, and serves
the derived ones. ``lc-bench --verify`` (:mod:`lcmodels.bench.verify`) replays a line's episodes and compares the
letters themselves.

Reports, zoo cards and the README take their test figures from here; ``tests/test_published.py`` checks it.
"""

from __future__ import annotations

import datetime as _dt
import functools
import hashlib
import json
import math
import os
import subprocess
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from lcmodels.stats import wilson_interval
from lcsim.core import OUTCOMES

LEDGER_VERSION = 1
CHECKOUT_LEDGER = Path(__file__).resolve().parents[2] / "docs" / "results" / "benchmark" / "ledger.jsonl"
"""The ledger a source checkout commits."""
OUTCOME_LETTERS = {"success": "s", "collision": "c", "off_road": "o", "timeout": "t"}
LETTER_OUTCOMES = {v: k for k, v in OUTCOME_LETTERS.items()}
MAX_LEDGER_BYTES = 256 * 1024 * 1024
"""A ledger larger than this is refused before it is read (a few thousand entries take a few MB)."""
_REQUIRED = ("v", "key", "identity", "scenario", "scenario_sha256", "episodes", "user_seeds", "outcomes")
NOT_COMMITTED = "not from the committed ledger"
"""How every figure read from, or appended to, another ledger than :data:`CHECKOUT_LEDGER` is marked."""
LOCK_WAIT_S = 60.0
"""How long an append waits for another run appending to the same ledger."""


def ledger_path() -> Path:
    """``$LC_LEDGER``, else the checkout's :data:`CHECKOUT_LEDGER`."""
    return Path(os.environ.get("LC_LEDGER") or CHECKOUT_LEDGER)


def is_committed(path: str | os.PathLike[str] | None = None) -> bool:
    """Whether ``path`` (default :func:`ledger_path`) is the checkout's committed ledger."""
    path = Path(path) if path is not None else ledger_path()
    try:
        return path.resolve() == CHECKOUT_LEDGER.resolve()
    except OSError:
        return False


def canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


def cell_key(identity: dict[str, Any], scenario_sha256: str, user_seeds: Sequence[int]) -> str:
    """The digest that names one evaluation: what, where, and on which episodes (first, last, count)."""
    seeds = [int(user_seeds[0]), int(user_seeds[-1]), len(user_seeds)] if len(user_seeds) else []
    return _key(identity, scenario_sha256, seeds)


def _key(identity: Any, scenario_sha256: Any, seeds: list[int]) -> str:
    return hashlib.sha256(canonical([identity, scenario_sha256, seeds]).encode()).hexdigest()[:20]


def outcome_string(outcomes: Iterable[str]) -> str:
    """Per-episode outcomes as letters (``s`` success, ``c`` collision, ``o`` off road, ``t`` timeout)."""
    return "".join(OUTCOME_LETTERS[o] for o in outcomes)


def counts(outcomes: str) -> dict[str, Any]:
    """Counts, rates and Wilson 95% intervals over episodes of an outcome string."""
    n = len(outcomes)
    out: dict[str, Any] = {"episodes": n}
    for o in OUTCOMES:
        k = outcomes.count(OUTCOME_LETTERS[o])
        out[o] = k
        out[f"{o}_rate"] = k / n if n else float("nan")
        out[f"{o}_wilson95"] = list(_wilson(k, n))
    return out


@functools.lru_cache(maxsize=4096)
def _wilson(k: int, n: int) -> tuple[float, float]:
    return wilson_interval(k, n)  # (every reading of the ledger derives them: the same few hundred, once)


FIGURES = ("episodes", *(f"{o}{suffix}" for o in OUTCOMES for suffix in ("", "_rate", "_wilson95")))
"""The fields :func:`counts` derives from the outcome letters (a stored one is checked, never served)."""


def _show(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    return repr(value)


def _same(stored: Any, derived: Any) -> bool:
    if isinstance(derived, list):
        return (isinstance(stored, list) and len(stored) == len(derived)
                and all(_same(a, b) for a, b in zip(stored, derived, strict=True)))  # fmt: skip
    if isinstance(derived, int):
        return type(stored) is int and stored == derived
    if isinstance(stored, bool) or not isinstance(stored, int | float):
        return False
    if math.isnan(derived):
        return math.isnan(stored)
    return math.isclose(stored, derived, rel_tol=1e-9, abs_tol=1e-12)


def derived_problem(entry: dict[str, Any], *, batch_in_key: bool = False) -> str:
    """Why a record (a ledger line, or with ``batch_in_key`` a validation cell cached by ``lc-bench``) cannot be
    served, in a few words (``""``: it can): its episodes are not one run of consecutive user seeds, its key is
    not the digest of its identity, scenario digest and episodes, or a stored figure differs from what its
    outcome letters give. ``entry`` has the fields of a well-formed line (:func:`read_ledger` checks those)."""
    seeds = entry["user_seeds"]
    n = len(entry["outcomes"])
    if n == 0:
        return "no outcomes"
    if (not isinstance(seeds, list) or len(seeds) != 2 or not all(type(u) is int for u in seeds)
            or seeds[1] - seeds[0] + 1 != n):  # fmt: skip
        return f"user_seeds {seeds!r} are not the first and last of its {n} episodes"
    identity = entry["identity"]
    if batch_in_key:
        if not isinstance(identity, dict):
            return "identity is not a JSON object"
        identity = {**identity, "batch": entry.get("batch")}
    key = _key(identity, entry["scenario_sha256"], [seeds[0], seeds[1], n])
    if entry["key"] != key:
        return (f"its key disagrees with its identity, scenario digest and episodes (they give {key}): an edited "
                "line")
    derived = counts(entry["outcomes"])
    for field in FIGURES:
        if field in entry and not _same(entry[field], derived[field]):
            return (f"stored {field} {_show(entry[field])} disagrees with its outcome letters "
                    f"({_show(derived[field])})")
    return ""


def with_derived_figures(entry: dict[str, Any]) -> dict[str, Any]:
    """``entry`` with every figure :func:`counts` gives derived anew from its outcome letters."""
    return {**entry, **counts(entry["outcomes"])}


CODE_PATHS = ("lcsim", "lcdata", "lcmodels", "lccli", "pyproject.toml", ":(glob)zoo/**/*.safetensors",
              ":(glob)zoo/**/*.pt")
"""What decides an evaluation's figures: a change here since the commit makes an entry ``dirty`` (the zoo's
weights, not its cards, which ``tools/publish_ledger.py`` writes)."""


def git_commit(root: Path | None = None) -> tuple[str | None, bool]:
    """``(short commit, whether the code (:data:`CODE_PATHS`) differs from it)`` of the checkout, ``(None,
    False)`` outside one."""
    cwd = root or CHECKOUT_LEDGER.parents[3]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=cwd, capture_output=True, text=True,
                              check=False, timeout=20)  # fmt: skip
        if head.returncode != 0:
            return None, False
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", *CODE_PATHS],
                               cwd=cwd, capture_output=True, text=True, check=False, timeout=20)  # fmt: skip
        return head.stdout.strip() or None, bool(dirty.stdout.strip())
    except (OSError, subprocess.SubprocessError):
        return None, False


def read_ledger(path: str | os.PathLike[str] | None = None) -> list[dict[str, Any]]:
    """Every entry of the ledger (none when the file does not exist), its figures derived from its outcome
    letters (:func:`with_derived_figures`). ``ValueError`` in one line naming the line for a line that is not a
    ledger entry, whose key or stored figures disagree with what it holds (:func:`derived_problem`), or for a
    file too large to be a ledger."""
    path = Path(path) if path is not None else ledger_path()
    if not path.exists():
        return []
    if not path.is_file():
        raise ValueError(f"ledger {path} is not a file")
    size = path.stat().st_size
    if size > MAX_LEDGER_BYTES:
        raise ValueError(f"ledger {path} is {size} bytes, more than the {MAX_LEDGER_BYTES} a ledger may be")
    entries = []
    with path.open(encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                entry = json.loads(line)
            except json.JSONDecodeError as exc:
                raise ValueError(f"ledger {path}, line {number}: not JSON ({exc.msg})") from None
            problem = _entry_problem(entry)
            if problem:
                raise ValueError(f"ledger {path}, line {number}: {problem}")
            problem = derived_problem(entry)
            if problem:
                raise ValueError(f"ledger line {entry['key']}: {problem}")
            entries.append(with_derived_figures(entry))
    return entries


def _entry_problem(entry: Any) -> str:
    if not isinstance(entry, dict):
        return "not a JSON object"
    missing = [k for k in _REQUIRED if k not in entry]
    if missing:
        return f"missing {', '.join(missing)}"
    if entry["v"] != LEDGER_VERSION:
        return f"ledger version {entry['v']!r}, this code reads {LEDGER_VERSION}"
    outcomes = entry["outcomes"]
    if not isinstance(outcomes, str) or set(outcomes) - set(LETTER_OUTCOMES):
        return "outcomes must be a string of the letters s, c, o, t"
    if type(entry["episodes"]) is not int or entry["episodes"] != len(outcomes):
        return f"episodes {entry['episodes']!r} differs from the {len(outcomes)} outcomes"
    if not isinstance(entry["key"], str) or not isinstance(entry["scenario_sha256"], str):
        return "key and scenario_sha256 must be strings"
    if not isinstance(entry["identity"], dict):
        return "identity must be a JSON object"
    return ""


def find_entry(entries: Sequence[dict[str, Any]], key: str) -> dict[str, Any] | None:
    """The newest entry with ``key`` (there is one unless the same evaluation was appended twice by hand)."""
    found = [e for e in entries if e["key"] == key]
    return found[-1] if found else None


def lock_name(path: Path) -> str:
    """The lock file beside ledger ``path`` that appends hold (:func:`append_entry`)."""
    return f".{path.name}.lock"


def append_entry(entry: dict[str, Any], path: str | os.PathLike[str] | None = None) -> tuple[dict[str, Any], bool]:
    """Append one entry (a line of JSON) to the ledger, stamping its version, date and commit, unless its key is
    there already: the ledger is read again under an exclusive lock beside it (:func:`lckit.fileio.folder_lock`,
    the one ``lc-record`` holds), so two runs at once never append one key twice. Returns ``(the ledger's entry
    of that key, whether this call appended it)``."""
    from lckit.fileio import check_target, folder_lock

    path = Path(path) if path is not None else ledger_path()
    commit, dirty = git_commit()  # the code that evaluated: this package's checkout
    full = {"v": LEDGER_VERSION, **entry,
            "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), "commit": commit,
            "dirty": dirty}  # fmt: skip
    problem = _entry_problem(full) or derived_problem(full)
    if problem:
        raise ValueError(f"not a ledger entry: {problem}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with folder_lock(path.parent, "lc-bench --final", lock_name(path), doing="is appending to the ledger in",
                     wait_s=LOCK_WAIT_S):  # fmt: skip
        found = find_entry(read_ledger(path), full["key"])
        if found is not None:  # another run measured it meanwhile: its line stands
            return found, False
        check_target(path)  # appended to where it is, never through a link
        flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
        with os.fdopen(os.open(path, flags, 0o644), "a", encoding="utf-8") as f:
            f.write(canonical(full) + "\n")
            f.flush()
            os.fsync(f.fileno())
    return with_derived_figures(full), True


__all__ = [
    "CHECKOUT_LEDGER",
    "LEDGER_VERSION",
    "NOT_COMMITTED",
    "append_entry",
    "cell_key",
    "counts",
    "derived_problem",
    "find_entry",
    "git_commit",
    "is_committed",
    "ledger_path",
    "lock_name",
    "outcome_string",
    "read_ledger",
    "with_derived_figures",
]
