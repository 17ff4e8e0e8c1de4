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

from lckit.fileio import write_file
from lcmodels.experiment.keys import StageKey
from lcmodels.experiment.store import read_record
from lcmodels.fileio import read_json
from lcmodels.presets import (
    FIG5_NAME,
    FIG6_NAME,
    INVOCATIONS,
    ORACLE_KEY,
    ORACLE_LABEL,
    PAPER_TABLE2,
    PAPER_TABLE3,
    PAPER_TABLE4,
    REPORT_NAME,
    ROWS,
    RULE_KEY,
    RULE_LABEL,
    TABLE3_ROWS,
    TABLE4_ROWS,
    Preset,
    StageResult,
)

RATES = ("success", "collision", "timeout", "off_road")
MIN_WINDOW = 20
"""Episodes a rolling success rate must average over before "steps to reach" counts it."""


@dataclass
class MethodRuns:
    """The evaluations (test and validation) and learning curves of one recipe over its seeds, or of a
    reference driver (missing runs left out)."""

    key: str
    label: str
    kind: str = ""
    row: str = ""
    evals: list[dict[str, Any]] = field(default_factory=list)
    """Test-set summaries, one per seed."""
    vals: list[dict[str, dict[str, Any]]] = field(default_factory=list)
    """Per seed: validation summaries by evaluation seed."""
    trains: list[dict[str, Any]] = field(default_factory=list)
    curves: list[dict[str, np.ndarray]] = field(default_factory=list)
    seeds: list[int] = field(default_factory=list)
    wall_s: list[float] = field(default_factory=list)
    """Per seed: the recorded compute time of every stage of the recipe (evaluation excluded)."""
    note: str = ""
    """Shown after the key in the tables (a shipped checkpoint's commit)."""


def read_progress(path: Path) -> dict[str, np.ndarray]:
    """progress.csv as float columns (empty dict when missing)."""
    if not path.exists():
        return {}
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    return {k: np.array([float(r[k]) if r[k] not in ("", None) else math.nan for r in rows]) for k in rows[0]}


def _add_eval(mr: MethodRuns, m: dict[str, Any] | None, seed: int) -> bool:
    if not m or "test" not in m:
        return False
    mr.seeds.append(seed)
    mr.evals.append(m["test"])
    mr.vals.append(m.get("val", {}))
    return True


def _stage_wall(out: Path, key: StageKey) -> float:
    return float((read_record(out, key) or {}).get("wall_s", 0.0))


def _metrics(out: Path, key: StageKey) -> dict[str, Any] | None:
    return read_json(key.path(out) / "metrics.json")


def collect(out: Path, seeds: int, recipes: list[Any]) -> dict[str, MethodRuns]:
    """Metrics of the references (rule, oracle), of every (recipe, seed) run found in ``out``, of the safety
    layer behind each recipe that has one (``<recipe>+safety``) and of the zoo's policies (``zoo:<name>``)."""
    runs: dict[str, MethodRuns] = {}
    for key, label in ((RULE_KEY, RULE_LABEL), (ORACLE_KEY, ORACLE_LABEL)):
        ref = MethodRuns(key, label)
        _add_eval(ref, _metrics(out, StageKey.of(key)), 0)
        runs[key] = ref
    for r in recipes:
        mr = MethodRuns(r.name, r.label or ROWS[r.row], r.kind, r.row)
        safe = MethodRuns(f"{r.name}+safety", f"{r.label or ROWS[r.row]} behind the safety layer", r.kind, r.row)
        for s in range(seeds):
            if not _add_eval(mr, _metrics(out, StageKey(r.name, s, "eval")), s):
                continue
            train = _metrics(out, StageKey(r.name, s, r.final_stage)) or {}
            mr.trains.append(train.get("train", {}))
            mr.curves.append(read_progress(StageKey(r.name, s, "train").path(out) / "progress.csv"))
            mr.wall_s.append(sum(_stage_wall(out, StageKey(r.name, s, st)) for st in r.stages))
            _add_eval(safe, _metrics(out, StageKey(r.name, s, "safety")), s)
        runs[r.name] = mr
        if safe.evals:
            runs[safe.key] = safe
    if zoo_names(out):
        from lcmodels.zoo import zoo_dir

        for name in zoo_names(out):
            card = read_json(zoo_dir() / name / "zoo.json") or {}
            commit = f" @ {card['commit']}" if card.get("commit") else ""
            z = MethodRuns(f"zoo:{name}", f"shipped checkpoint{commit}", "zoo", str(card.get("row", "")), note=commit)
            if _add_eval(z, _metrics(out, StageKey.of("zoo", name)), 0):
                runs[z.key] = z
            safe = MethodRuns(f"{z.key}+safety", f"shipped checkpoint{commit} behind the safety layer", "zoo",
                              z.row, note=commit)  # fmt: skip
            if _add_eval(safe, _metrics(out, StageKey.of("zoo-safety", name)), 0):
                runs[safe.key] = safe
    return runs


def zoo_names(out: Path) -> list[str]:
    """The zoo entries the experiment in ``out`` evaluated (the folders of its ``zoo`` stages)."""
    zoo = StageKey.of("zoo").path(out)
    return sorted(d.name for d in zoo.iterdir() if d.is_dir()) if zoo.is_dir() else []


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


def rate_cell(evals: list[dict[str, Any]], rate: str) -> str:
    """A rate in percent: ``value [95% CI]`` for one evaluation, ``mean ± std`` over several, ``—`` for none."""
    if len(evals) == 1:
        e = evals[0]
        ci = e.get(f"{rate}_rate_ci95")
        v = 100 * e[f"{rate}_rate"]
        return f"{v:.1f} [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]" if ci else f"{v:.1f}"
    return fmt_cell([e[f"{rate}_rate"] for e in evals], 100.0)


def _best_of_kind(runs: dict[str, MethodRuns], row: str, kind: str) -> MethodRuns | None:
    """The recipe of ``kind`` for ``row`` with the highest mean validation success (the choice is never made on
    the held-out episodes)."""
    found = [r for r in runs.values() if r.row == row and r.kind == kind and r.evals and "+" not in r.key]

    def validation(r: MethodRuns) -> float:
        v = [x["success_rate"] for per_seed in r.vals for x in per_seed.values()]
        return float(np.mean(v)) if v else -1.0

    return max(found, key=validation) if found else None


def outcome_table(runs: dict[str, MethodRuns], rows: tuple[str, ...], paper: dict[str, tuple[float, ...]]) -> str:
    """Per row: the paper's figures, the paper-faithful recipe's and the project's best recipe's (held-out), and
    the shipped checkpoint's (zoo) when the experiment evaluated the zoo."""
    titles = {"paper": "paper-faithful recipe", "best": "best recipe", "zoo": "shipped checkpoint (zoo)",
              "demo": "quick recipe (trained now)"}
    # the columns the experiment has runs for (both recipe columns always, so an empty row reads as not run)
    present = {r.kind for r in runs.values() if r.evals}
    kinds = [(k, t) for k, t in titles.items() if k in present or (k in ("paper", "best") and present & {"paper", "best"})]
    kinds = kinds or [("paper", titles["paper"]), ("best", titles["best"])]
    lines = ["| Method | paper: success / collision % | "
             + " | ".join(f"{title}: success % | collision %" for _, title in kinds) + " |",
             "|" + "---|" * (2 + 2 * len(kinds))]
    for key in rows:
        p = paper.get(key)
        cells = [ROWS[key], "—" if p is None else f"{p[0]:.1f} / {p[1]:.1f}"]
        for kind, _ in kinds:
            r = _best_of_kind(runs, key, kind)
            if r is None:
                cells += ["—", "—"]
            else:
                cells += [f"{rate_cell(r.evals, 'success')} (`{r.key}`{r.note})", rate_cell(r.evals, "collision")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def reference_table(runs: dict[str, MethodRuns]) -> str:
    """The rule-based driver, the oracle and every policy behind the safety layer, on the held-out episodes."""
    lines = ["| driver | success % | collision % |", "|---|---|---|"]
    for r in runs.values():
        if r.evals and (r.key in (RULE_KEY, ORACLE_KEY) or r.key.endswith("+safety")):
            lines.append(f"| {r.label} (`{r.key}`) | {rate_cell(r.evals, 'success')} | {rate_cell(r.evals, 'collision')} |")
    return "\n".join(lines) if len(lines) > 2 else "None evaluated."


def all_runs_table(runs: dict[str, MethodRuns]) -> str:
    """Every row of the experiment: held-out figures, validation success per evaluation seed, training time."""
    lines = ["| row | kind | seeds | held-out success % | collision % | timeout % | validation success % (eval seed) "
             "| training min | safety layer overrides |", "|" + "---|" * 9]
    for r in runs.values():
        if not r.evals:
            continue
        vals = []
        for per_seed in r.vals:
            vals += [f"{100 * v['success_rate']:.1f} ({k})" for k, v in per_seed.items()]
        overrides = [e.get("planner_overrides") for e in r.evals if e.get("planner_choices")]
        over = "—" if not overrides else ", ".join(
            f"{e['planner_overrides']} / {e['planner_choices']}" for e in r.evals if e.get("planner_choices"))
        lines.append(f"| {r.label} (`{r.key}`) | {r.kind or '—'} | {len(r.evals)} | {rate_cell(r.evals, 'success')} "
                     f"| {rate_cell(r.evals, 'collision')} | {rate_cell(r.evals, 'timeout')} | {'; '.join(vals) or '—'} "
                     f"| {fmt_cell([w / 60 for w in r.wall_s]) if r.wall_s else '—'} | {over} |")  # fmt: skip
    return "\n".join(lines)


def sealed_test_table(exp: ReportInput) -> str:
    """The experiment's final policies (the graph's final stages: every recipe and training seed; the zoo
    entries it evaluated) and the references as the ledger has them on the sealed test episodes of the paper's
    road: found by the policy's weights, never run here (``lc-bench POLICY... --suite paper --final`` measures
    them)."""
    from lcmodels.bench.ledger import (
        NOT_COMMITTED,
        cell_key,
        find_entry,
        is_committed,
        ledger_path,
        read_ledger,
    )
    from lcmodels.bench.run import policy_identity, scenario_sha256
    from lcmodels.fileio import POLICY_FILE
    from lcmodels.zoo import zoo_dir
    from lcsim.suite import SUITE_SCENARIOS

    if exp.preset.scenario not in SUITE_SCENARIOS:
        return (f"Scenario `{exp.preset.scenario}` is not a road of the benchmark suite (`lc-bench --list`): it has no "
                "sealed test episodes.")
    sc = SUITE_SCENARIOS[exp.preset.scenario]
    digest, seeds = scenario_sha256(sc.make()), sc.sealed_seeds()
    try:
        entries = read_ledger()
    except ValueError as exc:
        return f"The ledger cannot be read: {exc}"
    found: list[tuple[str, dict[str, Any]]] = []
    candidates = [(f"{k.recipe} seed {k.seed}", k.path(exp.out) / POLICY_FILE) for k in exp.finals]
    zoo = zoo_names(exp.out)
    candidates += [(f"zoo:{name}", zoo_dir() / name / POLICY_FILE) for name in zoo]
    for label, identity in ((RULE_LABEL, {"kind": "driver", "name": RULE_KEY}),
                            (ORACLE_LABEL, {"kind": "driver", "name": ORACLE_KEY})):  # fmt: skip
        entry = find_entry(entries, cell_key(identity, digest, seeds))
        if entry is not None:
            found.append((label, entry))
    if zoo:  # a zoo entry behind its safety layer, as its card describes it
        from lcmodels.bench.published import zoo_sealed

        for name in zoo:
            try:
                layer = zoo_sealed(name, entries)["safety_layer"]
            except (ValueError, OSError):
                continue
            if layer is not None:
                found.append((f"zoo:{name} behind its safety layer", {**layer, "key": layer["ledger_key"]}))
    for label, path in candidates:
        if not path.is_file():
            continue
        try:
            identity = policy_identity(path)[0]
        except (ValueError, OSError):
            continue
        entry = find_entry(entries, cell_key(identity, digest, seeds))
        if entry is not None:
            found.append((label, entry))
    if not found:
        return (f"No policy of this run is in the ledger yet: `lc-bench POLICY... --suite {sc.name} --final` measures "
                f"one on the {len(seeds)} sealed test episodes of `{sc.name}` and appends it.")
    mark = "" if is_committed() else f" Every figure here is **{NOT_COMMITTED}** ({ledger_path()})."
    lines = [f"{len(seeds)} sealed test episodes of `{sc.name}`; Wilson 95% intervals over episodes.{mark}\n",
             "| policy | success % [Wilson 95%] | collision % [Wilson 95%] | ledger entry (date, commit) |",
             "|---|---|---|---|"]  # fmt: skip
    for label, e in found:
        lo, hi = e["success_wilson95"]
        clo, chi = e["collision_wilson95"]
        lines.append(f"| {label} | {100 * e['success_rate']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}] | "
                     f"{100 * e['collision_rate']:.1f} [{100 * clo:.1f}, {100 * chi:.1f}] | `{e['key']}` "
                     f"({str(e.get('date', '?'))[:10]}, {e.get('commit') or '?'}) |")
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
    if "paper-hybrid-ppo" not in runs or "paper-hybrid-ppo-warm" not in runs:
        return []
    scratch, warm = runs["paper-hybrid-ppo"], runs["paper-hybrid-ppo-warm"]
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
    for i, m in enumerate(r for r in runs.values() if any(r.curves)):
        x, mean, lo, hi = band(m.curves, key)
        if len(x) == 0:
            continue
        n = len(m.curves)
        ax.plot(x, mean, color=colors(i % 10), lw=1.8, ls="-" if m.kind == "paper" else "--",
                marker="o" if len(x) < 4 else None, ms=3, label=f"{m.key} (n={n})")  # fmt: skip
        if n > 1 and len(x) > 1:
            ax.fill_between(x, lo, hi, color=colors(i % 10), alpha=0.18, lw=0)
        elif n > 1:  # one logged point: the band as an error bar
            ax.errorbar(x, mean, yerr=[mean - lo, hi - mean], color=colors(i % 10), capsize=3, lw=1)
    if reference is not None and math.isfinite(reference):
        ax.axhline(reference, color="black", ls=":", lw=1, label=f"{RULE_LABEL}, held-out episodes")
    ax.set_xlabel("training timesteps (decisions over all environments)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    write_file(path, lambda f: fig.savefig(f, format=path.suffix.lstrip(".") or None))  # never through a link
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
    recipes: list[Any] = field(default_factory=list)
    """The :class:`lcmodels.experiment.recipe.Recipe` objects the experiment ran."""
    recipe_seeds: dict[str, int] = field(default_factory=dict)
    """Training seeds of each recipe (default ``seeds``)."""
    finals: list[StageKey] = field(default_factory=list)
    """The final training stage of every recipe and training seed (:meth:`StageGraph.finals`): the policies the
    sealed test table looks up in the ledger."""


def write_report(exp: ReportInput, *, wall_s: float) -> Path:
    """Write ``REPORT.md`` and the two figures into ``exp.out``; returns the report's path."""
    from lcmodels.policy.train import versions

    out = exp.out
    runs = collect(out, exp.seeds, exp.recipes)
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
    counts = {r.name: exp.recipe_seeds.get(r.name, exp.seeds) for r in exp.recipes}
    usual = min(counts.values(), default=exp.seeds)
    more = ", ".join(f"`{n}` {k}" for n, k in counts.items() if k != usual)
    add(f"- recipes: {', '.join(f'`{r.name}`' for r in exp.recipes)}; training seeds per recipe: **{usual}** "
        f"(from 0){f'; more for {more}' if more else ''}")
    add(f"- **held-out**: {p.test_episodes} episodes of evaluation seed {p.test_seed}, "
        f"which no recipe here is chosen on; **validation**: {p.val_episodes} episodes of evaluation seed(s) "
        f"{', '.join(str(v) for v in p.val_seeds)}, the episodes the recipes are chosen on (last table). Both are "
        "validation episodes in the benchmark's sense (seed 9 informed earlier choices of the project): the "
        "figures to quote are the **sealed test** ones, which only `lc-bench --final` measures and the ledger "
        "keeps (section *Sealed test*).")
    parts = exp.invocations or [{"wall_s": wall_s}]
    total = sum(float(inv.get("wall_s", 0.0)) for inv in parts)
    add(f"- scenario: `{p.scenario}`; wall time: **{total / 60:.1f} min** over {len(parts)} invocation(s) "
        f"(`{INVOCATIONS}`; this one {wall_s / 60:.1f} min); compute time of all results (sum of the stages' "
        f"recorded wall times, every resumed part counted): **{sum(s.wall_s for s in exp.stages) / 60:.1f} min**")
    add(f"- written {_now()}; every number below is read from the `metrics.json` / `progress.csv` files of the "
        "stage directories (`policies/<recipe>/seed<k>/`).\n")
    if p.name != "paper":
        add(f"> The `{p.name}` preset runs small budgets: it shows the pipeline; the `paper` preset gives "
            "the results.\n")

    add("## Table II: trajectory prediction (test split)\n")
    add(table2(pred))
    if pred:
        c = pred.get("corpus", {})
        mc = pred.get("config", {}).get("model", {})
        add(f"\n{mc.get('history_steps', '?')} history + {mc.get('future_steps', '?')} future steps at 20 Hz; "
            f"{c.get('windows', {}).get('test', '?')} test windows from {c.get('test', {}).get('episodes', '?')} "
            f"held-out episode(s) of {c.get('all', {}).get('episodes', '?')}. Ours are metres on our simulator "
            "(constant velocity is a strong baseline there); the paper's MAD/FAD come from CARLA.\n")

    add(f"## Table III: methods (held-out episodes of seed {p.test_seed}, %)\n")
    add(outcome_table(runs, TABLE3_ROWS, PAPER_TABLE3))
    add(f"\n## Table IV: observation ablation (held-out episodes of seed {p.test_seed}, %)\n")
    add(outcome_table(runs, TABLE4_ROWS, PAPER_TABLE4))
    add("\nOne training seed: the value and its 95% Wilson interval over episodes; several: mean ± sample standard "
        "deviation over seeds (not an interval: `lc-bench` gives the t interval over seeds). *Paper-faithful*: the method trained from scratch on the paper's observation and budget; "
        "*best*: the project's recipe for the method (`lcmodels/recipes/<name>.toml`).\n")
    add(f"## References and the safety layer (held-out episodes of seed {p.test_seed}, %)\n")
    add(reference_table(runs))
    add("")
    add("## Sealed test (from the ledger)\n")
    add(sealed_test_table(exp))
    add("")
    add("## Every row (held-out and validation)\n")
    add(all_runs_table(runs))
    add("\nSafety layer: the final policy proposes each decision, the lookahead planner (imagining from what "
        "the ego's sensors show) vetoes a proposal it foresees crashing; overrides / decisions with a choice.\n")

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
    else:
        add("No completed `paper-hybrid-ppo` / `paper-hybrid-ppo-warm` pair.")

    add("\n## Learning curves\n")
    add(f"![Fig. 5: safe forward distance]({FIG5_NAME})\n")
    add(f"![Fig. 6: total reward]({FIG6_NAME})\n")
    add("One curve per recipe with an online training stage (solid: paper-faithful, from scratch; dashed: the "
        "project's recipes, from a clone): the mean over seeds of the rolling value over the last 100 training "
        "episodes, with a min–max band over seeds; the dotted line is the rule-based driver on the held-out "
        "episodes.\n")

    add("## Stages\n")
    add("| stage | this run | recorded wall s | directory |")
    add("|---|---|---|---|")
    for st in exp.stages:
        add(f"| {st.name} | {st.status} | {st.wall_s:.1f} | `{_rel(st.path, out)}` |")

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
    write_file(path, "\n".join(L) + "\n", root=out)
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
