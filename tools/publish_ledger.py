#!/usr/bin/env python
"""Write the ledger's figures where the project publishes them: the tables between ``<!-- ledger:NAME -->``
and ``<!-- /ledger -->`` in README.md, docs/results/README.md and zoo/README.md (their rows:
docs/results/benchmark/published.toml), ``sealed_test`` in every zoo card (``zoo/<name>/zoo.json``), and the
suite with each road's ceiling and floor (docs/results/benchmark/suite.json).

    python tools/publish_ledger.py            # rewrite them from docs/results/benchmark/ledger.jsonl
    python tools/publish_ledger.py --check    # exit 1 naming what differs from the ledger (what the tests check)

Nothing is evaluated here: a figure the ledger lacks reads "not measured yet" (lc-bench --final measures it).
"""

from __future__ import annotations

import argparse
import sys

from lcmodels.bench.ledger import read_ledger
from lcmodels.bench.published import (
    ROOT,
    SUITE_FILE,
    stale_blocks,
    suite_record,
    update_blocks,
    zoo_card_problems,
    zoo_sealed,
)
from lcmodels.fileio import read_json, write_json
from lcmodels.zoo import ENTRY_CARD, zoo_dir, zoo_entries

DOCUMENTS = ("README.md", "docs/results/README.md", "zoo/README.md", "docs/results/benchmark/NOTE.md")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 naming what differs")
    args = ap.parse_args(argv)
    try:
        entries = read_ledger()
        if args.check:
            problems = [f"{doc}: block {name} differs from the ledger" for doc in DOCUMENTS
                        for name in stale_blocks((ROOT / doc).read_text(), ROOT / doc, entries=entries)]
            problems += zoo_card_problems(entries)
            if read_json(SUITE_FILE) != suite_record(entries):
                problems.append(f"{SUITE_FILE.relative_to(ROOT)} differs from the suite and the ledger")
            for p in problems:
                print(p)
            print(f"publish_ledger: {len(problems)} difference(s) from the ledger ({len(entries)} entries)")
            return 1 if problems else 0
        for doc in DOCUMENTS:
            path = ROOT / doc
            text = path.read_text()
            new = update_blocks(text, path, entries=entries)
            if new != text:
                path.write_text(new)
                print(f"rewrote the ledger blocks of {doc}")
        record = suite_record(entries)
        if read_json(SUITE_FILE) != record:
            write_json(SUITE_FILE, record)
            print(f"wrote {SUITE_FILE.relative_to(ROOT)}")
        for e in zoo_entries():
            card_file = zoo_dir() / e.name / ENTRY_CARD
            card = read_json(card_file)
            sealed = zoo_sealed(e.name, entries)
            if card.get("sealed_test") != sealed:
                write_json(card_file, {**card, "sealed_test": sealed})
                print(f"wrote sealed_test into {card_file.relative_to(ROOT) if card_file.is_relative_to(ROOT) else card_file}")
    except (ValueError, OSError) as exc:
        print(f"publish_ledger: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
