"""The suite table: per scenario the ceiling (oracle), the floor (rule-based driver) and every driver's
success and collision with Wilson intervals over episodes and the normalised score (success / ceiling's
success); per driver the suite's mean normalised score, per method (a recipe's training seeds together) the
interquartile mean with rliable's stratified-bootstrap interval, and McNemar's exact test of each driver
against the first on the same episodes."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from lcmodels.bench.ledger import NOT_COMMITTED
from lcmodels.stats import aggregate_scores, mcnemar, t_interval

CEILING, FLOOR = "oracle", "rule"


def _won(record: dict[str, Any]) -> np.ndarray:
    return np.frombuffer(record["outcomes"].encode(), dtype=np.uint8) == ord("s")


def suite_summary(cells: dict[tuple[str, str], dict[str, Any]], drivers: Sequence[tuple[str, str]],
                  scenarios: Sequence[Any], *, suite: str, split: str,
                  pair_keys: dict[str, Any] | None = None) -> dict[str, Any]:
    """The table as data.

    Args:
        cells: ``{(driver label, scenario name): record}`` (ledger entries or cached cells), the ceiling and
            floor included under :data:`CEILING` and :data:`FLOOR`.
        drivers: ``(label, group)`` of the drivers benchmarked, in the user's order (the first is the
            reference of the paired tests).
        scenarios: the suite's :class:`lcsim.suite.SuiteScenario` s.
        pair_keys: ``{label: key}`` by which the methods' paired test pairs their runs (the training seed): runs
            with the same key; where a run has none, the runs pair in the order given.
    """
    rows = []
    for sc in scenarios:
        ceiling = cells[(CEILING, sc.name)]["success_rate"]
        row: dict[str, Any] = {"scenario": sc.name, "what": sc.what, "episodes": cells[(CEILING, sc.name)]["episodes"],
                               "drivers": {}}  # fmt: skip
        for label in dict.fromkeys([CEILING, FLOOR, *(d for d, _ in drivers)]):
            rec = cells[(label, sc.name)]
            row["drivers"][label] = {
                "success_rate": rec["success_rate"], "success_wilson95": rec["success_wilson95"],
                "collision_rate": rec["collision_rate"], "collision_wilson95": rec["collision_wilson95"],
                "timeout_rate": rec["timeout_rate"], "off_road_rate": rec["off_road_rate"],
                "normalised": rec["success_rate"] / ceiling if ceiling > 0 else float("nan"),
                "ledger_key": rec.get("key"), "commit": rec.get("commit"), "date": rec.get("date"),
            }  # fmt: skip
        rows.append(row)
    per_driver = []
    reference = drivers[0][0] if drivers else None
    for label, group in dict.fromkeys([(CEILING, CEILING), (FLOOR, FLOOR), *drivers]):
        norm = [r["drivers"][label]["normalised"] for r in rows]
        item: dict[str, Any] = {"driver": label, "group": group, "mean_normalised": float(np.mean(norm)),
                                "normalised": dict(zip([r["scenario"] for r in rows], norm, strict=True))}
        if reference is not None and label != reference:
            a = np.concatenate([_won(cells[(reference, sc.name)]) for sc in scenarios])
            b = np.concatenate([_won(cells[(label, sc.name)]) for sc in scenarios])
            item["mcnemar_vs_first"] = {"first": reference, **mcnemar(a, b).as_dict(),
                                        "verdict": mcnemar(a, b).verdict(reference, label)}
            item["mcnemar_per_scenario"] = {
                sc.name: mcnemar(_won(cells[(reference, sc.name)]), _won(cells[(label, sc.name)])).as_dict()
                for sc in scenarios}  # fmt: skip
        per_driver.append(item)
    groups: dict[str, list[str]] = {}
    for label, group in drivers:
        groups.setdefault(group, []).append(label)
    per_group = []
    for group, labels in groups.items():
        scores = np.array([[r["drivers"][lb]["normalised"] for r in rows] for lb in labels])
        entry: dict[str, Any] = {"group": group, "runs": labels}
        if np.isfinite(scores).all():
            entry["aggregate"] = aggregate_scores(scores)
        for sc_index, sc in enumerate(scenarios):
            rates = [cells[(lb, sc.name)]["success_rate"] for lb in labels]
            if len(rates) > 1:
                entry.setdefault("success_over_seeds", {})[sc.name] = {
                    "mean": float(np.mean(rates)), "t95": list(t_interval(rates)), "runs": len(rates)}
            del sc_index
        per_group.append(entry)
    _group_tests(per_group, cells, scenarios, pair_keys or {})
    return {"suite": suite, "split": split, "scenarios": rows, "drivers": per_driver, "groups": per_group}


def _pairs(a: Sequence[str], b: Sequence[str], keys: dict[str, Any]) -> list[tuple[str, str]]:
    """Runs of two methods paired: by their keys where every run has one (runs whose key the other method lacks
    are left out), else in the order given (the first ``min`` runs)."""
    if all(keys.get(lb) is not None for lb in (*a, *b)):
        theirs = {keys[lb]: lb for lb in b}
        return [(lb, theirs[keys[lb]]) for lb in a if keys[lb] in theirs]
    return list(zip(a, b, strict=False))


def _group_tests(per_group: list[dict[str, Any]], cells: dict[tuple[str, str], dict[str, Any]],
                 scenarios: Sequence[Any], keys: dict[str, Any]) -> None:
    """McNemar of every method against the first, pooled over their runs paired on the same episodes (by
    ``keys``, the training seed: seed with seed; else in the order given), over the suite and per scenario.
    Stored as ``mcnemar_vs_first_group`` with the pairs it made and how (``paired_by``)."""
    if len(per_group) < 2:
        return
    first = per_group[0]
    for g in per_group[1:]:
        pairs = _pairs(first["runs"], g["runs"], keys)
        if not pairs:
            continue
        by = "key" if all(keys.get(lb) is not None for lb in (*first["runs"], *g["runs"])) else "order"

        def won(labels: Sequence[str], names: Sequence[str]) -> np.ndarray:
            return np.concatenate([_won(cells[(lb, sc)]) for lb in labels for sc in names])

        names = [sc.name for sc in scenarios]
        a, b = won([p[0] for p in pairs], names), won([p[1] for p in pairs], names)
        test = mcnemar(a, b)
        g["mcnemar_vs_first_group"] = {
            "first": first["group"], "pairs": [list(p) for p in pairs], "paired_by": by, **test.as_dict(),
            "verdict": test.verdict(first["group"], g["group"]),
            "per_scenario": {sc: mcnemar(won([p[0] for p in pairs], [sc]), won([p[1] for p in pairs], [sc])).as_dict()
                             for sc in names},
        }  # fmt: skip


def _pct(rate: float, ci: Sequence[float]) -> str:
    return f"{100 * rate:.1f} [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"


def suite_markdown(summary: dict[str, Any], command: str = "", figures: str = "") -> str:
    """The table as Markdown (``figures``: Markdown embedding its figures, before the command that made it, which
    stays the last line)."""
    split = summary["split"]
    lines = [f"## Suite `{summary['suite']}`: {split} episodes", ""]
    ledger = summary.get("ledger") or {"committed": True}
    if split == "test" and ledger["committed"]:
        lines += ["Sealed test episodes; every figure is a ledger entry (docs/results/benchmark/ledger.jsonl).", ""]
    elif split == "test":
        lines += [f"Sealed test episodes; every figure is an entry of ledger {ledger['path']}, **{NOT_COMMITTED}** "
                  "(docs/results/benchmark/ledger.jsonl).", ""]  # fmt: skip
    lines += ["Success and collision in % of episodes with Wilson 95% intervals over episodes; normalised = "
              "success / the ceiling's (oracle) success on the same episodes.", "",
              "| scenario | driver | success % [Wilson 95%] | collision % [Wilson 95%] | normalised |",
              "|---|---|---|---|---|"]  # fmt: skip
    for row in summary["scenarios"]:
        first = True
        for label, d in row["drivers"].items():
            name = {CEILING: "ceiling: oracle", FLOOR: "floor: rule"}.get(label, f"`{label}`")
            scenario = f"{row['scenario']} ({row['episodes']})" if first else ""
            first = False
            lines.append(f"| {scenario} | {name} | {_pct(d['success_rate'], d['success_wilson95'])} | "
                         f"{_pct(d['collision_rate'], d['collision_wilson95'])} | {d['normalised']:.2f} |")
    lines += ["", "| driver | mean normalised score over the suite | paired test against the first driver "
              "(all episodes of the suite) |", "|---|---|---|"]
    for d in summary["drivers"]:
        test = d["mcnemar_vs_first"]["verdict"] if "mcnemar_vs_first" in d else "(the first driver)"
        if d["driver"] in (CEILING, FLOOR):
            test = "" if "mcnemar_vs_first" not in d else test
        lines.append(f"| `{d['driver']}` | {d['mean_normalised']:.3f} | {test} |")
    agg = [g for g in summary["groups"] if "aggregate" in g]
    if agg:
        lines += ["", "Per method over its runs (training seeds) and the scenarios: interquartile mean and mean of "
                  "the normalised scores, with rliable's stratified-bootstrap 95% interval over runs (none with "
                  "one run).", "", "| method | runs | IQM [bootstrap 95%] | mean [bootstrap 95%] |",
                  "|---|---|---|---|"]  # fmt: skip
        for g in agg:
            cells = []
            for k in ("iqm", "mean"):
                a = g["aggregate"][k]
                ci = a["ci95"]
                cells.append(f"{a['value']:.3f}" + (f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else ""))
            lines.append(f"| {g['group']} | {len(g['runs'])} | {cells[0]} | {cells[1]} |")
    tested = [g for g in summary["groups"] if "mcnemar_vs_first_group" in g]
    if tested and any(len(g["runs"]) > 1 for g in summary["groups"]):
        first = tested[0]["mcnemar_vs_first_group"]["first"]
        lines += ["", f"Per method against `{first}`: McNemar's test on every episode of the suite, pooled over the "
                  "runs paired training seed with training seed (or, where a run's seed is unknown, in the order "
                  "given).", "", "| method | pairs | paired by | only the first won | only this won | p | verdict |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for g in tested:
            t = g["mcnemar_vs_first_group"]
            by = "training seed" if t["paired_by"] == "key" else "order given"
            lines.append(f"| {g['group']} | {len(t['pairs'])} runs, {t['n']} episodes | {by} | {t['only_a']} | "
                         f"{t['only_b']} | {t['p_value']:.2g} | {t['verdict']} |")
    seeds = [g for g in summary["groups"] if "success_over_seeds" in g]
    if seeds:
        lines += ["", "Success over training seeds: mean with the t 95% interval over seeds.", "",
                  "| method | scenario | seeds | success % [t 95% over seeds] |", "|---|---|---|---|"]
        for g in seeds:
            for sc, s in g["success_over_seeds"].items():
                lines.append(f"| {g['group']} | {sc} | {s['runs']} | {_pct(s['mean'], s['t95'])} |")
    if figures:
        lines += ["", figures.rstrip("\n")]
    if command:
        lines += ["", f"`{command}`"]
    return "\n".join(lines) + "\n"


__all__ = ["CEILING", "FLOOR", "suite_markdown", "suite_summary"]
