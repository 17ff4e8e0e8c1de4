"""The ledger verified by replay: the simulator is deterministic, so anyone can run a line's episodes again with
the driver it names and compare the outcome letters (``lc-bench --verify``).

For each line: the driver is rebuilt from the line's identity (a built-in driver and its settings; a policy's
weights found by their digest, first where the line's label points, then among the weights the checkout keeps
under ``zoo/`` and ``docs/results/``; a safety layer's policy, follower and settings), its rebuilt identity must be
the line's, and the road's config must still have the line's digest; a deterministic random sample of its
episodes (or all of them) is run again, ``batch`` at a time as the line was, and each episode's letter compared.
A file whose weights differ from the digest the line names is refused, never run in its place. A line that
cannot be rebuilt is *not checkable*, with the reason; a letter that differs is a *mismatch*.
"""

from __future__ import annotations

import dataclasses
import random
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lcmodels.bench.run import FINAL_BATCH, BenchDriver, Runner, resolve_driver, scenario_sha256

ROOT = Path(__file__).resolve().parents[2]
WEIGHTS_FOLDERS = ("zoo", "docs/results")
"""Where the checkout keeps policies' weights (relative to its root), searched by digest."""
DEFAULT_EPISODES = 10
"""Episodes replayed per line unless told otherwise."""


@dataclass(frozen=True)
class Verdict:
    """What the replay of one ledger line found."""

    key: str
    what: str
    """The line's driver and road, as people read them."""
    status: str
    """``ok``, ``mismatch`` or ``not checkable``."""
    checked: int = 0
    episodes: int = 0
    detail: str = ""
    """Why it is not checkable, or the first episode whose letter differs."""
    wall_s: float = 0.0

    def line(self) -> str:
        head = f"{self.key} {self.what}"
        if self.status == "ok":
            return f"{head}: checked {self.checked}/{self.episodes} episodes, ok ({self.wall_s:.1f} s)"
        if self.status == "mismatch":
            return f"{head}: MISMATCH: {self.detail}"
        return f"{head}: not checkable: {self.detail}"


def sample_episodes(entry: dict[str, Any], episodes: int | None, seed: int = 0) -> list[int]:
    """The indices of the episodes of ``entry`` to replay: all of them when ``episodes`` is None or not fewer than
    the line's, else ``episodes`` drawn without replacement by a generator seeded with ``seed`` and the line's key
    (the same sample on every machine), in order."""
    n = int(entry["episodes"])
    if episodes is None or episodes >= n:
        return list(range(n))
    return sorted(random.Random(f"{seed}:{entry['key']}").sample(range(n), episodes))


class WeightsIndex:
    """The policies' weights the checkout keeps, by digest: ``zoo:NAME`` for a zoo entry's (a zoo entry drives
    with the zoo's predictor), else the file's path. Hashed once, when first asked."""

    def __init__(self, roots: Sequence[Path] | None = None) -> None:
        self.roots = [ROOT / f for f in WEIGHTS_FOLDERS] if roots is None else list(roots)
        self._specs: dict[str, str] | None = None

    def spec(self, digest: str) -> str | None:
        if self._specs is None:
            self._specs = self._scan()
        return self._specs.get(digest)

    def _scan(self) -> dict[str, str]:
        from lcmodels.zoo import weights_sha256, zoo_entries

        specs: dict[str, str] = {}
        for root in self.roots:
            if root.is_dir():
                for path in sorted(root.rglob("*.safetensors")):
                    if path.is_file() and not path.is_symlink():
                        try:
                            specs.setdefault(weights_sha256(path), str(path))
                        except Exception:  # a file that is not one: no weights to index
                            continue
        try:
            for e in zoo_entries():
                specs[e.weights_sha256] = f"zoo:{e.name}"
        except (ValueError, OSError):
            pass
        return specs


def _as_path(spec: str) -> str:
    """A spec's file relative to the checkout's root, as ``lc-bench`` was run from there."""
    if spec.startswith("zoo:") or Path(spec).is_absolute():
        return spec
    return str(ROOT / spec)


def _digest_of(spec: str) -> str | None:
    """The weights digest of the policy file ``spec`` names (``zoo:NAME`` or a path), None when there is none."""
    from lcmodels.policy.driverspec import resolve_policy_spec
    from lcmodels.policy.evaluate import policy_path_of
    from lcmodels.zoo import weights_sha256

    try:
        path = policy_path_of(resolve_policy_spec(_as_path(spec))[0])
        return weights_sha256(path) if path.is_file() else None
    except Exception:  # a missing zoo entry, a file that is not a policy: none
        return None


def _policy_spec(identity: dict[str, Any], hint: str | None, index: WeightsIndex) -> tuple[str | None, str]:
    """``(spec, "")`` of a file holding the weights ``identity`` names (``hint``, the line's own spelling, first),
    or ``(None, why)``."""
    digest = identity.get("weights_sha256")
    if not isinstance(digest, str):
        return None, "the line names no weights digest"
    refused = ""
    if hint:
        have = _digest_of(hint)
        if have == digest:
            return _as_path(hint), ""
        if have is not None:
            refused = f"; {hint} holds other weights ({have[:12]}), refused"
    found = index.spec(digest)
    if found is not None:
        return found, ""
    return None, f"weights not present (weights_sha256 {digest[:12]}, named {hint or 'nowhere'}{refused})"


def _layer(settings: Any, follow: str = "") -> Any:
    from lcsim.planning import SafetyLayerConfig
    from lcsim.planning.safety import REFERENCE

    return SafetyLayerConfig(**{**REFERENCE, **dict(settings or {})}, follow=follow)


def replay_driver(entry: dict[str, Any], index: WeightsIndex) -> tuple[BenchDriver | None, str]:
    """``(driver, "")``: the driver ``entry`` names, rebuilt, with the line's identity; or ``(None, why)``."""
    from lcmodels.policy.driverspec import split_safety_layer
    from lcsim.registry import DRIVER_NAMES

    ident = entry["identity"]
    label = str(entry.get("label") or "")
    kind = ident.get("kind")
    try:
        if kind == "driver":
            name = ident.get("name")
            if "lookahead" in ident:
                driver = resolve_driver("safety-layer:rule", safety=_layer(ident["lookahead"]))
            elif name in DRIVER_NAMES:
                driver = resolve_driver(str(name))
            else:
                return None, f"no built-in driver {name!r} in this version"
        elif kind == "policy":
            spec, why = _policy_spec(ident, split_safety_layer(label)[0] if label else None, index)
            if spec is None:
                return None, why
            driver = resolve_driver(spec)
        elif kind == "safety-layer":
            about = entry.get("about") or {}
            spec, why = _policy_spec(ident.get("policy") or {}, split_safety_layer(label)[0] if label else None,
                                     index)  # fmt: skip
            if spec is None:
                return None, why
            follow = ident.get("follow")
            follow_spec = ""
            if isinstance(follow, dict) and follow.get("kind") == "policy":
                follow_spec, why = _policy_spec(follow, about.get("follow"), index)
                if follow_spec is None:
                    return None, f"its follower's {why}"
            elif isinstance(follow, dict) and follow.get("kind") == "driver":
                follow_spec = str(follow.get("name"))
            driver = resolve_driver(f"safety-layer:{spec}", safety=_layer(ident.get("lookahead"), follow_spec))
        elif kind == "callable":
            return None, "a user's callable: the ledger keeps no code to run"
        else:
            return None, f"an identity of kind {kind!r} this version does not know"
    except (ValueError, OSError, TypeError) as exc:
        return None, f"its driver cannot be rebuilt ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
    if driver.identity != ident:
        return None, "the driver rebuilt from it has another identity (this version identifies drivers otherwise)"
    return driver, ""


def verify_entry(entry: dict[str, Any], runner: Runner, *, episodes: int | None = DEFAULT_EPISODES, seed: int = 0,
                 index: WeightsIndex | None = None) -> Verdict:
    """Replay :func:`sample_episodes` of ledger line ``entry`` (all with ``episodes=None``) and compare letters."""
    from lcsim.suite import SUITE_SCENARIOS

    key, n = entry["key"], int(entry["episodes"])
    what = f"{entry.get('label') or entry['identity'].get('name') or '?'} on {entry['scenario']}"
    sc = SUITE_SCENARIOS.get(entry["scenario"])
    if sc is None:
        return Verdict(key, what, "not checkable", episodes=n, detail=f"no suite road {entry['scenario']!r} here")
    if scenario_sha256(sc.make()) != entry["scenario_sha256"]:
        return Verdict(key, what, "not checkable", episodes=n,
                       detail=f"road {sc.name}'s config has changed since (its digest differs from the line's)")
    driver, why = replay_driver(entry, index or WeightsIndex())
    if driver is None:
        return Verdict(key, what, "not checkable", episodes=n, detail=why)
    picked = sample_episodes(entry, episodes, seed)
    if driver.spec.name == "random" and len(picked) < n:
        return Verdict(key, what, "not checkable", episodes=n,
                       detail="the random driver's draws follow its calls: only all its episodes replay it")
    first = int(entry["user_seeds"][0])
    start = time.perf_counter()
    batch = entry.get("batch") if type(entry.get("batch")) is int and entry["batch"] > 0 else FINAL_BATCH
    # the ledger's own episodes: the benchmark's leave to run sealed ones
    got = dataclasses.replace(runner, batch=batch).run(driver, sc.make(), sc.name, [first + i for i in picked],
                                                       sealed=True)["outcomes"]  # fmt: skip
    wall = time.perf_counter() - start
    differ = [(i, g) for i, g in zip(picked, got, strict=True) if entry["outcomes"][i] != g]
    if differ:
        i, g = differ[0]
        return Verdict(key, what, "mismatch", len(picked), n, wall_s=wall,
                       detail=f"episode {i} (user seed {first + i}): the ledger says {entry['outcomes'][i]!r}, the "
                       f"replay {g!r} ({len(differ)} of {len(picked)} replayed episodes differ)")
    return Verdict(key, what, "ok", len(picked), n, wall_s=wall)


def verify_ledger(entries: Sequence[dict[str, Any]], runner: Runner, *, episodes: int | None = DEFAULT_EPISODES,
                  seed: int = 0, index: WeightsIndex | None = None,
                  before: Callable[[dict[str, Any]], None] | None = None) -> Iterator[Verdict]:
    """:func:`verify_entry` of every entry, one :class:`Verdict` after another (``before(entry)`` first)."""
    index = index or WeightsIndex()
    for entry in entries:
        if before is not None:
            before(entry)
        yield verify_entry(entry, runner, episodes=episodes, seed=seed, index=index)


def select_entries(entries: Sequence[dict[str, Any]], keys: Sequence[str]) -> list[dict[str, Any]]:
    """The entries named by ``keys`` (a key or a prefix of at least 6 characters naming one line), in the
    ledger's order; every entry when ``keys`` is empty. ``ValueError`` naming a key that names none or several."""
    if not keys:
        return list(entries)
    chosen: set[str] = set()
    for k in keys:
        hits = {e["key"] for e in entries if e["key"] == k or (len(k) >= 6 and e["key"].startswith(k))}
        if len(hits) != 1:
            raise ValueError(f"{k!r} names {'no' if not hits else 'more than one'} ledger line"
                             + ("" if hits or len(k) >= 6 else " (a key, or 6 or more of its first characters)"))
        chosen |= hits
    return [e for e in entries if e["key"] in chosen]


__all__ = [
    "DEFAULT_EPISODES",
    "Verdict",
    "WeightsIndex",
    "replay_driver",
    "sample_episodes",
    "select_entries",
    "verify_entry",
    "verify_ledger",
]
