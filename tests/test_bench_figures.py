"""The suite table's methods compared run with run, and its figures: written, non-empty, the table's numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcmodels.bench.figures import FIGURES, FORMATS, figures_markdown, normalised_bars, write_figures
from lcmodels.bench.ledger import counts
from lcmodels.bench.table import CEILING, FLOOR, suite_markdown, suite_summary
from lcmodels.stats import mcnemar
from lcsim.suite import SuiteScenario


def _cells(rng: np.random.Generator, labels: dict[str, float], roads: list[str], n: int) -> dict:
    cells = {}
    for label, p in labels.items():
        for road in roads:
            outcomes = "".join(np.where(rng.random(n) < p, "s", "c"))
            cells[(label, road)] = {"outcomes": outcomes, **counts(outcomes)}
    return cells


@pytest.fixture
def summary() -> dict:
    rng = np.random.default_rng(0)
    roads = ["a", "b", "c"]
    runs = {"hybrid": ["h0", "h1", "h2"], "pure": ["p0", "p1", "p2"], "image": ["i0"]}
    rates = {CEILING: 0.95, FLOOR: 0.6, "h0": 0.8, "h1": 0.78, "h2": 0.82, "p0": 0.6, "p1": 0.62, "p2": 0.58, "i0": 0.7}
    cells = _cells(rng, rates, roads, 200)
    drivers = [(lb, g) for g, labels in runs.items() for lb in labels]
    scenarios = [SuiteScenario(name=r, block=i, test_episodes=10, what=r, make=lambda: None) for i, r in enumerate(roads)]
    s = suite_summary(cells, drivers, scenarios, suite="t", split="validation seed 0")
    s["_cells"] = cells
    return s


def test_methods_are_tested_against_the_first_run_with_run_on_the_same_episodes(summary: dict) -> None:
    cells = summary.pop("_cells")
    groups = {g["group"]: g for g in summary["groups"]}
    assert "mcnemar_vs_first_group" not in groups["hybrid"]
    pure = groups["pure"]["mcnemar_vs_first_group"]
    assert pure["pairs"] == [["h0", "p0"], ["h1", "p1"], ["h2", "p2"]] and pure["n"] == 3 * 3 * 200
    won = {lb: np.concatenate([np.frombuffer(cells[(lb, r)]["outcomes"].encode(), np.uint8) == ord("s")
                               for r in "abc"]) for lb in ("h0", "h1", "h2", "p0", "p1", "p2")}
    expect = mcnemar(np.concatenate([won[f"h{k}"] for k in range(3)]), np.concatenate([won[f"p{k}"] for k in range(3)]))
    assert (pure["only_a"], pure["only_b"], pure["p_value"]) == (expect.only_a, expect.only_b, expect.p_value)
    assert pure["p_value"] < 1e-6 and "hybrid beats pure" in pure["verdict"]
    assert groups["image"]["mcnemar_vs_first_group"]["pairs"] == [["h0", "i0"]]  # fewer runs: the first pairs
    assert set(pure["per_scenario"]) == {"a", "b", "c"}
    md = suite_markdown(summary)
    assert "| pure | 3 runs, 1800 episodes | order given |" in md


def test_runs_pair_by_training_seed_where_every_run_has_one() -> None:
    rng = np.random.default_rng(1)
    rates = {CEILING: 0.9, FLOOR: 0.5, "h0": 0.8, "h2": 0.8, "p1": 0.6, "p2": 0.6}
    cells = _cells(rng, rates, ["a"], 50)
    scenarios = [SuiteScenario(name="a", block=0, test_episodes=10, what="a", make=lambda: None)]
    keys = {"h0": 0, "h2": 2, "p1": 1, "p2": 2}
    s = suite_summary(cells, [("h0", "h"), ("h2", "h"), ("p1", "p"), ("p2", "p")], scenarios, suite="t",
                      split="validation seed 0", pair_keys=keys)  # fmt: skip
    test = s["groups"][1]["mcnemar_vs_first_group"]
    assert test["pairs"] == [["h2", "p2"]] and test["paired_by"] == "key" and test["n"] == 50  # seed 2 alone
    order = suite_summary(cells, [("h0", "h"), ("h2", "h"), ("p1", "p"), ("p2", "p")], scenarios, suite="t",
                          split="validation seed 0")["groups"][1]["mcnemar_vs_first_group"]  # fmt: skip
    assert order["pairs"] == [["h0", "p1"], ["h2", "p2"]] and order["paired_by"] == "order"


def test_the_figures_are_written_beside_the_table_and_show_its_numbers(summary: dict, tmp_path: Path) -> None:
    summary.pop("_cells")
    bars = normalised_bars(summary)
    assert bars["methods"] == ["hybrid", "pure", "image"] and bars["value"].shape == (3, 3)
    hybrid_a = [next(r for r in summary["scenarios"] if r["scenario"] == "a")["drivers"][lb]["normalised"]
                for lb in ("h0", "h1", "h2")]
    assert bars["value"][0, 0] == pytest.approx(np.mean(hybrid_a))
    assert (bars["low"] <= bars["value"]).all() and (bars["value"] <= bars["high"]).all()
    paths = write_figures(summary, tmp_path / "out")
    assert sorted(p.name for p in paths) == sorted(f"{s}.{f}" for s in FIGURES for f in FORMATS)
    for p in paths:
        assert p.stat().st_size > 1000
    assert (tmp_path / "out" / "bench_normalised.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "<svg" in (tmp_path / "out" / "bench_intervals.svg").read_text()
    assert "![bench_normalised](bench_normalised.svg)" in figures_markdown()
