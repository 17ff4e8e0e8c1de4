"""The controlled input ablation's verdict: does the hybrid input help?

Reads what ``lc-experiment --preset ablation`` measured (every run's ``suite`` stage: its cells on every road of
the suite, validation episodes, next to each road's ceiling and floor) and answers per training block (the paper's
road; every road of the suite) with lc-bench's statistics, the hybrid input first so that every other input is
tested against it: success per road with Wilson intervals, each input's IQM and mean of the normalised scores with
rliable's stratified-bootstrap intervals over its runs, and McNemar's test against the hybrid input pooled over the
runs paired training seed with training seed, on every episode of the suite and per road.

Runs not measured yet are left out and said so: a partial ablation is reported as partial.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from lckit.fileio import write_file
from lcmodels.bench.figures import figures_markdown, write_figures
from lcmodels.bench.table import CEILING, FLOOR, suite_markdown, suite_summary
from lcmodels.fileio import read_json
from lcmodels.presets import ABLATION_INPUTS, ABLATION_SEEDS, PAPER_TABLE4, policy_dir

REFERENCE = "hybrid"
"""The input every other is tested against (the paper's claim: the hybrid input beats each input alone)."""
BLOCKS = {"paper": "ablation-", "roads": "ablation-roads-"}
"""The training blocks and their recipes' prefix: trained on the paper's road; on every road of the suite."""
PAPER_ROWS = {"pure": "ppo-pure", "image": "ppo-image", "prediction": "ppo-prediction", "hybrid": "ppo-hybrid"}
"""The inputs the paper's Table IV has, and its rows."""


def inputs_in_order() -> list[str]:
    """The inputs with the reference first, then the rest in the ablation's order."""
    return [REFERENCE, *(m for m in ABLATION_INPUTS if m != REFERENCE)]


def _suite_file(out: Path, key: str) -> Path:
    return Path(out) / "suite" / key / "suite.json"


def block_summary(out: str | Path, block: str, *, seeds: int = ABLATION_SEEDS) -> dict[str, Any] | None:
    """lc-bench's summary (:func:`lcmodels.bench.table.suite_summary`) of the block's measured runs, grouped by
    input with the hybrid input first, plus ``missing`` (the runs not measured yet). None when the ceiling, the
    floor or the hybrid input has no measured run."""
    out = Path(out)
    ends = {CEILING: read_json(_suite_file(out, CEILING)), FLOOR: read_json(_suite_file(out, FLOOR))}
    if any(v is None for v in ends.values()):
        return None
    cells: dict[tuple[str, str], dict[str, Any]] = {}
    for label, data in ends.items():
        for sc, rec in data["cells"].items():
            cells[(label, sc)] = rec
    roads = list(ends[CEILING]["cells"])
    drivers: list[tuple[str, str]] = []
    missing: list[str] = []
    for mode in inputs_in_order():
        recipe = f"{BLOCKS[block]}{mode}"
        for seed in range(seeds):
            data = read_json(policy_dir(out, recipe, seed) / "suite" / "suite.json")
            if data is None or set(data.get("cells", {})) != set(roads):
                missing.append(f"{recipe}/seed{seed}")
                continue
            for sc, rec in data["cells"].items():
                cells[(f"{mode}/seed{seed}", sc)] = rec
            drivers.append((f"{mode}/seed{seed}", mode))
    if not drivers or drivers[0][1] != REFERENCE:
        return None
    from lcsim.suite import suite

    scenarios = [sc for sc in suite(ends[CEILING]["config"]["suite"]) if sc.name in roads]
    split = f"validation seed {ends[CEILING]['config']['seed']}"
    seeds = {label: int(label.rsplit("seed", 1)[1]) for label, _ in drivers}
    summary = suite_summary(cells, drivers, scenarios, suite=ends[CEILING]["config"]["suite"], split=split,
                            pair_keys=seeds)  # fmt: skip
    summary["block"], summary["missing"] = block, missing
    return summary


def verdict_rows(summary: dict[str, Any]) -> list[dict[str, Any]]:
    """Per input: its runs, success on the paper's road (mean over runs), IQM and mean normalised score over the
    suite with their bootstrap intervals, and McNemar against the hybrid input over every episode of the suite."""
    paper = next((r for r in summary["scenarios"] if r["scenario"] == "paper"), None)
    rows = []
    for g in summary["groups"]:
        row: dict[str, Any] = {"input": g["group"], "runs": len(g["runs"]), "aggregate": g.get("aggregate")}
        if paper is not None:
            rates = [paper["drivers"][lb]["success_rate"] for lb in g["runs"]]
            row["paper_success"] = sum(rates) / len(rates)
        row["paper_table4"] = PAPER_TABLE4.get(PAPER_ROWS.get(g["group"], ""), (None,))[0]
        if "mcnemar_vs_first_group" in g:
            t = g["mcnemar_vs_first_group"]
            row["vs_hybrid"] = {k: t[k] for k in ("n", "only_a", "only_b", "p_value", "verdict", "pairs")}
            if paper is not None:
                row["vs_hybrid_paper_road"] = t["per_scenario"]["paper"]
        rows.append(row)
    return rows


def _cell(a: dict[str, Any] | None, key: str) -> str:
    if not a:
        return "—"
    x = a[key]
    return f"{x['value']:.3f}" + (f" [{x['ci95'][0]:.3f}, {x['ci95'][1]:.3f}]" if x["ci95"] else "")


def verdict_markdown(summary: dict[str, Any]) -> str:
    """The block's answer as one Markdown table (the paper's Table IV beside it)."""
    block = {"paper": "trained on the paper's road", "roads": "trained on every road of the suite"}[summary["block"]]
    lines = [f"### Inputs {block} ({summary['split']} episodes, {summary['scenarios'][0]['episodes']} a road)", "",
             "| input | runs | paper road success % (mean over runs) | paper's Table IV % | suite IQM [bootstrap 95%] "
             "| suite mean [bootstrap 95%] | against hybrid (McNemar, all roads, runs paired seed with seed) |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in verdict_rows(summary):
        paper = f"{100 * r['paper_success']:.1f}" if "paper_success" in r else "—"
        table4 = f"{r['paper_table4']:.1f}" if r["paper_table4"] is not None else "—"
        test = "(the reference)"
        if "vs_hybrid" in r:
            t = r["vs_hybrid"]
            test = f"{t['verdict']}; {t['only_a']} episodes only hybrid won, {t['only_b']} only {r['input']}"
        lines.append(f"| {r['input']} | {r['runs']} | {paper} | {table4} | {_cell(r['aggregate'], 'iqm')} | "
                     f"{_cell(r['aggregate'], 'mean')} | {test} |")
    if summary["missing"]:
        lines += ["", f"Not measured yet ({len(summary['missing'])} runs): " + ", ".join(summary["missing"]) + "."]
    return "\n".join(lines) + "\n"


VERDICT_PREFACE = ("# The input ablation: the verdict\n\n"
                   "Generated by `python tools/publish_ablation.py RUN` from `lc-experiment --preset ablation --out RUN`; "
                   "validation episodes. Success % is the mean over an input's runs (training seeds) on the paper's road; "
                   "IQM and mean are of the normalised scores (success / the oracle's) over runs and roads, with "
                   "rliable's stratified-bootstrap 95% intervals over runs; the McNemar test pairs each run with the "
                   "hybrid run of the same training seed on the same episodes, over every road (pooled over the pairs, "
                   "as if they were independent: the intervals over runs are the honest width for a recipe).\n")


def write_ablation(out: str | Path, dest: str | Path) -> list[Path]:
    """Each block's table, lc-bench's full table and figures, ``ablation.json`` and ``VERDICT.md`` (one table per
    block) into ``dest``, never through a link; returns the files written (none when no block has anything
    measured)."""
    dest = Path(dest)
    written: list[Path] = []
    record: dict[str, Any] = {}
    parts = [VERDICT_PREFACE]
    for block in BLOCKS:
        summary = block_summary(out, block)
        if summary is None:
            continue
        folder = dest / block
        written += write_figures(summary, folder, root=dest)
        written.append(write_file(folder / "BENCH.md", suite_markdown(summary, figures=figures_markdown()), root=dest))
        record[block] = {"verdict": verdict_rows(summary), "missing": summary["missing"], "summary": summary}
        parts += [verdict_markdown(summary), f"Every road, every run, figures: [{block}/BENCH.md]({block}/BENCH.md)\n"]
    if record:
        written.append(write_file(dest / "ablation.json", json.dumps(record, indent=1, sort_keys=True) + "\n",
                                  root=dest))  # fmt: skip
        written.append(write_file(dest / "VERDICT.md", "\n".join(parts), root=dest))
    return written


__all__ = ["BLOCKS", "REFERENCE", "block_summary", "verdict_markdown", "verdict_rows", "write_ablation"]
