"""What the documents quote of the ledger, checked against its own source: each figure against the rows of the
method its sentence names, never against any number anywhere in a table.

A *method* is a recipe (its runs alone and behind the safety layer, each training seed), a built-in driver (the
rule-based driver, the oracle), or the paper's own reported figures. :func:`method_sources` collects, per method,
the text of its own rows in the published tables (:mod:`lcmodels.bench.published`): its table rows, its column of
the suite table, its method's aggregate rows and the paired tests it takes part in. Documents name methods as
``published.toml``'s ``[names]`` lists them, by their recipe's name, or by their zoo entries' (``zoo:NAME``).

:func:`problems` reads a document in *units* (a paragraph, a list item, a table cell read with its row's first
cell and its column's header) and reports every figure a unit quotes (a rate or an interval's bound, a
p-value, a count of paired episodes or of episodes won, a normalised score) that neither the rows of a method
the unit names nor a file the unit links (a note or a report, its own ledger blocks left out) holds, and every
commit hash it quotes that is not in the checkout's history. Only units about the sealed test episodes are
read, unless the document is one the ledger's tables are published in (then every unit). A table cell that holds
one number alone (76.9, 0.726) quotes it.
"""

from __future__ import annotations

import functools
import re
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lckit.config import read_data_file
from lcmodels.bench.published import BLOCK, ROOT, SPEC, _in_root, load_spec, render_table

RATES = (
    re.compile(r"(?<![\w.])(\d{1,3}(?:\.\d{1,2})?)(?=\s?%)"),  # 77.2%, 2%
    re.compile(r"(?<![\w.])(\d{1,3}\.\d)(?= \[\d)"),  # 77.2 [74.5, 79.7]
    re.compile(r"(?<=\[)(\d{1,3}\.\d)(?=, \d)|(?<=, )(\d{1,3}\.\d)(?=\])"),  # its bounds
    re.compile(r"(?<![\w.])(\d{1,3}\.\d)(?= ?/ ?\d{1,3}\.\d)|(?<=\d / )(\d{1,3}\.\d)(?![\d.])"),  # 90.5 / 88.5
)
"""Quoted rates: percentages, a figure with its interval, and pairs of figures."""
LEVEL = re.compile(r"\s?%\s*(?:CI|interval|confidence|Wilson|bootstrap|t\b)")
"""A percentage that names an interval's level (95% interval), not a figure."""
THRESHOLD = re.compile(r"\bat (?:least|most)\s+$")
"""A percentage that is a goal or a bound set beforehand (at least 90%), not a figure anything measured."""
P_VALUE = re.compile(r"\bp\s*(?:=|<=|≤|<|is)\s*(\d(?:\.\d+)?(?:e-?\d+)?)(?![\d.])")
COUNTS = (
    re.compile(r"(?<![\w.,])(\d{1,3}(?:,\d{3})+|\d+)(?= (?:paired episodes|episode pairs|pairs|won\b|against \d))"),
    re.compile(r"(?<=\d against )(\d{1,3}(?:,\d{3})+|\d+)(?![\d.])"),
)
"""Counts of paired episodes and of episodes won alone (``908 against 771``)."""
SCORE = re.compile(r"(?<![\w.])([01]\.\d{3})(?![\d])")
"""A normalised score as the tables print it (0.726)."""
BARE = re.compile(r"^\**(\d{1,3}\.\d|[01]\.\d{3})\**$")
"""A table cell that is one figure (a rate with one decimal, a score with three)."""
COMMIT = re.compile(r"(?<![\w/.:#-])(?P<pre>(?:commits?|@)\s+)?`?(?P<hash>[0-9a-f]{7,12})`?(?![\w/.-])")
LINK = re.compile(r"\]\(([^)#\s]+)")
ABOUT_SEALED = re.compile(r"\bsealed\b|\bledger\b", re.I)


@dataclass(frozen=True)
class Unit:
    """What one figure is read in."""

    text: str
    names: str
    """Where the methods it is about are named (a cell: with its row's first cell and its column's header)."""
    links: tuple[str, ...]
    sealed: bool
    """About the sealed test episodes (it, its table's header or its section's heading says so)."""
    cell: bool = False
    """A table's cell (a number alone in it is a figure)."""


def units(text: str) -> list[Unit]:
    """The units of a Markdown ``text``, its ledger blocks left out."""
    out: list[Unit] = []
    heading = ""
    for para in re.split(r"\n\s*\n", BLOCK.sub("", text)):
        lines = para.splitlines()
        heads = [line for line in lines if line.startswith("#")]
        if heads:
            heading = heads[-1]
        rows = [line for line in lines if line.startswith("|")]
        if rows:
            header = _cells(rows[0])
            table_sealed = bool(ABOUT_SEALED.search(rows[0] + heading))
            for row in rows[2:] if len(rows) > 1 and set(rows[1]) <= set("|-: ") else rows:
                cells, links = _cells(row), tuple(LINK.findall(row))
                for i, cell in enumerate(cells):
                    names = " | ".join(dict.fromkeys((cells[0], header[i] if i < len(header) else "", cell)))
                    out.append(Unit(cell, names, links, table_sealed or bool(ABOUT_SEALED.search(row)), cell=True))
        current: list[str] = []
        for line in [x for x in lines if not x.startswith(("|", "#"))] + ["- "]:
            if re.match(r"\s*[-*] ", line):
                if current and "".join(current).strip():
                    body = "\n".join(current)
                    out.append(Unit(body, body, tuple(LINK.findall(body)),
                                    bool(ABOUT_SEALED.search(body + heading))))  # fmt: skip
                current = [line]
            else:
                current.append(line)
    return [u for u in out if u.text.strip()]


def _cells(row: str) -> list[str]:
    return [c.strip() for c in row.strip().strip("|").split("|")]


def quoted(text: str) -> list[tuple[str, str]]:
    """The figures ``text`` quotes as ``(kind, figure)``, commas of thousands dropped: ``rate`` (a rate or an
    interval's bound) and ``score`` (a normalised score), which a method's own rows hold; ``paired`` (a p-value,
    a count of paired episodes or of episodes won alone), which a paired test of two methods holds."""
    found: list[tuple[str, str]] = []
    for pattern in RATES:
        for m in pattern.finditer(text):
            if pattern is RATES[0] and (LEVEL.match(text, m.end()) or THRESHOLD.search(text, 0, m.start())):
                continue
            found += [("rate", g) for g in m.groups() if g]
    p_values = [(m.start(1), m.group(1)) for m in P_VALUE.finditer(text)]
    found += [("score", m.group(1)) for m in SCORE.finditer(text) if m.start(1) not in dict(p_values)]
    found += [("paired", f) for _, f in p_values]
    for pattern in COUNTS:
        found += [("paired", f) for f in pattern.findall(text)]
    return [(kind, f.replace(",", "")) for kind, f in found]


def holds(source: str, figure: str) -> bool:
    """Whether ``source`` states ``figure`` (as a whole number, commas of thousands dropped)."""
    return re.search(rf"(?<![\d.]){re.escape(figure)}(?![\d])", re.sub(r"(?<=\d),(?=\d{3})", "", source)) is not None


def load_names(path: Path = SPEC) -> dict[str, list[str]]:
    """How the documents name each method in prose (``[names]`` of ``published.toml``)."""
    return {k: list(v) for k, v in (read_data_file(path, "published tables").get("names") or {}).items()}


def _method(spec: str) -> str:
    """The method a driver spec is a run of: its recipe, or the built-in driver's name."""
    from lcmodels.bench.run import resolve_driver

    with _in_root():
        driver = resolve_driver(spec)
    return str(driver.about.get("recipe") or driver.identity.get("name") or spec)


def _rows(markdown: str, label: str) -> list[str]:
    return [line for line in markdown.splitlines() if line.startswith(f"| {label} |")]


@dataclass(frozen=True)
class Sources:
    """What the published tables say of each method."""

    rows: dict[str, list[str]]
    """Per method, its own rows (table rows, its suite column's cells, its aggregate rows)."""
    paired: list[tuple[str, str, str]]
    """``(method, method, sentence)`` of every paired test of two methods."""


def method_sources(entries: list[dict[str, Any]] | None = None) -> Sources:
    """Per method, the text of its own rows in every published table, and every paired test (see the module's
    docstring)."""
    sources: dict[str, list[str]] = {}
    paired: list[tuple[str, str, str]] = []

    def add(method: str, *texts: str) -> None:
        sources.setdefault(method, []).extend(texts)

    for name, table in load_spec().items():
        md = render_table(name, entries=entries)
        compares = [line for line in md.splitlines() if " against " in line and "McNemar" in line]
        if table.get("kind") == "suite":
            drivers = ["oracle", "rule", *table["drivers"]]
            methods = {d: _method(d) for d in drivers}
            header_at = next(i for i, line in enumerate(md.splitlines()) if line.startswith("| scenario"))
            lines = md.splitlines()
            for line in lines[header_at + 2:]:
                if not line.startswith("|"):
                    break
                cells = _cells(line)
                for d, cell in zip(drivers, cells[1:], strict=False):
                    add(methods[d], f"{cells[0]}: {cell}")
            groups = table.get("groups", {})
            for d in table["drivers"]:
                add(methods[d], *(x for x in lines if x.startswith(f"| {groups.get(d, d)} |")))
            for cmp in table.get("compare", []):
                said = [x for x in compares if x.startswith(f"{cmp['a_name']} against {cmp['b_name']} ")]
                paired += [(methods[a], methods[b], x) for a in cmp["a"] for b in cmp["b"] for x in said]
        elif table.get("kind") == "remeasured":
            for row in table["row"]:
                add(_method(row["run"]), *_rows(md, row["label"]))
        else:
            method_of = {}
            for row in table["row"]:
                method_of[row["label"]] = "paper" if "reported" in row else row.get("recipe") or _method(row["runs"][0])
                add(method_of[row["label"]], *_rows(md, row["label"]))
            for cmp in table.get("compare", []):
                said = [x for x in compares if x.startswith(f"{cmp['a']} against {cmp['b']}:")]
                paired += [(method_of[cmp["a"]], method_of[cmp["b"]], x) for x in said]
    return Sources(sources, sorted(set(paired)))


def aliases(sources: Sources, names: dict[str, list[str]] | None = None) -> dict[str, str]:
    """Every prose name of a method (lower case) and the method it names."""
    from lcmodels.zoo import zoo_entries

    names = load_names() if names is None else names
    out = {m.lower(): m for m in sources.rows}
    for e in zoo_entries():
        recipe = e.card.get("recipe")
        if recipe in sources.rows:
            out[f"zoo:{e.name}"] = recipe
    for method, spelt in names.items():
        for alias in spelt:
            out[alias.lower()] = method
    return out


def named(text: str, alias_of: dict[str, str]) -> set[str]:
    """The methods ``text`` names, a name inside a longer one (PPO pure in PPO pure with DAgger) not counted."""
    spans = []
    low = text.lower().replace("*", "").replace("`", "")
    for alias, method in alias_of.items():
        for m in re.finditer(rf"(?<![\w-]){re.escape(alias)}(?![\w-])", low):
            spans.append((m.start(), m.end(), method))
    return {m for s, e, m in spans if not any(s2 <= s and e <= e2 and (e2 - s2) > (e - s) for s2, e2, _ in spans)}


def _linked(document: Path, links: tuple[str, ...]) -> Iterator[str]:
    for link in links:
        target = (document.parent / link).resolve()
        if target.is_dir() and (target / "NOTE.md").is_file():
            target = target / "NOTE.md"
        if target.is_file() and target.is_relative_to(ROOT) and target.suffix not in (".json", ".jsonl"):
            yield BLOCK.sub("", target.read_text(errors="replace"))


def _git(*args: str) -> subprocess.CompletedProcess[str] | None:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.SubprocessError):
        return None


@functools.lru_cache(maxsize=1024)
def known_commit(commit: str) -> bool | None:
    """Whether ``commit`` is in the checkout's history (an ancestor of HEAD); None where git cannot say (no git, not
    a repository, or a shallow clone that lacks the commit)."""
    shallow = _git("rev-parse", "--is-shallow-repository")
    if shallow is None or shallow.returncode != 0:
        return None
    exists = _git("cat-file", "-e", f"{commit}^{{commit}}")
    if exists is None or exists.returncode != 0:
        return None if shallow.stdout.strip() == "true" else False
    ancestor = _git("merge-base", "--is-ancestor", commit, "HEAD")
    return None if ancestor is None or ancestor.returncode not in (0, 1) else ancestor.returncode == 0


def quoted_commits(text: str) -> list[str]:
    """The commit hashes ``text`` quotes outside its code blocks (where ledger keys and digests stand): 7 to 12 hex
    digits with a letter among them, or any after ``commit``/``@``."""
    prose = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return [m["hash"] for m in COMMIT.finditer(prose)
            if re.search("[a-f]", m["hash"]) or m["pre"]]  # fmt: skip


def problems(document: Path, text: str | None = None, *, every_unit: bool, sources: Sources,
             alias_of: dict[str, str]) -> list[str]:
    """What ``document`` (or ``text`` read as if it were that document) quotes that its source does not hold (see
    the module's docstring); ``every_unit``: read every unit, not only those about the sealed test episodes."""
    text = document.read_text() if text is None else text
    out = []
    for unit in units(text):
        if not (every_unit or unit.sealed):
            continue
        bare = BARE.match(unit.text) if unit.cell else None
        figures = [("score" if "." in bare[1] and len(bare[1].split(".")[1]) == 3 else "rate", bare[1])] if bare \
            else quoted(unit.text)  # fmt: skip
        if not figures:
            continue
        methods = named(unit.names, alias_of)
        own = {"rate": [s for m in methods for s in sources.rows.get(m, [])],
               "paired": [x for a, b, x in sources.paired if a in methods and b in methods]}  # fmt: skip
        own["score"] = own["rate"]
        linked = list(_linked(document, unit.links))
        for kind, fig in dict.fromkeys(figures):
            if not any(holds(s, fig) for s in own[kind]) and not any(holds(s, fig) for s in linked):
                out.append(f"{fig} in: {unit.text.strip()[:110]}")
    for commit in dict.fromkeys(quoted_commits(text)):
        if known_commit(commit) is False:
            out.append(f"commit {commit} is not in the history")
    return out


__all__ = [
    "Sources",
    "Unit",
    "aliases",
    "holds",
    "known_commit",
    "load_names",
    "method_sources",
    "named",
    "problems",
    "quoted",
    "quoted_commits",
    "units",
]
