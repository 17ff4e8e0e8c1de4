"""The ablation's verdict from what the experiment measured: per block, the hybrid input first, every other input
tested against it with its runs paired seed with seed; a partial ablation says what is missing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lcmodels.ablation import block_summary, verdict_markdown, verdict_rows, write_ablation
from lcmodels.bench.ledger import counts
from lcmodels.presets import policy_dir

ROADS = ("paper", "dense")


def _write(path: Path, label: str, rate: float, rng: np.random.Generator, n: int = 120) -> None:
    cells = {}
    for road in ROADS:
        outcomes = "".join(np.where(rng.random(n) < rate, "s", "c"))
        cells[road] = {"outcomes": outcomes, **counts(outcomes)}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"config": {"suite": "highway", "seed": 0, "episodes": n}, "label": label,
                                "cells": cells}))  # fmt: skip


def test_each_input_against_the_hybrid_input_paired_seed_with_seed(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    _write(tmp_path / "suite" / "oracle" / "suite.json", "oracle", 0.95, rng)
    _write(tmp_path / "suite" / "rule" / "suite.json", "rule", 0.6, rng)
    rates = {"hybrid": 0.85, "pure": 0.6, "image": 0.7, "prediction": 0.8}
    for mode, rate in rates.items():
        for seed in range(3):
            if (mode, seed) == ("image", 1):
                continue  # not measured yet
            _write(policy_dir(tmp_path, f"ablation-{mode}", seed) / "suite" / "suite.json", mode, rate, rng)
    assert block_summary(tmp_path, "roads") is None  # nothing of that block measured
    s = block_summary(tmp_path, "paper")
    assert [g["group"] for g in s["groups"]] == ["hybrid", "pure", "image", "prediction"]
    assert s["missing"] == ["ablation-image/seed1", *(f"ablation-lane-aware/seed{k}" for k in range(3))]
    rows = {r["input"]: r for r in verdict_rows(s)}
    assert "vs_hybrid" not in rows["hybrid"] and rows["hybrid"]["paper_table4"] == 87.8
    assert rows["image"]["vs_hybrid"]["pairs"] == [["hybrid/seed0", "image/seed0"], ["hybrid/seed2", "image/seed2"]]
    assert rows["pure"]["vs_hybrid"]["n"] == 3 * 2 * 120 and rows["pure"]["vs_hybrid"]["p_value"] < 1e-6
    assert "hybrid beats pure" in rows["pure"]["vs_hybrid"]["verdict"]
    assert 0.5 < rows["pure"]["paper_success"] < 0.7 and rows["pure"]["runs"] == 3
    md = verdict_markdown(s)
    assert "| pure | 3 |" in md and "Not measured yet (4 runs)" in md
    (tmp_path / "docs").mkdir()
    written = write_ablation(tmp_path, tmp_path / "docs")
    assert (tmp_path / "docs" / "paper" / "BENCH.md").is_file() and (tmp_path / "docs" / "ablation.json") in written
    assert "| pure | 3 |" in (tmp_path / "docs" / "VERDICT.md").read_text()
    assert not (tmp_path / "docs" / "roads").exists()
