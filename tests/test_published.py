"""Every published figure is the one its source holds: the ledger's tables in the README, the results index, the
zoo's README and the benchmark's note; the zoo cards' sealed test figures; every figure a sentence of a document
about the ledger quotes, in the own rows of the method it names (lcmodels/bench/quoted.py) or a file it links;
the commits documents quote; the labels of seed 9; and recipes that quote no figures."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from lcmodels.bench import quoted
from lcmodels.bench.ledger import counts, read_ledger
from lcmodels.bench.published import (
    BLOCK,
    SUITE_FILE,
    load_spec,
    paired_tests,
    stale_blocks,
    suite_record,
    zoo_card_problems,
)
from lcmodels.experiment.recipe import load_recipe
from lcmodels.zoo import zoo_entries

ROOT = Path(__file__).resolve().parent.parent
DOCUMENTS = ("README.md", "docs/results/README.md", "zoo/README.md", "docs/results/benchmark/NOTE.md")


@pytest.fixture(scope="module")
def entries() -> list[dict]:
    return read_ledger()


def test_the_ledger_is_well_formed_and_its_counts_are_its_outcomes(entries):
    assert entries, "the committed ledger is empty"
    keys = [e["key"] for e in entries]
    assert len(set(keys)) == len(keys), "an evaluation appears twice"
    for e in entries:
        assert e["split"] == "test" and e["commit"] and not e.get("dirty"), e["key"]
        again = counts(e["outcomes"])
        for k in ("success", "collision", "off_road", "timeout", "success_rate", "collision_rate"):
            assert e[k] == again[k], (e["key"], k)


@pytest.mark.parametrize("document", DOCUMENTS)
def test_every_ledger_block_is_what_the_ledger_gives(document: str, entries):
    path = ROOT / document
    text = path.read_text()
    names = [m.group("name") for m in BLOCK.finditer(text)]
    assert set(names) <= set(load_spec())
    assert stale_blocks(text, path, entries=entries) == [], "run python tools/publish_ledger.py"


def test_a_figure_changed_by_hand_is_caught(entries):
    path = ROOT / "README.md"
    text = path.read_text()
    m = next(BLOCK.finditer(text))
    body = m.group("body")
    figure = re.search(r"\d+\.\d \[", body)
    assert figure, "the README's results block quotes no figure"
    i = m.start("body") + figure.start()
    digit = text[i]
    forged = text[:i] + ("1" if digit != "1" else "2") + text[i + 1 :]
    assert stale_blocks(forged, path, entries=entries) == [m.group("name")]


def test_the_zoo_cards_quote_the_ledger(entries):
    assert zoo_card_problems(entries) == []
    for e in zoo_entries():
        assert "test" not in e.card and "test" not in (e.card.get("safety_layer") or {}), e.name
        assert e.card["sealed_test"]["alone"] is not None, f"zoo:{e.name} has no sealed test figure"
        if (e.card.get("safety_layer") or {}).get("follow"):  # measured behind its layer: that figure too
            assert e.card["sealed_test"]["safety_layer"] is not None, f"zoo:{e.name}: no sealed figure behind its layer"


def test_the_suite_is_stored_with_its_ceilings_and_floors(entries):
    stored = json.loads(SUITE_FILE.read_text())
    now = suite_record(entries)
    for name, road in now["roads"].items():
        assert name in stored["roads"], f"road {name} is new: run python tools/publish_ledger.py"
        assert road["scenario_sha256"] == stored["roads"][name]["scenario_sha256"], (
            f"road {name}'s config changed: its sealed entries no longer apply; re-measure with lc-bench --final "
            "and run python tools/publish_ledger.py")  # fmt: skip
        assert road["ceiling"] is not None and road["floor"] is not None, f"{name} has no ceiling or floor yet"
        assert road["ceiling"]["success_rate"] > road["floor"]["success_rate"], name
    assert stored == now


COVERED = ("README.md", *sorted(p.relative_to(ROOT).as_posix() for folder in ("docs/results", "zoo")
                                 for p in (ROOT / folder).rglob("*.md")
                                 if re.search(r"sealed|ledger", p.read_text(), re.I)))  # fmt: skip
"""Every document that states figures of the ledger (it names the sealed test episodes or the ledger)."""


@pytest.fixture(scope="module")
def sources(entries) -> quoted.Sources:
    return quoted.method_sources(entries)


@pytest.fixture(scope="module")
def alias_of(sources) -> dict[str, str]:
    return quoted.aliases(sources)


def test_the_covered_documents_are_those_the_ledger_is_published_in_and_more():
    assert set(DOCUMENTS) <= set(COVERED) and len(COVERED) > len(DOCUMENTS)
    assert "docs/results/roads/NOTE.md" in COVERED and "docs/results/routes/NOTE.md" in COVERED


@pytest.mark.parametrize("document", COVERED)
def test_every_quoted_figure_is_its_methods_own(document: str, sources, alias_of):
    """A rate or a score a sentence (a table cell: with its row's and its column's names) quotes is in the own rows
    of a method it names; a p-value or a count of pairs, in a paired test of two methods it names; else in a file
    it links. In the documents the ledger's tables are published in, every sentence; elsewhere, those about the
    sealed test episodes. Commit hashes: in the history."""
    path = ROOT / document
    text = path.read_text()
    assert text.count("<!-- ledger:") == len(list(BLOCK.finditer(text))), "a malformed ledger marker"
    missing = quoted.problems(path, every_unit=document in DOCUMENTS, sources=sources, alias_of=alias_of)
    assert missing == [], f"{document}: figures their source does not hold:\n" + "\n".join(missing)


def _problems(text: str, path: Path, sources, alias_of) -> list[str]:
    every_unit = path.relative_to(ROOT).as_posix() in DOCUMENTS
    return quoted.problems(path, text, every_unit=every_unit, sources=sources, alias_of=alias_of)


def test_a_figure_of_another_method_is_caught(sources, alias_of):
    """The case of the report: the oracle's 94.5 said of Hybrid-PPO passed because it was somewhere in a block."""
    path = ROOT / "docs" / "results" / "README.md"
    text = path.read_text()
    assert _problems(text, path, sources, alias_of) == []
    for sentence, caught in (("Hybrid-PPO alone wins 94.5% of the sealed episodes.", "94.5"),
                             ("The oracle wins 94.5% of the sealed episodes.", None),
                             ("PPO pure with DAgger wins 73.6% of the sealed episodes.", "73.6"),
                             ("PPO pure beats Hybrid-PPO on the suite (McNemar p = 0.0009).", "0.0009"),
                             ("PPO pure on the suite's roads beats PPO pure (908 against 771, p = 0.0009).", None),
                             ("Hybrid-PPO against PPO pure: 841 against 771 won alone.", "771"),
                             ("`zoo:roads-ppo` scores 0.726 over the suite, `zoo:pure-ppo` 0.726.", None),
                             ("`zoo:hybrid-ppo` scores 0.726 over the suite.", "0.726")):  # fmt: skip
        found = _problems(text + "\n" + sentence + "\n", path, sources, alias_of)
        assert found == ([] if caught is None else [f"{caught} in: {sentence}"]), sentence


def test_a_figure_changed_in_a_hand_written_sealed_table_is_caught(sources, alias_of):
    path = ROOT / "docs" / "results" / "roads" / "NOTE.md"
    text = path.read_text()
    row = next(line for line in text.splitlines() if line.startswith("| paper (2000) |"))
    assert "| 76.9 |" in row  # roads-ppo seed 0 on the paper's road; 76.8 is pure-ppo seed 0's, not roads-ppo's
    found = _problems(text.replace(row, row.replace("| 76.9 |", "| 76.8 |")), path, sources, alias_of)
    assert found == ["76.8 in: 76.8"]  # (the cell alone is its text)


def test_a_prose_figure_changed_by_hand_is_caught(sources, alias_of):
    path = ROOT / "docs" / "results" / "README.md"
    text = path.read_text()
    row = next(line for line in text.splitlines() if line.startswith("| paper-best |") and "76.5%" in line)
    found = _problems(text.replace(row, row.replace("76.5%", "12.3%")), path, sources, alias_of)
    assert len(found) == 1 and found[0].startswith("12.3 in: ")
    assert _problems(text + "\nThe best policy wins 99.9% of the episodes.\n", path, sources, alias_of)


def test_quoted_commits_are_in_the_history():
    if quoted.known_commit("HEAD") is not True:
        pytest.skip("no git history here")
    text = (ROOT / "zoo" / "README.md").read_text()
    commits = quoted.quoted_commits(text)
    assert "1b425b6" in commits and "43aa187" in commits
    assert all(quoted.known_commit(c) for c in commits)
    assert quoted.known_commit("0123abc") is False or quoted.known_commit("0123abc") is None
    found = quoted.problems(ROOT / "zoo" / "README.md", text.replace("1b425b6", "1b425b7"), every_unit=False,
                            sources=quoted.Sources({}, []), alias_of={})  # fmt: skip
    assert found == ["commit 1b425b7 is not in the history"]


def test_a_paired_test_of_different_seeds_says_so_with_the_same_seed_test_beside_it():
    def run(seed: int, letters: str) -> list[dict]:
        return [{"about": {"training_seed": seed}, "outcomes": letters}]

    a0, b0, b1 = run(0, "sscs"), run(0, "sccs"), run(1, "ccss")
    (only,) = paired_tests([a0], [b0])
    assert only[0] == "seed with seed" and only[1] == 1
    across, same = paired_tests([a0], [b1, b0])
    assert across[0] == "training seed 0 of the first with training seed 1 of the second"
    assert same[0] == "seed with seed: training seed 0 of each" and same[2] == only[2]
    assert paired_tests([a0], []) == []
    # as published: PPO pure with DAgger (training seed 0) against the shipped Hybrid-PPO (seed 1), and its own seed's
    text = (ROOT / "docs" / "results" / "README.md").read_text()
    dagger = [line for line in text.splitlines() if line.startswith("PPO on sensor data, with DAgger against")]
    assert len(dagger) == 2 and "training seed 0 of the first with training seed 1 of the second" in dagger[0]
    assert "seed with seed: training seed 0 of each" in dagger[1]


def test_seed_9_is_called_held_out_not_test():
    """Seed 9 is validation-like held-out episodes; the only test is the sealed one, through lc-bench --final."""
    from lccli.experiment import experiment_parser

    seed9_test = re.compile(r"\*\*test\*\*: \d+ held-out|\(test episodes|test success %|Every row \(test and|"
                            r"driver on the test episodes")  # fmt: skip
    for report in sorted((ROOT / "docs" / "results").rglob("REPORT.md")):
        found = seed9_test.findall(report.read_text())
        assert found == [], f"{report.relative_to(ROOT)} calls seed 9 test: {found}"
    help_text = experiment_parser().format_help()
    assert "held-out" in help_text and not re.search(r"(?<!sealed )test episodes", help_text)


def test_recipes_quote_no_figures():
    for toml in sorted((ROOT / "lcmodels" / "recipes").glob("*.toml")):
        desc = load_recipe(str(toml)).description
        assert not re.search(r"\d+(\.\d+)?\s?%", desc), f"{toml.name}: figures belong in its .reached.json"


def test_reached_records_say_what_the_seed_9_figures_are():
    for rec in sorted((ROOT / "lcmodels" / "recipes").glob("*.reached.json")):
        data = json.loads(rec.read_text())
        assert "test" not in data and "heldout" in data, rec.name
