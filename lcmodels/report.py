"""REPORT.md and the learning-curve figures of an ``lc-experiment`` directory.

Every number in the report is read from the stage outputs (``predictor/metrics.json``,
``rule/metrics.json``, ``policies/<method>/seed<k>/metrics.json`` and ``progress.csv``), so the report
can be rebuilt from a finished directory at any time (:func:`write_report`).
"""

from __future__ import annotations

import csv
import json
import math
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lcmodels.fileio import read_json
from lcmodels.presets import (
    FIG5_NAME,
    FIG6_NAME,
    INVOCATIONS,
    METHOD_BY_KEY,
    METHODS,
    PAPER_TABLE2,
    PAPER_TABLE3,
    PAPER_TABLE4,
    REPORT_NAME,
    RULE_KEY,
    RULE_LABEL,
    TABLE3_ROWS,
    TABLE4_ROWS,
    Preset,
    StageResult,
    method_timesteps,
    policy_dir,
)

RATES = ("success", "collision", "timeout", "off_road")
MIN_WINDOW = 20
"""Episodes a rolling success rate must average over before "steps to reach" counts it."""


@dataclass
class MethodRuns:
    """The evaluation and learning curves of one method over its seeds (missing runs left out)."""

    key: str
    label: str
    evals: list[dict[str, Any]] = field(default_factory=list)
    trains: list[dict[str, Any]] = field(default_factory=list)
    curves: list[dict[str, np.ndarray]] = field(default_factory=list)
    seeds: list[int] = field(default_factory=list)


def read_progress(path: Path) -> dict[str, np.ndarray]:
    """progress.csv as float columns (empty dict when missing)."""
    if not path.exists():
        return {}
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    return {k: np.array([float(r[k]) if r[k] not in ("", None) else math.nan for r in rows]) for k in rows[0]}


def collect(out: Path, seeds: int) -> dict[str, MethodRuns]:
    """Metrics of the rule-based reference and of every (method, seed) run found in ``out``."""
    runs: dict[str, MethodRuns] = {}
    rule = MethodRuns(RULE_KEY, RULE_LABEL)
    m = read_json(out / RULE_KEY / "metrics.json")
    if m and "eval" in m:
        rule.evals.append(m["eval"])
        rule.seeds.append(0)
    runs[RULE_KEY] = rule
    for method in METHODS:
        mr = MethodRuns(method.key, method.label)
        for s in range(seeds):
            d = policy_dir(out, method.key, s)
            m = read_json(d / "metrics.json")
            if not m or "eval" not in m:
                continue
            mr.seeds.append(s)
            mr.evals.append(m["eval"])
            mr.trains.append(m.get("train", {}))
            mr.curves.append(read_progress(d / "progress.csv"))
        runs[method.key] = mr
    return runs


# -------------------------------------------------------------------------------------------- formatting
def mean_std(values: list[float]) -> tuple[float, float | None]:
    """Mean and sample standard deviation (None for a single value)."""
    a = np.asarray(values, dtype=float)
    return float(a.mean()), (float(a.std(ddof=1)) if len(a) > 1 else None)


def fmt_cell(values: list[float], scale: float = 1.0, digits: int = 1) -> str:
    """``mean ± std`` over seeds (``mean`` alone for one seed, ``—`` for none), values times ``scale``."""
    if not values:
        return "—"
    m, s = mean_std([v * scale for v in values])
    return f"{m:.{digits}f}" if s is None else f"{m:.{digits}f} ± {s:.{digits}f}"


def _paper(v: float | None) -> str:
    return "—" if v is None else f"{v:.1f}"


def outcome_table(runs: dict[str, MethodRuns], rows: tuple[str, ...], paper: dict[str, tuple[float, ...]]) -> str:
    head = ("| Method | seeds | Success % (ours) | Success % (paper) | Collision % (ours) | Collision % (paper) "
            "| Timeout % (ours) | Timeout % (paper) | Off-road % (ours) | Safe forward m (ours) | Return (ours) |")
    lines = [head, "|" + "---|" * 11]
    for key in rows:
        r = runs[key]
        p = paper.get(key, (None, None, None))
        cells = [r.label, str(len(r.evals))]
        for i, rate in enumerate(("success", "collision", "timeout")):
            cells += [fmt_cell([e[f"{rate}_rate"] for e in r.evals], 100.0), _paper(p[i])]
        cells.append(fmt_cell([e["off_road_rate"] for e in r.evals], 100.0))
        cells.append(fmt_cell([e["mean_safe_forward_m"] for e in r.evals]))
        cells.append(fmt_cell([e["mean_return"] for e in r.evals]))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table2(pred: dict[str, Any] | None) -> str:
    lines = ["| Predictor | ADE / MAD | FDE / FAD | Miss rate |", "|---|---|---|---|"]
    if pred:
        for key, label in (("model", "Transformer (ours), m"), ("constant_velocity", "Constant velocity, m"),
                           ("constant_acceleration", "Constant acceleration, m")):  # fmt: skip
            m = pred.get(key, {})
            lines.append(f"| {label} | {m.get('ade', math.nan):.4f} | {m.get('fde', math.nan):.4f} | "
                         f"{m.get('miss_rate', math.nan):.4f} |")  # fmt: skip
    else:
        lines.append("| Transformer (ours) | — | — | — |")
    lines.append(f"| Paper (Hybrid-PPO), units as reported | {PAPER_TABLE2['ade']:.3f} | {PAPER_TABLE2['fde']:.3f} | — |")
    return "\n".join(lines)


def first_reach(curve: dict[str, np.ndarray], target: float, min_window: int) -> int | None:
    """First logged timestep whose rolling success rate (over >= ``min_window`` episodes) reaches ``target``."""
    if not curve:
        return None
    ok = (curve["window"] >= min_window) & (curve["success_rate"] >= target - 1e-12)
    idx = np.flatnonzero(ok)
    return int(curve["timesteps"][idx[0]]) if len(idx) else None


def warm_start_rows(runs: dict[str, MethodRuns]) -> list[dict[str, Any]]:
    """Per seed: the scratch run's final rolling success and the first step each run reaches it."""
    scratch, warm = runs["ppo-hybrid"], runs["ppo-hybrid-warm"]
    by_seed = dict(zip(warm.seeds, warm.curves, strict=True))
    out = []
    for seed, curve in zip(scratch.seeds, scratch.curves, strict=True):
        if not curve or seed not in by_seed:
            continue
        ok = np.isfinite(curve["success_rate"])
        if not ok.any():
            continue
        last = int(np.flatnonzero(ok)[-1])
        target = float(curve["success_rate"][last])
        min_window = int(min(MIN_WINDOW, curve["window"][last]))
        out.append({"seed": seed, "target": target, "min_window": min_window,
                    "scratch": first_reach(curve, target, min_window),
                    "warm": first_reach(by_seed[seed], target, min_window)})  # fmt: skip
    return out


# ----------------------------------------------------------------------------------------------- figures
def band(curves: list[dict[str, np.ndarray]], key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(x, mean, min, max)`` of column ``key`` over seeds, interpolated onto the shared timestep range."""
    series = []
    for c in curves:
        if not c:
            continue
        ok = np.isfinite(c[key])
        if ok.any():
            series.append((c["timesteps"][ok], c[key][ok]))
    if not series:
        return (np.zeros(0),) * 4
    lo, hi = max(s[0][0] for s in series), min(s[0][-1] for s in series)
    x = np.unique(np.concatenate([s[0] for s in series]))
    x = x[(x >= lo) & (x <= hi)]
    if len(x) == 0:  # no overlap: show the first seed alone
        x, y = series[0]
        return x, y, y, y
    ys = np.stack([np.interp(x, sx, sy) for sx, sy in series])
    return x, ys.mean(0), ys.min(0), ys.max(0)


def plot_curves(runs: dict[str, MethodRuns], key: str, ylabel: str, title: str, path: Path,
                reference: float | None = None) -> None:  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5), dpi=110)
    colors = plt.get_cmap("tab10")
    for i, m in enumerate(METHODS):
        x, mean, lo, hi = band(runs[m.key].curves, key)
        if len(x) == 0:
            continue
        n = len(runs[m.key].curves)
        ax.plot(x, mean, color=colors(i), lw=1.8, marker="o" if len(x) < 4 else None, ms=3,
                label=f"{m.label} (n={n})")  # fmt: skip
        if n > 1 and len(x) > 1:
            ax.fill_between(x, lo, hi, color=colors(i), alpha=0.18, lw=0)
        elif n > 1:  # one logged point: the band as an error bar
            ax.errorbar(x, mean, yerr=[mean - lo, hi - mean], color=colors(i), capsize=3, lw=1)
    if reference is not None and math.isfinite(reference):
        ax.axhline(reference, color="black", ls="--", lw=1, label=f"{RULE_LABEL}, held-out")
    ax.set_xlabel("training timesteps (decisions over all environments)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ report
@dataclass(frozen=True)
class ReportInput:
    """What the report says of the invocations besides the stage outputs it reads."""

    out: Path
    preset: Preset
    seeds: int
    stages: list[StageResult]
    invocations: list[dict[str, Any]]
    command: str


def write_report(exp: ReportInput, *, wall_s: float) -> Path:
    """Write ``REPORT.md`` and the two figures into ``exp.out``; returns the report's path."""
    from lcmodels.policy.train import versions

    out = exp.out
    runs = collect(out, exp.seeds)
    pred = read_json(out / "predictor" / "metrics.json")
    rule_eval = runs[RULE_KEY].evals[0] if runs[RULE_KEY].evals else {}
    plot_curves(runs, "mean_safe_forward_m", "safe forward distance, m (mean of last 100 episodes)",
                "Fig. 5: safe forward distance over training", out / FIG5_NAME,
                rule_eval.get("mean_safe_forward_m"))  # fmt: skip
    plot_curves(runs, "mean_return", "total reward per episode (mean of last 100 episodes)",
                "Fig. 6: total reward over training", out / FIG6_NAME, rule_eval.get("mean_return"))  # fmt: skip
    p = exp.preset
    L: list[str] = []
    add = L.append
    add(f"# lc-experiment report: preset `{p.name}`\n")
    add(f"- seeds per method: **{exp.seeds}** (training seeds 0..{exp.seeds - 1}); held-out evaluation: "
        f"{p.eval_episodes} episodes of evaluation seed {p.eval_seed} (the same episodes for every method)")
    parts = exp.invocations or [{"wall_s": wall_s}]
    total = sum(float(inv.get("wall_s", 0.0)) for inv in parts)
    add(f"- scenario: `{p.scenario}`; wall time: **{total / 60:.1f} min** over {len(parts)} invocation(s) "
        f"(`{INVOCATIONS}`; this one {wall_s / 60:.1f} min); compute time of all results (sum of the stages' "
        f"recorded wall times, every resumed part counted): **{sum(s.wall_s for s in exp.stages) / 60:.1f} min**")
    add(f"- written {_now()}; every number below is read from the `metrics.json` / `progress.csv` files named in "
        "*Files*.\n")
    if p.name != "paper":
        add(f"> The `{p.name}` preset uses budgets far below convergence: it shows the pipeline, not the "
            "paper's results. Use `--preset paper` for those.\n")

    add("## Table II: trajectory prediction (test split)\n")
    add(table2(pred))
    if pred:
        c = pred.get("corpus", {})
        mc = pred.get("config", {}).get("model", {})
        add(f"\n{mc.get('history_steps', '?')} history + {mc.get('future_steps', '?')} future steps at 20 Hz; "
            f"{c.get('windows', {}).get('test', '?')} test windows from {c.get('test', {}).get('episodes', '?')} "
            f"held-out episode(s) of {c.get('all', {}).get('episodes', '?')}. Ours are metres on our simulator "
            "(constant velocity is a strong baseline there); the paper's MAD/FAD come from CARLA.\n")

    add("## Table III: methods (held-out evaluation, %)\n")
    add(outcome_table(runs, TABLE3_ROWS, PAPER_TABLE3))
    add("\n## Table IV: observation ablation of PPO (held-out evaluation, %)\n")
    add(outcome_table(runs, TABLE4_ROWS, PAPER_TABLE4))
    add("\nCells are mean ± sample standard deviation over seeds (a single value for one seed). "
        "The rule-based driver is deterministic: one evaluation.\n")

    add("## Warm start: steps to reach the same success\n")
    rows = warm_start_rows(runs)
    if rows:
        add("Target = final rolling success rate (last 100 training episodes) of Hybrid-PPO from scratch; "
            "the first logged timestep at which each run's rolling success (over at least "
            f"{rows[0]['min_window']} episodes) reaches it.\n")
        add("| seed | target success % | Hybrid-PPO from scratch | Hybrid-PPO + warm start |")
        add("|---|---|---|---|")
        for r in rows:
            add(f"| {r['seed']} | {100 * r['target']:.1f} | {_steps(r['scratch'])} | {_steps(r['warm'])} |")
        wst = [t.get("warm_start") for t in runs["ppo-hybrid-warm"].trains if t.get("warm_start")]
        if wst:
            w = wst[0]
            add(f"\nBehaviour cloning on {w.get('decisions', '?')} decisions of {w.get('episodes', '?')} rule-based "
                f"episodes: NLL {w.get('nll_before', math.nan):.3f} -> {w.get('nll_after', math.nan):.3f}.")
    else:
        add("No completed Hybrid-PPO / warm-start pair yet.")

    add("\n## Learning curves\n")
    add(f"![Fig. 5: safe forward distance]({FIG5_NAME})\n")
    add(f"![Fig. 6: total reward]({FIG6_NAME})\n")
    add("One curve per method: the mean over seeds of the rolling value over the last 100 training episodes, "
        "with a min–max band over seeds; the dashed line is the rule-based driver on the held-out episodes.\n")

    add("## Training budget\n")
    add("| Method | timesteps per seed | training episodes (mean) | training wall min (mean) | eval wall s (mean) |")
    add("|---|---|---|---|---|")
    for m in METHODS:
        r = runs[m.key]
        steps = sorted({int(t.get("timesteps", 0)) for t in r.trains}) or [method_timesteps(p, METHOD_BY_KEY[m.key])]
        add(f"| {m.label} | {', '.join(str(s) for s in steps)} | "
            f"{fmt_cell([t.get('episodes', math.nan) for t in r.trains], digits=0)} | "
            f"{fmt_cell([t.get('wall_s', math.nan) / 60 for t in r.trains], digits=1)} | "
            f"{fmt_cell([e.get('wall_s', math.nan) for e in r.evals], digits=1)} |")

    add("\n## Stages\n")
    add("| stage | this run | recorded wall s | directory |")
    add("|---|---|---|---|")
    for s in exp.stages:
        add(f"| {s.name} | {s.status} | {s.wall_s:.1f} | `{_rel(s.path, out)}` |")

    add("\n## Files\n")
    add("| row | seed | metrics |")
    add("|---|---|---|")
    add(f"| Table II | — | `predictor/metrics.json` |\n| {RULE_LABEL} | — | `{RULE_KEY}/metrics.json` |")
    for m in METHODS:
        for s in runs[m.key].seeds:
            add(f"| {m.label} | {s} | `{_rel(policy_dir(out, m.key, s), out)}/metrics.json` |")

    add("\n## Reproduce\n")
    add("```bash")
    add(exp.command or f"lc-experiment --preset {p.name} --seeds {exp.seeds} --out {shlex.quote(str(out))}")
    add("```\n")
    add("Rerunning the same command skips every complete stage and redoes what is missing or stale.\n")
    add("Versions:\n")
    add("```json\n" + json.dumps(versions(), indent=2, sort_keys=True) + "\n```\n")
    add(f"Preset `{p.name}`:\n")
    add("```json\n" + json.dumps({**p.to_dict(), "seeds": exp.seeds}, indent=2) + "\n```")
    path = out / REPORT_NAME
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text("\n".join(L) + "\n")
    tmp.replace(path)
    return path


def _steps(v: int | None) -> str:
    return "not reached" if v is None else str(v)


def _rel(p: Path, base: Path) -> str:
    try:
        return str(Path(p).relative_to(base))
    except ValueError:
        return str(p)


def _now() -> str:
    import time

    return time.strftime("%Y-%m-%d %H:%M:%S %Z")
