"""Running the benchmark: any driver on every scenario of a suite, on validation or sealed test episodes.

A *driver spec* is what ``lc-bench`` takes: ``zoo:NAME``, a ``policy.safetensors``, a built-in driver
(``rule``, ``oracle``, ...), ``safety-layer:POLICY`` (a policy behind the safety layer, with the settings of a
:class:`lcsim.planning.SafetyLayerConfig`; ``lookahead-blind:POLICY`` is an older spelling), or a
user's own policy as ``package.module:callable``: it is called with the batched gymnasium observation (a
dict of ``(E, ...)`` arrays: ``current``, ``history``, ``image``) and, when it takes a second argument, the
``(E, 3)`` action mask, and returns ``(E,)`` actions (0 right, 1 keep, 2 left).

A *cell* is one driver on one scenario on one set of episodes. Validation cells are cached as JSON in the
run's folder; sealed test cells are looked up in, or appended to, the ledger (:mod:`lcmodels.bench.ledger`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib
import inspect
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lcmodels.bench.ledger import (
    LETTER_OUTCOMES,
    append_entry,
    canonical,
    cell_key,
    counts,
    derived_problem,
    find_entry,
    outcome_string,
    read_ledger,
    with_derived_figures,
)
from lcmodels.fileio import file_sha256, read_json, write_json
from lcmodels.policy.driverspec import DriverSpec, as_driver_spec
from lcsim.planning import SafetyLayerConfig
from lcsim.suite import SuiteScenario, is_sealed

FINAL_BATCH = 20
"""Episodes simulated together in every sealed test evaluation."""
SHARD_EPISODES = 100
"""Episodes per shard of a cell run on workers or Ray: progress as shards end, the load balanced."""
logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class BenchDriver:
    """A driver spec resolved: what to run and what it is."""

    label: str
    """As the user named it (``zoo:hybrid-ppo``, ``rule``, ...)."""
    spec: DriverSpec
    """What drives, behind which layer, following what (:func:`lcmodels.policy.evaluate.driver_for` takes it)."""
    identity: dict[str, Any]
    """What it is, for the ledger: a policy's weights digest, recipe, training seed; a driver's name; ..."""
    about: dict[str, Any] = field(default_factory=dict)
    """What people call it (recipe, training seed, zoo name, ...): in the record, not in the key."""
    predictor: str | None = None

    @property
    def is_callable(self) -> bool:
        return self.identity.get("kind") == "callable"

    @property
    def group(self) -> str:
        """Runs of the same method (a recipe's training seeds, by the recipe's name) share a group; anything
        else is its own."""
        about = self.about
        if about.get("recipe"):  # (by name: a zoo card knows the recipe's version, an experiment's folder not)
            layer = " + safety layer" if self.identity.get("kind") == "safety-layer" else ""
            return f"{about['recipe']}{layer}"
        return self.label


def policy_identity(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """What a policy file is, as ``(identity, about)``: the identity is what decides how it drives (its
    weights' digest and its predictor's), ``about`` what people call it: algorithm, observation, training
    seed, and its recipe (from a zoo card beside it, or from ``lc-experiment``'s layout
    ``policies/<recipe>/seed<k>/<stage>/``)."""
    from lcmodels.policy.checkpoint import read_meta
    from lcmodels.zoo import ENTRY_CARD, weights_sha256

    meta = read_meta(path)
    train = meta.get("train_config") or {}
    predictor = (meta.get("predictor") or {}).get("sha256")
    ident = {"kind": "policy", "weights_sha256": weights_sha256(path), "predictor_sha256": predictor}
    about: dict[str, Any] = {"algo": meta.get("algo"), "obs_mode": meta.get("obs_mode"),
                             "training_seed": train.get("seed")}  # fmt: skip
    card = path.parent / ENTRY_CARD
    if card.is_file():
        zoo = read_json(card)
        about.update(recipe=zoo.get("recipe"), recipe_version=zoo.get("recipe_version"), zoo=zoo.get("name"))
        if zoo.get("training_seed") is not None:
            about["training_seed"] = zoo.get("training_seed")
    else:
        parts = path.resolve().parts
        if len(parts) >= 5 and parts[-5] == "policies" and parts[-3].startswith("seed"):
            about.update(recipe=parts[-4], stage=parts[-2])
            with contextlib.suppress(ValueError):
                about["training_seed"] = int(parts[-3].removeprefix("seed"))
    return ident, about


def resolve_driver(label: DriverSpec | str, *, safety: SafetyLayerConfig | None = None,
                   predictor: str | None = None) -> BenchDriver:
    """A driver (:class:`~lcmodels.policy.driverspec.DriverSpec`, or its words parsed here once with ``safety`` the
    layer in place of what they mean: the form stored records and scripts give) as :class:`BenchDriver`. A layer
    is identified in the ledger by the policy, its follower and :meth:`SafetyLayerConfig.ledger_settings
    <lcsim.planning.SafetyLayerConfig.ledger_settings>`. ``ValueError`` with one line for a name that is nothing
    known, a missing file, or settings that do not apply to it."""
    from lcsim.registry import DRIVER_NAMES

    spec = as_driver_spec(label, safety)
    text, layer = spec.text, spec.layer
    if spec.kind == "driver":
        if layer is None:
            return BenchDriver(text, spec, {"kind": "driver", "name": spec.name})
        ident: dict[str, Any] = {"kind": "driver", "name": "lookahead-blind" if layer.blind else "lookahead",
                                 "lookahead": layer.ledger_settings()}  # fmt: skip
        return BenchDriver(text, dataclasses.replace(spec, layer=dataclasses.replace(layer, follow=""), follow=None),
                           ident)  # fmt: skip
    if spec.kind == "callable":
        return BenchDriver(text, spec, {"kind": "callable", "name": text, "source_sha256": _source_digest(text)})
    path = spec.path
    if not path.is_file():
        what = "is a directory" if path.is_dir() else "does not exist"
        raise ValueError(f"{text}: {path} {what} (expected zoo:NAME, a policy.safetensors, a built-in driver "
                         f"({', '.join(DRIVER_NAMES)}) or package.module:callable)")
    try:
        policy, about = policy_identity(path)
    except Exception as exc:  # a foreign or corrupt file: whatever safetensors or torch raise, one line
        raise ValueError(f"{text}: {path} is not a readable policy file ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
    if layer is None:
        return BenchDriver(text, spec, policy, about, predictor=predictor or spec.predictor)
    follow_ident = None
    if spec.follow is not None:
        followed = resolve_driver(spec.follow)
        follow_ident = followed.identity
        about = {**about, "follow": followed.label, "follow_about": followed.about}
    ident = {"kind": "safety-layer", "policy": policy, "follow": follow_ident, "lookahead": layer.ledger_settings()}
    return BenchDriver(text, spec, ident, about, predictor=predictor or spec.predictor)


def _source_digest(spec: str) -> str | None:
    """SHA-256 of the source file of ``package.module:callable``'s module (``None`` when it has none)."""
    module = _import_callable(spec)[0]
    source = getattr(module, "__file__", None)
    return file_sha256(source) if source else None


def _import_callable(spec: str) -> tuple[Any, Callable[..., Any]]:
    name, _, attr = spec.partition(":")
    try:
        module = importlib.import_module(name)
    except Exception as exc:  # the user's module: a missing one, or one that fails while importing
        raise ValueError(f"{spec}: cannot import {name} ({type(exc).__name__}: {exc})") from None
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise ValueError(f"{spec}: {name} has no callable {attr}")
    if _with_mask(fn) is None:
        raise ValueError(f"{spec} takes {_signature(fn)}; a policy is called as fn(obs) or fn(obs, action_mask)")
    return module, fn


def _signature(fn: Callable[..., Any]) -> inspect.Signature | None:
    try:
        return inspect.signature(fn)
    except (TypeError, ValueError):  # a builtin without one: called as it is
        return None


def _with_mask(fn: Callable[..., Any]) -> bool | None:
    """Whether ``fn`` is called with the action mask too (it takes two positional arguments), False: with the
    observation alone; None: it takes neither."""
    sig = _signature(fn)
    if sig is None:
        return False
    positional = [p for p in sig.parameters.values() if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    for n in (2, 1) if len(positional) >= 2 else (1,):
        with contextlib.suppress(TypeError):
            sig.bind(*range(n))
            return n == 2
    return None


def _what(value: Any) -> str:
    """What a user's callable returned, in a few words (its type, and its shape and dtype when it has them)."""
    if isinstance(value, np.ndarray):
        values = f" from {value.min()} to {value.max()}" if value.size and value.dtype.kind in "iuf" else ""
        return f"an array of shape {value.shape} and dtype {value.dtype}{values}"
    if isinstance(value, list | tuple):
        kinds = sorted({type(v).__name__ for v in value[:1000]})
        return f"a {type(value).__name__} of {len(value)} item(s) ({', '.join(kinds[:3]) or 'empty'})"
    text = " ".join(repr(value).split())
    return f"{type(value).__name__} {text[:60]}{'...' if len(text) > 60 else ''}"


class CallableDriver:
    """A user's ``package.module:callable`` as a driver: ``fn(obs)`` or ``fn(obs, action_mask)`` -> ``(E,)``. What
    it raises or returns amiss is a ``ValueError`` in one line naming it (and what it returned)."""

    def __init__(self, spec: str) -> None:
        self.spec = spec
        self.fn = _import_callable(spec)[1]
        self.name = spec.replace(":", ".").replace("_", "-")
        self.with_mask = bool(_with_mask(self.fn))

    def __call__(self, obs: dict[str, np.ndarray], action_mask: np.ndarray, core: Any) -> np.ndarray:
        n = len(action_mask)
        try:
            actions = self.fn(obs, action_mask) if self.with_mask else self.fn(obs)
        except Exception as exc:  # the user's code: one line naming it, not a traceback through ours
            detail = " ".join(str(exc).split())[:160]
            raise ValueError(f"{self.spec} raised {type(exc).__name__}" + (f": {detail}" if detail else "")) from None
        try:
            out = np.asarray(actions).reshape(-1)
            ok = out.shape == (n,) and np.issubdtype(out.dtype, np.integer) and not ((out < 0) | (out > 2)).any()
        except Exception:  # a ragged list, an object numpy cannot take
            ok = False
        if not ok:
            raise ValueError(f"{self.spec} returned {_what(actions)}; expected ({n},) integers in 0..2 (0 right, "
                             "1 keep, 2 left)")
        return out.astype(np.int64)


def scenario_sha256(config: Any) -> str:
    """Digest of a scenario's config (a change of the scenario makes new ledger keys)."""
    return hashlib.sha256(config.to_json().encode()).hexdigest()


@dataclass
class Runner:
    """Where cells run: in this process, on a pool of ``workers`` processes, or on Ray."""

    workers: int = 1
    executor: str = "local"
    threads: int = 1
    batch: int = 20
    ray_address: str | None = None
    progress: Callable[[int, int], None] | None = None
    _pool: Any = None

    @contextlib.contextmanager
    def session(self) -> Iterator[Runner]:
        """Open the pool or the Ray session for the whole run, and close it after."""
        from lcdata.executors import ray_session
        from lcmodels.policy.evaluate import shard_pool

        if self.executor == "ray":
            with ray_session(self.ray_address):
                yield self
        elif self.workers > 1:
            with shard_pool(self.workers, self.threads) as pool:
                self._pool = pool
                try:
                    yield self
                finally:
                    self._pool = None
        else:
            yield self

    def run(self, driver: BenchDriver, config: Any, scenario: str, user_seeds: list[int], *,
            sealed: bool = False) -> dict[str, Any]:
        """The driver's episodes ``user_seeds`` in ``config``: counts, means and per-episode outcomes.
        ``sealed``: the final path's leave to run sealed test episodes (:func:`lcsim.suite.check_unsealed`)."""
        from lcmodels.policy.evaluate import driver_for, evaluate, evaluate_sharded

        start = time.perf_counter()
        extra: dict[str, Any] = {}
        if driver.identity["kind"] == "driver":  # a built-in driver reads no image: none is rendered
            config = dataclasses.replace(config, render_image=False)
        if driver.is_callable or driver.spec.name == "random" or (self.executor == "local" and self.workers <= 1):
            if driver.is_callable:
                built, run_config = CallableDriver(driver.spec.name), config
            else:
                built, own = driver_for(driver.spec, predictor=driver.predictor, scenario=config)
                run_config = own or config
            summary, results = evaluate(built, run_config, user_seeds=user_seeds, batch=self.batch,
                                        progress=self.progress, scenario=scenario, sealed=sealed)
            if hasattr(built, "overrides"):
                extra = {"planner_choices": built.choices, "planner_overrides": built.overrides}
        else:
            summary, results = evaluate_sharded(
                driver.spec, config, episodes=len(user_seeds), user_seeds=user_seeds,
                shards=max(self.workers, -(-len(user_seeds) // SHARD_EPISODES)), executor=self.executor,
                pool=self._pool, predictor=driver.predictor, scenario=scenario,
                batch=self.batch, progress=self.progress, sealed=sealed)  # fmt: skip
            extra = {k: summary[k] for k in ("planner_choices", "planner_overrides") if k in summary}
        outcomes = outcome_string(r.outcome for r in results)
        return {"outcomes": outcomes, **counts(outcomes),
                "mean_safe_forward_m": float(np.mean([r.safe_forward_m for r in results])),
                "mean_return": float(np.mean([r.ret for r in results])),
                "wall_s": round(time.perf_counter() - start, 1), **extra}


@dataclass(frozen=True)
class Cell:
    driver: BenchDriver
    scenario: SuiteScenario
    record: dict[str, Any]
    source: str
    """``ledger`` (found), ``ledger+`` (run and appended), ``cache`` (found in the run's folder), ``run``."""


def episodes_for(sc: SuiteScenario, *, final: bool, episodes: int, seed: int) -> list[int]:
    """The user seeds of a cell: the scenario's sealed test episodes, or ``episodes`` of evaluation seed ``seed``."""
    from lcmodels.policy.evaluate import eval_user_seeds

    return sc.sealed_seeds() if final else eval_user_seeds(episodes, seed)


def bench_cell(driver: BenchDriver, sc: SuiteScenario, runner: Runner, *, final: bool, episodes: int = 100,
               seed: int = 0, cache_dir: Path | None = None, ledger: Path | None = None,
               command: str = "") -> Cell:
    """One driver on one suite scenario: from the ledger or the cache when it is there, else run (and, on
    the sealed test episodes, appended to the ledger)."""
    config = sc.make()
    digest = scenario_sha256(config)
    seeds = episodes_for(sc, final=final, episodes=episodes, seed=seed)
    if final != all(is_sealed(u) for u in (seeds[0], seeds[-1])):
        raise AssertionError("validation cells never run sealed seeds, final cells only sealed seeds")
    if final and driver.is_callable:
        raise ValueError(f"{driver.label}: a callable has no weights to key the ledger by (retrained, it would keep "
                         "its entry); --final takes policy files, zoo entries and built-in drivers")
    if final and runner.batch != FINAL_BATCH:
        raise ValueError(f"--final runs {FINAL_BATCH} episodes at a time, as every ledger entry did (a few drivers' "
                         "draws follow the batch); drop --batch")
    # a validation cell also depends on the batch (the random driver's and some planners' draws follow it)
    key = cell_key(driver.identity if final else {**driver.identity, "batch": runner.batch}, digest, seeds)
    if final:
        found = find_entry(read_ledger(ledger), key)
        if found is not None:
            return Cell(driver, sc, found, "ledger")
    elif cache_dir is not None:
        cached = cached_cell(cache_dir / f"{key}.json", key, len(seeds))
        if cached is not None:
            return Cell(driver, sc, cached, "cache")
    result = runner.run(driver, config, sc.name, seeds, sealed=final)
    record = {"key": key, "label": driver.label, "group": driver.group, "identity": driver.identity,
              "about": driver.about,
              "scenario": sc.name, "scenario_sha256": digest, "user_seeds": [seeds[0], seeds[-1]],
              "split": "test" if final else f"validation seed {seed}", "batch": runner.batch, **result,
              "command": command}  # fmt: skip
    if final:
        entry, appended = append_entry(record, ledger)  # (another run may have appended the key meanwhile)
        return Cell(driver, sc, entry, "ledger+" if appended else "ledger")
    if cache_dir is not None:
        write_json(cache_dir / f"{key}.json", {"v": 1, **record})
    return Cell(driver, sc, record, "run")


def cached_cell(path: Path, key: str, episodes: int) -> dict[str, Any] | None:
    """The validation cell cached at ``path`` with its figures derived from its outcome letters, or None when
    there is none. A cell that is not what its name says (unreadable, not JSON, another key, other episodes, a key
    or a stored figure that disagrees with what it holds: :func:`lcmodels.bench.ledger.derived_problem`) is never
    served: a warning says why, and the cell is run again and written anew."""
    if not path.exists() and not path.is_symlink():
        return None
    cached = read_json(path) if path.is_file() else None
    problem = "not a readable JSON object"
    if isinstance(cached, dict):
        cached = {k: v for k, v in cached.items() if k != "v"}
        missing = [k for k in ("key", "identity", "scenario_sha256", "user_seeds", "outcomes", "batch") if k not in cached]
        outcomes = cached.get("outcomes")
        if missing:
            problem = f"missing {', '.join(missing)}"
        elif not isinstance(outcomes, str) or set(outcomes) - set(LETTER_OUTCOMES):
            problem = "outcomes must be a string of the letters s, c, o, t"
        elif cached["key"] != key or len(outcomes) != episodes:
            problem = f"holds {cached['key']!r} on {len(outcomes)} episodes, not {key} on {episodes}"
        else:
            problem = derived_problem(cached, batch_in_key=True)
        if not problem:
            return with_derived_figures(cached)
    logger.warning("cached cell %s: %s; discarded, run again", path, problem)
    return None


def identity_digest(identity: dict[str, Any]) -> str:
    return hashlib.sha256(canonical(identity).encode()).hexdigest()[:12]


__all__ = [
    "BenchDriver",
    "CallableDriver",
    "Cell",
    "Runner",
    "bench_cell",
    "cached_cell",
    "episodes_for",
    "policy_identity",
    "resolve_driver",
    "scenario_sha256",
]
