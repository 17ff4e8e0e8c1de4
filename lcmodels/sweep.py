"""Sweeps: a grid of policy-config values times training seeds, each trial a training run with its held-out
evaluation, gathered into one table sorted by held-out success (``lc-tune``).

A sweep file (TOML or JSON)::

    seeds = [0, 1]              # training seeds of every grid point
    [base]                      # PolicyConfig fields every trial shares
    obs = "pure"
    scenario = "light"
    timesteps = 200000
    [grid]                      # each field: the values to try; every combination is a grid point
    gamma = [0.9, 0.95]
    window_features = [false, true]

Trials run one after the other here (``executor="local"``) or as Ray Tune trials (``"ray"``), each in
``DIR/trials/<name>`` (an ``lc-train-policy`` run directory: a rerun skips the finished ones and resumes
the others). ``DIR/SWEEP.md`` and ``DIR/sweep.json`` hold the table.

A sweep holds at most :data:`MAX_TRIALS` trials (grid points times seeds, counted before any is made). A
trial's name is its grid values (``gamma=0.9_window_features=false_seed0``); one with a character a folder
name should not have (a path separator, ``..``, a quote), or longer than :data:`MAX_NAME_CHARS`, has them
replaced and a short hash of its values added, so that every trial stays in ``DIR/trials/``, apart.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lckit.config import read_data_file
from lckit.fileio import check_inside, make_folder, write_file
from lcmodels.fileio import write_json
from lcmodels.policy.config import PolicyConfig

SWEEP_JSON = "sweep.json"
SWEEP_MD = "SWEEP.md"
MAX_TRIALS = 1000
"""The most trials a sweep may hold (grid points times seeds), each a training run: checked before any is made."""
MAX_NAME_CHARS = 100
"""The longest trial folder name kept as it is (a longer one is cut and given a hash of its values)."""
_NAME_CHARS = re.compile(r"[A-Za-z0-9._=+,\[\] -]")
"""What a trial's name may hold as it is: its values' letters, digits and the marks JSON lists and numbers use."""


@dataclass(frozen=True)
class Sweep:
    """The trials of a sweep file: the shared config, the grid and the seeds."""

    base: dict[str, Any]
    grid: dict[str, list[Any]]
    seeds: list[int]

    @classmethod
    def from_file(cls, path: str | os.PathLike[str]) -> Sweep:
        """``ValueError`` naming the file and the problem: an unknown field, an empty grid axis, a config the
        policy refuses."""
        path = Path(path)
        data = read_data_file(path, "sweep file")
        unknown = set(data) - {"base", "grid", "seeds"}
        if unknown:
            raise ValueError(f"{path}: unknown top-level key(s) {sorted(unknown)} (base, grid, seeds)")
        base, grid = data.get("base", {}), data.get("grid", {})
        seeds = data.get("seeds", [0])
        if not isinstance(base, dict) or not isinstance(grid, dict):
            raise ValueError(f"{path}: base and grid must be tables")
        if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) and s >= 0 for s in seeds):
            raise ValueError(f"{path}: seeds must be a non-empty list of integers >= 0, got {seeds!r}")
        for key, values in grid.items():
            if not isinstance(values, list) or not values:
                raise ValueError(f"{path}: grid.{key} must be a non-empty list of values, got {values!r}")
        count = math.prod(len(v) for v in grid.values()) * len(seeds)
        if count > MAX_TRIALS:
            raise ValueError(f"{path}: {count} trials ({' x '.join(str(len(v)) for v in grid.values()) or '1'} grid "
                             f"points x {len(seeds)} seeds); a sweep holds at most {MAX_TRIALS}")
        sweep = cls(base, {k: list(v) for k, v in grid.items()}, list(seeds))
        seen: set[str] = set()
        for name, _ in sweep.trials():  # every trial is a valid config with a folder of its own, or refused now
            if name in seen:
                raise ValueError(f"{path}: two trials would share the folder trials/{name} (grid values that read "
                                 "alike); give each value once")
            seen.add(name)
        return sweep

    def trials(self) -> list[tuple[str, PolicyConfig]]:
        """``(name, config)`` of every trial: grid points in file order, each with every seed (the name is
        :func:`trial_name`'s)."""
        out = []
        keys = list(self.grid)
        for values in itertools.product(*(self.grid[k] for k in keys)):
            point = dict(zip(keys, values, strict=True))
            for seed in self.seeds:
                name = trial_name(point)
                try:
                    cfg = PolicyConfig.from_dict({**self.base, **point, "seed": seed}, stored=False)
                except ValueError as exc:
                    raise ValueError(f"trial {name}, seed {seed}: {exc}") from None
                out.append((f"{name}_seed{seed}", cfg))
        return out


def trial_name(point: dict[str, Any]) -> str:
    """The folder name of grid point ``point`` (without its seed): ``key=value`` joined by ``_`` (``base`` for no
    grid), as it is when it holds only :data:`_NAME_CHARS`, no ``..``, and at most :data:`MAX_NAME_CHARS`;
    else the other characters replaced by ``-``, cut, and the first 8 hex digits of its SHA-256 added."""
    name = "_".join(f"{k}={_label(v)}" for k, v in point.items()) or "base"
    if len(name) <= MAX_NAME_CHARS and ".." not in name and all(_NAME_CHARS.match(c) for c in name):
        return name
    safe = re.sub(r"-{2,}", "-", "".join(c if _NAME_CHARS.match(c) else "-" for c in name).replace("..", "-"))
    return f"{safe[: MAX_NAME_CHARS - 9].strip(' .-') or 'trial'}-{hashlib.sha256(name.encode()).hexdigest()[:8]}"


def _absolute_paths(cfg: PolicyConfig) -> PolicyConfig:
    """``cfg`` with its file paths (a scenario file, demonstrations, an initial policy) made absolute: a Ray
    Tune trial runs in a working directory of its own."""
    import dataclasses

    from lcsim.registry import SCENARIOS

    changes = {k: str(Path(v).resolve()) for k, v in (("warm_start", cfg.warm_start), ("init_policy", cfg.init_policy))
               if v}  # fmt: skip
    if cfg.scenario not in SCENARIOS:
        changes["scenario"] = str(Path(cfg.scenario).resolve())
    return dataclasses.replace(cfg, **changes)


def _label(v: Any) -> str:
    return json.dumps(v) if isinstance(v, list | dict) else str(v).lower() if isinstance(v, bool) else str(v)


def _trial(name: str, cfg_json: str, out: str, predictor: str | None, threads: int) -> dict[str, Any]:
    """One trial: the training run and its held-out evaluation in ``out/trials/name``."""
    import torch

    from lcmodels.policy.train import train_policy

    torch.set_num_threads(threads)
    cfg = PolicyConfig.from_json(cfg_json)
    res = train_policy(cfg, Path(out) / "trials" / name, predictor=predictor if _needs(cfg) else None)
    ev = res.metrics.get("eval", {})
    return {"trial": name, "policy_config": cfg.to_dict(), "timesteps": res.timesteps, "train_wall_s": res.wall_s,
            **{k: ev.get(k) for k in ("episodes", "success_rate", "success_rate_ci95", "collision_rate",
                                      "collision_rate_ci95", "mean_return")}}  # fmt: skip


def _needs(cfg: PolicyConfig) -> bool:
    from lcmodels.policy.names import needs_predictor

    return needs_predictor(cfg.obs)


def _tune_trial(config: dict[str, Any]) -> None:
    """A Ray Tune trainable: one trial, its figures reported to Tune."""
    from ray import tune

    name = config["name"]
    tune.report(_trial(name, config["configs"][name], config["out"], config["predictor"], config["threads"]))


def run_sweep(sweep: Sweep, out: str | os.PathLike[str], *, predictor: str | None = None, threads: int = 1,
              executor: str = "local", ray_address: str | None = None,
              progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Run every trial (skipping finished ones), write the table, return its rows sorted by held-out success."""
    out = Path(out)
    trials = sweep.trials()
    if any(_needs(cfg) for _, cfg in trials) and predictor is None:
        raise ValueError("the sweep has prediction or hybrid trials: give the predictor (--predictor)")
    out.mkdir(parents=True, exist_ok=True)
    make_folder(out / "trials", out)
    for name, _ in trials:  # a trial's folder is in trials/, never reached through a link out of --out
        check_inside(out / "trials" / name, out / "trials")
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    if executor == "ray":
        from lcdata.executors import ray_session

        with ray_session(ray_address):
            from ray import tune

            configs = {n: _absolute_paths(cfg).to_json() for n, cfg in trials}  # trials run in their own folders
            space = {"name": tune.grid_search(list(configs)), "configs": configs, "out": str(out.resolve()),
                     "predictor": None if predictor is None else str(Path(predictor).resolve()),
                     "threads": threads}  # fmt: skip
            tuner = tune.Tuner(tune.with_resources(_tune_trial, {"cpu": threads}), param_space=space,
                               run_config=tune.RunConfig(storage_path=str((out / "ray_results").resolve()),
                                                         name="sweep", verbose=0))  # fmt: skip
            grid = tuner.fit()
            for result in grid:
                if result.error is not None:
                    raise ValueError(f"a Ray Tune trial failed: {' '.join(str(result.error).split())[:200]}")
                rows.append({k: v for k, v in result.metrics.items() if k in _ROW_KEYS})
    elif executor == "local":
        for k, (name, cfg) in enumerate(trials, 1):
            rows.append(_trial(name, cfg.to_json(), str(out), predictor, threads))
            if progress is not None:
                progress(f"[{name}] {k}/{len(trials)}: success {100 * (rows[-1]['success_rate'] or 0):.1f}%")
    else:
        raise ValueError(f"executor must be local or ray, got {executor!r}")
    rows.sort(key=lambda r: (r["success_rate"] is None, -(r["success_rate"] or 0.0), r["trial"]))
    write_json(out / SWEEP_JSON, {"trials": rows, "wall_s": time.perf_counter() - t0,
                                  "seeds": sweep.seeds, "grid": sweep.grid, "base": sweep.base}, root=out)  # fmt: skip
    write_file(out / SWEEP_MD, _table(rows, sweep), root=out)
    return rows


_ROW_KEYS = ("trial", "policy_config", "timesteps", "train_wall_s", "episodes", "success_rate", "success_rate_ci95",
             "collision_rate", "collision_rate_ci95", "mean_return")


def _table(rows: list[dict[str, Any]], sweep: Sweep) -> str:
    keys = list(sweep.grid)
    lines = ["# Sweep", "", f"Grid: {json.dumps(sweep.grid)}; seeds {sweep.seeds}; shared: {json.dumps(sweep.base)}.",
             "Sorted by held-out success (95% Wilson intervals).", "",
             "| " + " | ".join([*keys, "seed", "success %", "collision %", "return", "episodes"]) + " |",
             "|" + "---|" * (len(keys) + 5)]  # fmt: skip
    for r in rows:
        cells = [_label(r["policy_config"][k]) for k in keys] + [str(r["policy_config"]["seed"])]
        if r["success_rate"] is None:  # no held-out evaluation (eval_episodes = 0)
            cells += ["—", "—", "—", "0"]
        else:
            lo, hi = r["success_rate_ci95"]
            clo, chi = r["collision_rate_ci95"]
            cells += [f"{100 * r['success_rate']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]",
                      f"{100 * r['collision_rate']:.1f} [{100 * clo:.1f}, {100 * chi:.1f}]",
                      f"{r['mean_return']:.1f}", str(r["episodes"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
