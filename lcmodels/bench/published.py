"""Published tables made from the ledger, and the check that what a document quotes is what the ledger holds.

``docs/results/benchmark/published.toml`` lists the tables the documents show: each row names the policies it
reports (zoo entries or committed policy files, a safety layer's follower and settings) exactly as
``lc-bench`` takes them. :func:`render_table` finds each one's ledger entry by its identity (never by a label,
never by running anything) and writes the Markdown; :func:`update_blocks` rewrites the blocks between
``<!-- ledger:NAME -->`` and ``<!-- /ledger -->`` in a document, and :func:`stale_blocks` says which blocks
differ from what the ledger gives (``tools/publish_ledger.py --check`` and ``tests/test_published.py``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lckit.config import read_data_file
from lcmodels.bench.ledger import cell_key, find_entry, read_ledger
from lcmodels.bench.run import resolve_driver, scenario_sha256
from lcmodels.policy.driverspec import parse_driver_spec, split_safety_layer, zoo_safety_layer
from lcmodels.stats import McNemar, mcnemar, t_interval
from lcsim.suite import SUITE_SCENARIOS, suite

BLOCK = re.compile(r"(<!-- ledger:(?P<name>[a-z0-9-]+) -->\n)(?P<body>.*?)(<!-- /ledger -->)", re.S)
ROOT = Path(__file__).resolve().parents[2]
SPEC = ROOT / "docs" / "results" / "benchmark" / "published.toml"


@dataclass(frozen=True)
class Found:
    """A run of a published row and its ledger entry (``None``: not measured yet)."""

    spec: str
    entry: dict[str, Any] | None
    note: str = ""


def _key(spec: str, sc_name: str, follow: str | None, safety: dict[str, Any] | None) -> str:
    """The ledger key of a run of a row: a driver spec, the follower and the ``[safety]`` settings of a row
    behind the safety layer (the settings apply to the runs behind it)."""
    sc = SUITE_SCENARIOS[sc_name]
    layer = split_safety_layer(spec)[1] is not None
    driver = resolve_driver(parse_driver_spec(spec, safety_table=safety if layer else None, follow=follow, where=spec))
    return cell_key(driver.identity, scenario_sha256(sc.make()), sc.sealed_seeds())


def _safety_table(row: dict[str, Any]) -> dict[str, Any] | None:
    """A row's safety layer settings: its ``safety`` table (``lookahead``: the older name)."""
    return row.get("safety", row.get("lookahead"))


def _pct(rate: float, ci: list[float] | tuple[float, float]) -> str:
    return f"{100 * rate:.1f} [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"


def _runs(row: dict[str, Any], sc: str, entries: list[dict[str, Any]]) -> list[Found]:
    follows = row.get("follow") or [None] * len(row["runs"])
    notes = row.get("notes") or [""] * len(row["runs"])
    out = []
    for spec, follow, note in zip(row["runs"], follows, notes, strict=True):
        with _in_root():
            key = _key(spec, sc, follow, _safety_table(row))
        out.append(Found(spec, find_entry(entries, key), note))
    return out


class _in_root:
    """Resolve the relative paths of the spec from the checkout's root."""

    def __enter__(self) -> None:
        import os

        self.cwd = os.getcwd()
        os.chdir(ROOT)

    def __exit__(self, *exc: object) -> None:
        import os

        os.chdir(self.cwd)


def _rows_table(table: dict[str, Any], entries: list[dict[str, Any]], base: str) -> str:
    sc = table.get("scenario", "paper")
    n = SUITE_SCENARIOS[sc].test_episodes
    lines = [f"Sealed test episodes of `{sc}` ({n}); success and collision in %. One run: its Wilson 95% interval "
             "over episodes; several training seeds: their mean with the t 95% interval over seeds, then each "
             "seed's own figure.", "",
             "| method | recipe | success % | collision % | shipped |", "|---|---|---|---|---|"]  # fmt: skip
    found_by_label: dict[str, list[Found]] = {}
    for row in table["row"]:
        runs = _runs(row, sc, entries)
        found_by_label[row["label"]] = runs
        done = [f for f in runs if f.entry is not None]
        recipe = row.get("recipe", "")
        recipe_cell = f"[`{recipe}`]({base}lcmodels/recipes/{recipe}.toml)" if recipe else ""
        if "reported" in row:  # the paper's own figure, on its own episodes
            success, collision = (f"{v:.1f} (the paper's, {row.get('where', 'its own episodes')})"
                                  for v in row["reported"])  # fmt: skip
        elif not done:
            success, collision = "not measured yet", ""
        elif len(done) == 1:
            e = done[0].entry
            assert e is not None
            success = _pct(e["success_rate"], e["success_wilson95"])
            if len(runs) > 1:
                success += f" ({done[0].note or done[0].spec}; {len(runs) - 1} more not measured yet)"
            collision = _pct(e["collision_rate"], e["collision_wilson95"])
        else:
            rates = [f.entry["success_rate"] for f in done if f.entry]
            lo, hi = t_interval(rates)
            each = "; ".join(f"{f.note or f.spec} {_pct(f.entry['success_rate'], f.entry['success_wilson95'])}"
                             for f in done if f.entry)  # fmt: skip
            missing = f" ({len(runs) - len(done)} more not measured yet)" if len(done) < len(runs) else ""
            success = (f"**{100 * np.mean(rates):.1f}**, t 95% [{100 * lo:.1f}, {100 * hi:.1f}] over {len(done)} "
                       f"seeds{missing}: {each}")
            collision = f"{100 * np.mean([f.entry['collision_rate'] for f in done if f.entry]):.1f} (mean)"
        lines.append(f"| {row['label']} | {recipe_cell} | {success} | {collision} | {row.get('shipped', '')} |")
    for cmp in table.get("compare", []):
        a_runs = [[f.entry] for f in found_by_label[cmp["a"]] if f.entry]
        b_runs = [[f.entry] for f in found_by_label[cmp["b"]] if f.entry]
        for pairing, runs, test in paired_tests(a_runs, b_runs):
            lines += ["", f"{cmp['a']} against {cmp['b']}: these policies paired episode by episode ({test.n} pairs: "
                      f"{runs} training seed(s) of each, {pairing}): {test.only_a} won by the first alone, "
                      f"{test.only_b} by the second alone; {test.verdict(cmp.get('a_short', 'the first'), cmp.get('b_short', 'the second'))}."]  # fmt: skip
    return "\n".join(lines)


def _training_seed(run: list[dict[str, Any]]) -> Any:
    return (run[0].get("about") or {}).get("training_seed") if run else None


def _won(run: list[dict[str, Any]]) -> np.ndarray:
    return np.concatenate([np.frombuffer(e["outcomes"].encode(), np.uint8) == ord("s") for e in run])


def paired_tests(a_runs: list[list[dict[str, Any]]],
                 b_runs: list[list[dict[str, Any]]]) -> list[tuple[str, int, McNemar]]:
    """McNemar's test of two methods' runs (each run: its ledger entries, one per road, in the same order), as
    ``[(how the runs are paired, runs paired, test)]``: the runs paired in the order given, named as they are
    paired (``seed with seed`` only when each pair shares its training seed); and when that pairs different
    training seeds, beside it the runs of the same training seed paired (when there are any)."""
    pairs = list(zip(a_runs, b_runs, strict=False))
    if not pairs:
        return []

    def test(chosen: list[tuple[list[dict[str, Any]], list[dict[str, Any]]]]) -> McNemar:
        return mcnemar(np.concatenate([_won(a) for a, _ in chosen]), np.concatenate([_won(b) for _, b in chosen]))

    seeds = [(_training_seed(a), _training_seed(b)) for a, b in pairs]
    if all(x == y and x is not None for x, y in seeds):
        return [("seed with seed", len(pairs), test(pairs))]
    named = ", ".join(f"training seed {x} of the first with training seed {y} of the second" for x, y in seeds)
    out = [(named, len(pairs), test(pairs))]
    of_b = {_training_seed(b): b for b in b_runs if _training_seed(b) is not None}
    same = [(a, of_b[_training_seed(a)]) for a in a_runs if _training_seed(a) in of_b]
    if same:
        which = ", ".join(str(_training_seed(a)) for a, _ in same)
        out.append((f"seed with seed: training seed {which} of each", len(same), test(same)))
    return out


def _suite_table(table: dict[str, Any], entries: list[dict[str, Any]], base: str) -> str:
    from lcmodels.bench.table import CEILING, FLOOR, suite_summary

    scenarios = suite(table.get("suite", "highway"))
    drivers = [*table["drivers"]]
    cells: dict[tuple[str, str], dict[str, Any]] = {}
    groups = {}
    missing = []
    with _in_root():
        resolved = {d: resolve_driver(d) for d in [CEILING, FLOOR, *drivers]}
    for sc in scenarios:
        for d, drv in resolved.items():
            e = find_entry(entries, cell_key(drv.identity, scenario_sha256(sc.make()), sc.sealed_seeds()))
            if e is None:
                missing.append(f"{d} on {sc.name}")
            else:
                cells[(d, sc.name)] = e
        groups = {d: table.get("groups", {}).get(d, resolved[d].group) for d in drivers}
    if missing:
        return f"Not measured yet: {', '.join(missing)}."
    names = table.get("names", {})
    summary = suite_summary(cells, [(d, groups[d]) for d in drivers], scenarios, suite=table.get("suite", "highway"),
                            split="test")  # fmt: skip
    head = ["scenario (sealed episodes)", "ceiling: oracle", "floor: rule", *(names.get(d, d) for d in drivers)]
    lines = ["Success % of the sealed test episodes [Wilson 95% over episodes] and, after the slash, the normalised "
             "score (success / the oracle's success on the same episodes).", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]  # fmt: skip
    for row in summary["scenarios"]:
        cells_md = []
        for d in [CEILING, FLOOR, *drivers]:
            x = row["drivers"][d]
            cells_md.append(f"{_pct(x['success_rate'], x['success_wilson95'])} / {x['normalised']:.2f}")
        lines.append(f"| {row['scenario']} ({row['episodes']}) | " + " | ".join(cells_md) + " |")
    means = {d["driver"]: d["mean_normalised"] for d in summary["drivers"]}
    lines.append("| **mean normalised score** | " + " | ".join(f"{means[d]:.3f}" for d in [CEILING, FLOOR, *drivers])
                 + " |")
    agg = [g for g in summary["groups"] if "aggregate" in g]
    if agg:
        lines += ["", "Per method over its training seeds and the suite's scenarios (rliable: interquartile mean and "
                  "mean of the normalised scores, stratified-bootstrap 95% intervals over runs):", "",
                  "| method | runs | IQM [bootstrap 95%] | mean [bootstrap 95%] |", "|---|---|---|---|"]
        for g in agg:
            parts = []
            for k in ("iqm", "mean"):
                a = g["aggregate"][k]
                parts.append(f"{a['value']:.3f}" + (f" [{a['ci95'][0]:.3f}, {a['ci95'][1]:.3f}]" if a["ci95"] else ""))
            lines.append(f"| {g['group']} | {len(g['runs'])} | {parts[0]} | {parts[1]} |")
    for cmp in table.get("compare", []):
        a_runs = [[cells[(a, sc.name)] for sc in scenarios] for a in cmp["a"]]
        b_runs = [[cells[(b, sc.name)] for sc in scenarios] for b in cmp["b"]]
        for pairing, _, test in paired_tests(a_runs, b_runs):
            lines += ["", f"{cmp['a_name']} against {cmp['b_name']} on every episode of the suite, paired ({test.n} "
                      f"pairs, {pairing}): {test.only_a} won by the first alone, {test.only_b} by the second alone; "
                      f"{test.verdict(cmp['a_name'], cmp['b_name'])}."]  # fmt: skip
    return "\n".join(lines)


def _dig(data: Any, path: str) -> Any:
    for part in path.split("."):
        data = data.get(part) if isinstance(data, dict) else None
    return data


def _remeasured_table(table: dict[str, Any], entries: list[dict[str, Any]], base: str) -> str:
    """Each row's figure as published before (read from the file the row names) next to its sealed test figure
    from the ledger, and the difference."""
    from lcmodels.fileio import read_json

    sc = table.get("scenario", "paper")
    lines = [f"| row | before: {table['before']} | sealed test: {SUITE_SCENARIOS[sc].test_episodes} episodes of "
             f"`{sc}` | difference, points | before, from |", "|---|---|---|---|---|"]  # fmt: skip
    for row in table["row"]:
        found = _runs({"runs": [row["run"]], "follow": [row.get("follow")], "safety": _safety_table(row)},
                      sc, entries)[0]  # fmt: skip
        old = read_json(ROOT / row["before"]) or {}
        rate, ci = _dig(old, row["before_key"] + ".success_rate"), _dig(old, row["before_key"] + ".success_rate_ci95")
        before = _pct(rate, ci) if rate is not None and ci else "—"
        source = f"[{Path(row['before']).parent.name}]({base}{row['before']})"
        if found.entry is None:
            lines.append(f"| {row['label']} | {before} | not measured yet | | {source} |")
            continue
        e = found.entry
        diff = f"{100 * (e['success_rate'] - rate):+.1f}" if rate is not None else ""
        lines.append(f"| {row['label']} | {before} | {_pct(e['success_rate'], e['success_wilson95'])} | {diff} "
                     f"| {source} |")
    return "\n".join(lines)


def load_spec(path: Path = SPEC) -> dict[str, dict[str, Any]]:
    """The published tables by name."""
    data = read_data_file(path, "published tables")
    return {t["name"]: t for t in data.get("table", [])}


def render_table(name: str, *, spec: dict[str, dict[str, Any]] | None = None,
                 entries: list[dict[str, Any]] | None = None, base: str = "") -> str:
    """The Markdown of published table ``name`` from the ledger; ``base``: the way from the document's folder
    to the checkout's root (its links start with it)."""
    spec = load_spec() if spec is None else spec
    entries = read_ledger() if entries is None else entries
    if name not in spec:
        raise ValueError(f"no published table {name!r} (docs/results/benchmark/published.toml has "
                         f"{', '.join(spec)})")
    table = spec[name]
    kinds = {"suite": _suite_table, "remeasured": _remeasured_table}
    return kinds.get(table.get("kind", ""), _rows_table)(table, entries, base)


def link_base(document: Path) -> str:
    """The relative way from ``document``'s folder to the checkout's root (``""``, ``"../"``, ``"../../"``)."""
    import os

    rel = os.path.relpath(ROOT, Path(document).resolve().parent)
    return "" if rel == "." else rel + "/"


def update_blocks(text: str, document: Path, **kw: Any) -> str:
    """``text`` of ``document`` with every ``<!-- ledger:NAME -->`` block rendered anew."""
    base = link_base(document)
    return BLOCK.sub(lambda m: m.group(1) + render_table(m.group("name"), base=base, **kw) + "\n" + m.group(4), text)


def stale_blocks(text: str, document: Path, **kw: Any) -> list[str]:
    """The names of the blocks of ``document`` (its ``text``) that differ from what the ledger gives."""
    base = link_base(document)
    return [m.group("name") for m in BLOCK.finditer(text)
            if m.group("body") != render_table(m.group("name"), base=base, **kw) + "\n"]  # fmt: skip


def _figures(entry: dict[str, Any]) -> dict[str, Any]:
    keep = ("key", "scenario", "episodes", "success_rate", "success_wilson95", "collision_rate", "collision_wilson95",
            "timeout_rate", "commit", "date", "planner_overrides", "planner_choices")
    return {("ledger_key" if k == "key" else k): entry[k] for k in keep if k in entry}


def zoo_sealed(name: str, entries: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """What the card of zoo entry ``name`` says of the sealed test episodes of the paper's road: ``{"alone":
    figures or None, "safety_layer": figures or None}`` from the ledger (the layer: following the zoo entry of
    the recipe its card names, with the card's settings)."""
    from lcmodels.zoo import zoo_entries, zoo_entry

    entries = read_ledger() if entries is None else entries
    entry = zoo_entry(name)
    sc = SUITE_SCENARIOS["paper"]
    digest, seeds = scenario_sha256(sc.make()), sc.sealed_seeds()
    alone = find_entry(entries, cell_key(resolve_driver(f"zoo:{name}").identity, digest, seeds))
    out: dict[str, Any] = {"alone": _figures(alone) if alone else None, "safety_layer": None}
    layer = entry.card.get("safety_layer") or {}
    follow = (layer.get("follow") or {}).get("recipe")
    if follow:
        weights = (layer.get("follow") or {}).get("weights_sha256")
        follower = next((e for e in zoo_entries() if e.card.get("recipe") == follow
                         and (weights is None or e.weights_sha256 == weights)), None)  # fmt: skip
        safety = zoo_safety_layer(entry, f"zoo:{follower.name}") if follower is not None else None
        if safety is not None:
            drv = resolve_driver(f"safety-layer:zoo:{name}", safety=safety)
            found = find_entry(entries, cell_key(drv.identity, digest, seeds))
            out["safety_layer"] = _figures(found) if found else None
    return out


def zoo_card_problems(entries: list[dict[str, Any]] | None = None) -> list[str]:
    """Zoo cards whose ``sealed_test`` differs from the ledger (``tools/publish_ledger.py`` writes them)."""
    from lcmodels.zoo import zoo_entries

    entries = read_ledger() if entries is None else entries
    problems = []
    for e in zoo_entries():
        want = zoo_sealed(e.name, entries)
        if e.card.get("sealed_test") != want:
            problems.append(f"zoo/{e.name}/zoo.json: sealed_test differs from the ledger")
    return problems


SUITE_FILE = ROOT / "docs" / "results" / "benchmark" / "suite.json"


def suite_record(entries: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The suite as stored beside the ledger: per road its block of sealed seeds, episode count, config digest,
    and its ceiling (oracle) and floor (rule-based driver) from the ledger (``None`` until measured)."""
    entries = read_ledger() if entries is None else entries
    roads = {}
    for name, sc in SUITE_SCENARIOS.items():
        digest, seeds = scenario_sha256(sc.make()), sc.sealed_seeds()
        refs = {}
        for role, driver in (("ceiling", "oracle"), ("floor", "rule")):
            e = find_entry(entries, cell_key({"kind": "driver", "name": driver}, digest, seeds))
            refs[role] = None if e is None else {"driver": driver, **_figures(e)}
        roads[name] = {"what": sc.what, "block": sc.block, "test_episodes": sc.test_episodes,
                       "first_seed": seeds[0], "scenario_sha256": digest, **refs}  # fmt: skip
    from lcsim.suite import SUITES

    return {"suites": {k: list(v) for k, v in SUITES.items()}, "roads": roads}


__all__ = [
    "BLOCK",
    "SPEC",
    "SUITE_FILE",
    "link_base",
    "load_spec",
    "paired_tests",
    "render_table",
    "stale_blocks",
    "suite_record",
    "update_blocks",
    "zoo_card_problems",
    "zoo_sealed",
]
