"""The ledger trusts nothing stored: keys and figures are derived again (a forged line is refused in one line, a
corrupt cached cell is run again), the committed file only grows, appends hold a lock, and the sealed test
episodes run only through the benchmark's final path, in the library as in the commands."""

from __future__ import annotations

import itertools
import json
import shutil
import subprocess
from pathlib import Path

import pytest

from lccli.bench import main as bench_main
from lcmodels.bench.ledger import (
    CHECKOUT_LEDGER,
    NOT_COMMITTED,
    append_entry,
    cell_key,
    counts,
    lock_name,
    read_ledger,
)
from lcsim.suite import SEALED_SEED_BASE, SUITE_SCENARIOS

RULE_ON_PAPER = "bba65e26c02ddfe975f2"
"""The committed ledger's line of the rule-based driver on the paper's road (its letters: 54.85% success)."""


def _lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _write(path: Path, lines: list[dict]) -> None:
    path.write_text("".join(json.dumps(e, sort_keys=True) + "\n" for e in lines))


def _forged(tmp_path: Path, key: str, **changes) -> Path:
    lines = _lines(CHECKOUT_LEDGER)
    for e in lines:
        if e["key"] == key:
            e.update(changes)
    path = tmp_path / "forged.jsonl"
    _write(path, lines)
    return path


def test_a_forged_figure_is_refused_in_one_line(tmp_path: Path, capsys):
    """The case of the report: a success_rate of 0.99 where the letters say 54.85%."""
    forged = _forged(tmp_path, RULE_ON_PAPER, success_rate=0.99)
    assert bench_main(["rule", "--final", "--suite", "paper", "--ledger", str(forged), "--out",
                       str(tmp_path / "out"), "-q"]) == 2  # fmt: skip
    captured = capsys.readouterr()
    assert captured.err.strip() == (f"lc-bench: error: ledger line {RULE_ON_PAPER}: stored success_rate 0.99 "
                                    "disagrees with its outcome letters (0.5485)")  # fmt: skip
    assert "99" not in captured.out and not (tmp_path / "out").exists()  # nothing printed as a result
    for changes, message in (({"success": 1999}, "stored success 1999 disagrees"),
                             ({"collision_wilson95": [0.0, 0.1]}, "stored collision_wilson95"),
                             ({"identity": {"kind": "driver", "name": "oracle"}}, "its key disagrees"),
                             ({"user_seeds": [3000000000, 3000000009]}, "are not the first and last")):
        with pytest.raises(ValueError, match=message):
            read_ledger(_forged(tmp_path, RULE_ON_PAPER, **changes))


def test_figures_are_derived_from_the_letters_never_read(tmp_path: Path):
    line = next(e for e in _lines(CHECKOUT_LEDGER) if e["key"] == RULE_ON_PAPER)
    bare = {k: v for k, v in line.items() if k not in counts("s") or k == "episodes"}  # the letters, no figures
    path = tmp_path / "bare.jsonl"
    _write(path, [bare])
    (entry,) = read_ledger(path)
    assert entry["success_rate"] == bare["outcomes"].count("s") / 2000 == 0.5485
    assert entry["success_wilson95"] == counts(bare["outcomes"])["success_wilson95"]


def test_a_corrupt_cached_cell_is_run_again_never_served(tiny_suite: Path, tmp_path: Path, capsys, caplog):
    out = tmp_path / "bench"
    argv = ["keep", "--suite", "tiny", "--episodes", "4", "--out", str(out), "-q"]
    assert bench_main(argv) == 0
    table = json.loads((out / "bench.json").read_text())
    cells = sorted((out / "cells").glob("*.json"))
    assert len(cells) == 6
    cells[0].write_text("{not json")
    forged = json.loads(cells[1].read_text())
    cells[1].write_text(json.dumps({**forged, "success_rate": 0.99, "success": 4}))
    other = json.loads(cells[2].read_text())
    cells[2].write_text(json.dumps({**other, "key": "0" * 20}))
    capsys.readouterr()
    assert bench_main(argv) == 0
    err = capsys.readouterr().err + caplog.text
    assert "Traceback" not in err
    for cell, why in ((cells[0], "not a readable JSON object"), (cells[1], "disagrees with its outcome letters"),
                      (cells[2], "not " + cells[2].stem)):  # fmt: skip
        assert f"cached cell {cell}: " in err and why in err, (cell, err)
    assert json.loads((out / "bench.json").read_text()) == table  # the cells run again give the same table
    assert json.loads(cells[1].read_text())["success_rate"] == forged["success_rate"]  # written anew


def history_problems(versions: list[tuple[str, str]]) -> list[str]:
    """Where a version of the ledger (``(name, text)``, oldest first) does not begin with the one before it."""
    return [f"the ledger at {newer} does not begin with the ledger at {older}: a line was edited or deleted "
            "(append a new line instead)"
            for (older, before), (newer, after) in itertools.pairwise(versions)
            if not after.startswith(before)]  # fmt: skip


def test_the_committed_ledger_only_grows():
    """Each version of the ledger git shows cheaply (the parent commit's, HEAD's, every commit that touched it
    along the history) is a prefix of the next, the working tree's last. Skipped without git or history (a
    shallow clone). About a second."""
    root = CHECKOUT_LEDGER.parents[3]
    rel = CHECKOUT_LEDGER.relative_to(root).as_posix()

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=60, check=False)

    try:
        parent = git("show", f"HEAD~1:{rel}")
        shallow = git("rev-parse", "--is-shallow-repository").stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pytest.skip("git is not available")
    if parent.returncode != 0 or shallow != "false":
        pytest.skip("no history to compare with (not a git checkout, a shallow clone, or no parent commit)")
    now = ("the working tree", CHECKOUT_LEDGER.read_text())
    # the parent commit's version, HEAD's and the working tree's; then every version along the first-parent history
    # (a branch merged in brings its lines after the mainline's: its own commits are not in this line of versions)
    assert history_problems([("HEAD~1", parent.stdout), ("HEAD", git("show", f"HEAD:{rel}").stdout), now]) == []
    chain = git("log", "--first-parent", "--reverse", "--format=%H", "HEAD", "--", rel).stdout.split()
    assert chain, "the ledger has no commit"
    assert history_problems([*((c[:10], git("show", f"{c}:{rel}").stdout) for c in chain), now]) == []


def test_an_edited_or_deleted_line_fails_the_history_check():
    text = CHECKOUT_LEDGER.read_text()
    lines = text.splitlines(keepends=True)
    edited = text.replace('"success_rate":0.5485', '"success_rate":0.99', 1)
    assert edited != text
    assert history_problems([("a", text), ("b", edited)]) != []
    assert history_problems([("a", text), ("b", "".join(lines[:3] + lines[4:]))]) != []
    assert history_problems([("a", "".join(lines[:-1])), ("b", text), ("c", text + lines[0])]) == []


def _entry(n: int = 3) -> dict:
    identity, digest = {"kind": "driver", "name": "keep"}, "d" * 64
    seeds = list(range(SEALED_SEED_BASE, SEALED_SEED_BASE + n))
    return {"key": cell_key(identity, digest, seeds), "identity": identity, "scenario": "tiny-a",
            "scenario_sha256": digest, "user_seeds": [seeds[0], seeds[-1]], "outcomes": "s" * n, "episodes": n,
            "split": "test"}  # fmt: skip


def test_two_appends_of_one_key_leave_one_line(tmp_path: Path):
    ledger = tmp_path / "ledger.jsonl"
    first, appended = append_entry(_entry(), ledger)
    again, appended_again = append_entry({**_entry(), "outcomes": "ccc"}, ledger)
    assert appended and not appended_again and again["outcomes"] == first["outcomes"] == "sss"
    assert len(read_ledger(ledger)) == 1
    assert (tmp_path / lock_name(ledger)).is_file()  # the lock lives beside the ledger, never in it


def test_an_append_waits_for_the_lock_and_says_who_holds_it(tmp_path: Path, monkeypatch):
    from lckit.fileio import folder_lock
    from lcmodels.bench import ledger as ledger_mod

    ledger = tmp_path / "ledger.jsonl"
    monkeypatch.setattr(ledger_mod, "LOCK_WAIT_S", 0.2)
    with folder_lock(tmp_path, "lc-bench --final", lock_name(ledger)):  # another run, checking and appending
        with pytest.raises(ValueError, match=r"another lc-bench --final \(pid \d+\) is appending to the ledger"):
            append_entry(_entry(), ledger)
    assert not ledger.exists()
    assert append_entry(_entry(), ledger)[1]  # once it let go


def test_the_library_refuses_the_sealed_episodes_outside_the_final_path():
    from lcmodels.policy.evaluate import evaluate, evaluate_sharded
    from lcsim.config import tiny_scenario
    from lcsim.drivers import RuleBasedDriver
    from lcsim.envs import LaneChangeEnv
    from lcsim.episodes import run_episodes

    sealed = SEALED_SEED_BASE + 7
    with pytest.raises(ValueError, match="sealed test episodes"):
        evaluate(RuleBasedDriver(), tiny_scenario(), user_seeds=[sealed])
    with pytest.raises(ValueError, match="sealed test episodes"):
        evaluate_sharded("rule", tiny_scenario(), user_seeds=[1, sealed], shards=1)
    with pytest.raises(ValueError, match="sealed test episodes"):
        run_episodes(RuleBasedDriver(), tiny_scenario(), [sealed])
    with pytest.raises(ValueError, match="sealed test episodes"):
        LaneChangeEnv(tiny_scenario()).reset(seed=sealed)
    # the final path's explicit leave, and nothing else, runs them
    summary, results = evaluate(RuleBasedDriver(), tiny_scenario(), user_seeds=[sealed], sealed=True)
    assert len(results) == 1 and summary["user_seeds"] == [sealed, sealed]


def test_another_ledger_runs_but_every_figure_says_so(tiny_suite: Path, tmp_path: Path, capsys):
    out = tmp_path / "final"
    assert bench_main(["keep", "--suite", "tiny", "--final", "--out", str(out), "-q"]) == 0
    printed = capsys.readouterr().out
    cell_lines = [line for line in printed.splitlines() if line.startswith("[")]
    assert len(cell_lines) == 6 and all(line.endswith(f"[{NOT_COMMITTED}]") for line in cell_lines)
    assert NOT_COMMITTED in (out / "BENCH.md").read_text()
    assert json.loads((out / "bench.json").read_text())["ledger"] == {"path": str(tiny_suite), "committed": False}


def test_the_committed_ledger_is_marked_as_such(tmp_path: Path):
    from lcmodels.bench.ledger import is_committed

    assert is_committed(CHECKOUT_LEDGER) and not is_committed(tmp_path / "ledger.jsonl")
    copy = tmp_path / "ledger.jsonl"
    shutil.copyfile(CHECKOUT_LEDGER, copy)
    assert not is_committed(copy)  # the same lines elsewhere are not the committed ledger
    assert SUITE_SCENARIOS["paper"].sealed_seeds()[0] == SEALED_SEED_BASE
