"""Every published figure is the one its source holds: the ledger's tables in the README, the results index and
the zoo's README, the zoo cards' sealed test figures, every other percentage in those documents (found in a
file the same paragraph links), and recipes that quote no figures."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from lcmodels.bench.ledger import counts, read_ledger
from lcmodels.bench.published import (
    BLOCK,
    SUITE_FILE,
    load_spec,
    stale_blocks,
    suite_record,
    zoo_card_problems,
)
from lcmodels.experiment.recipe import load_recipe
from lcmodels.zoo import zoo_entries

ROOT = Path(__file__).resolve().parent.parent
DOCUMENTS = ("README.md", "docs/results/README.md", "zoo/README.md", "docs/results/benchmark/NOTE.md")
FIGURES = (
    re.compile(r"(?<![\w.])(\d{1,3}(?:\.\d{1,2})?)(?=\s?%)"),  # 77.2%, 2%
    re.compile(r"(?<![\w.])(\d{1,3}\.\d)(?= \[\d)"),  # 77.2 [74.5, 79.7]
    re.compile(r"(?<=\[)(\d{1,3}\.\d)(?=, \d)|(?<=, )(\d{1,3}\.\d)(?=\])"),  # its bounds
    re.compile(r"(?<![\w.])(\d{1,3}\.\d)(?= ?/ ?\d{1,3}\.\d)|(?<=\d / )(\d{1,3}\.\d)(?![\d.])"),  # 90.5 / 88.5
)
"""Quoted rates: percentages, a figure with its interval, and pairs of figures."""
LINK = re.compile(r"\]\(([^)#\s]+)")


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


def _units(text: str) -> list[str]:
    """What one figure's source must be linked from: a paragraph, but each table row and list item alone."""
    units = []
    for para in re.split(r"\n\s*\n", BLOCK.sub("", text)):
        current: list[str] = []
        for line in para.splitlines():
            if line.startswith("|") or re.match(r"\s*[-*] ", line):
                if current:
                    units.append("\n".join(current))
                current = [line]
            else:
                current.append(line)
        if current:
            units.append("\n".join(current))
    return [u for u in units if u.strip()]


LEVEL = re.compile(r"\s?%\s*(?:CI|interval|confidence|Wilson|bootstrap|t\b)")
"""A percentage that names an interval's level (95% interval), not a figure."""


def _quoted(unit: str) -> list[str]:
    found = []
    for pattern in FIGURES:
        for m in pattern.finditer(unit):
            if pattern is FIGURES[0] and LEVEL.match(unit, m.end()):
                continue
            found += [g for g in m.groups() if g]
    return found


def _holds(source: str, figure: str) -> bool:
    return re.search(rf"(?<![\d.]){re.escape(figure)}(?![\d])", source) is not None


def unsourced(text: str, path: Path) -> list[str]:
    """The rates ``text`` (the document at ``path``) quotes outside the ledger's blocks that neither a file its
    paragraph (table row, list item) links holds, a note or a report rather than raw JSON, nor this document's
    own ledger blocks, which the tests above check against the ledger."""
    blocks = "\n".join(m.group("body") for m in BLOCK.finditer(text))
    missing = []
    for unit in _units(text):
        figures = _quoted(unit)
        if not figures:
            continue
        sources = [blocks]
        for link in LINK.findall(unit):
            target = (path.parent / link).resolve()
            if target.is_dir() and (target / "NOTE.md").is_file():
                target = target / "NOTE.md"
            if target.is_file() and target.is_relative_to(ROOT) and target.suffix not in (".json", ".jsonl"):
                sources.append(target.read_text(errors="replace"))
        missing += [f"{fig} in: {unit.strip()[:110]}" for fig in figures if not any(_holds(s, fig) for s in sources)]
    return missing


@pytest.mark.parametrize("document", DOCUMENTS)
def test_every_other_figure_is_in_a_file_the_paragraph_links(document: str):
    path = ROOT / document
    text = path.read_text()
    assert text.count("<!-- ledger:") == len(list(BLOCK.finditer(text))), "a malformed ledger marker"
    missing = unsourced(text, path)
    assert missing == [], f"{document}: figures no linked file holds:\n" + "\n".join(missing)


def test_a_prose_figure_changed_by_hand_is_caught():
    path = ROOT / "docs" / "results" / "README.md"
    text = path.read_text()
    assert unsourced(text, path) == []
    row = next(line for line in text.splitlines() if line.startswith("| paper-best |") and "76.5%" in line)
    assert unsourced(text.replace(row, row.replace("76.5%", "12.3%")), path) == ["12.3 in: " + row.replace(
        "76.5%", "12.3%")[:110]]  # fmt: skip
    assert unsourced(text + "\nThe best policy wins 99.9% of the episodes.\n", path)


def test_recipes_quote_no_figures():
    for toml in sorted((ROOT / "lcmodels" / "recipes").glob("*.toml")):
        desc = load_recipe(str(toml)).description
        assert not re.search(r"\d+(\.\d+)?\s?%", desc), f"{toml.name}: figures belong in its .reached.json"


def test_reached_records_say_what_the_seed_9_figures_are():
    for rec in sorted((ROOT / "lcmodels" / "recipes").glob("*.reached.json")):
        data = json.loads(rec.read_text())
        assert "test" not in data and "heldout" in data, rec.name
