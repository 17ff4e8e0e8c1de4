"""The ledger of sealed test evaluations: one JSON line per evaluation, appended, never rewritten.

Every evaluation on the sealed test episodes (:mod:`lcsim.suite`) appends one entry: what was evaluated (its
identity: a policy's weights digest, recipe and training seed; a built-in driver's name; a safety layer's
policy, follower and settings), where (suite scenario and the digest of its config), on which episodes,
when and at which commit, and what happened in every episode (``outcomes``, one letter each, so that two
entries on the same episodes can be compared pairwise). An entry is found again by its ``key``, the digest
of identity, scenario and episodes: a policy already measured is not measured again, and a policy whose
weights changed gets a new key and a new line beside the old one, so re-rolls stay visible.

Reports, zoo cards and the README take their test figures from here; ``tests/test_published.py`` checks it.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
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


def ledger_path() -> Path:
    """``$LC_LEDGER``, else the checkout's :data:`CHECKOUT_LEDGER`."""
    return Path(os.environ.get("LC_LEDGER") or CHECKOUT_LEDGER)


def canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


def cell_key(identity: dict[str, Any], scenario_sha256: str, user_seeds: Sequence[int]) -> str:
    """The digest that names one evaluation: what, where, and on which episodes (first, last, count)."""
    seeds = [int(user_seeds[0]), int(user_seeds[-1]), len(user_seeds)] if len(user_seeds) else []
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
        out[f"{o}_wilson95"] = list(wilson_interval(k, n))
    return out


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
    """Every entry of the ledger (none when the file does not exist). ``ValueError`` naming the line for a
    line that is not a ledger entry, or for a file too large to be one."""
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
            entries.append(entry)
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
    if not isinstance(entry["episodes"], int) or entry["episodes"] != len(outcomes):
        return f"episodes {entry['episodes']!r} differs from the {len(outcomes)} outcomes"
    return ""


def find_entry(entries: Sequence[dict[str, Any]], key: str) -> dict[str, Any] | None:
    """The newest entry with ``key`` (there is one unless the same evaluation was appended twice by hand)."""
    found = [e for e in entries if e["key"] == key]
    return found[-1] if found else None


def append_entry(entry: dict[str, Any], path: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Append one entry (a line of JSON) to the ledger, stamping its version, date and commit. Returns it."""
    path = Path(path) if path is not None else ledger_path()
    commit, dirty = git_commit()  # the code that evaluated: this package's checkout
    full = {"v": LEDGER_VERSION, **entry,
            "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), "commit": commit,
            "dirty": dirty}  # fmt: skip
    problem = _entry_problem(full)
    if problem:
        raise ValueError(f"not a ledger entry: {problem}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", encoding="utf-8") as f:
        f.write(canonical(full) + "\n")
        f.flush()
        os.fsync(f.fileno())
    return full


__all__ = [
    "CHECKOUT_LEDGER",
    "LEDGER_VERSION",
    "append_entry",
    "cell_key",
    "counts",
    "find_entry",
    "git_commit",
    "ledger_path",
    "outcome_string",
    "read_ledger",
]
