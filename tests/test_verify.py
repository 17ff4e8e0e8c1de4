"""``lc-bench --verify``: ledger lines replayed with the weights they name, their outcome letters compared.

``test_every_line_whose_weights_are_here_replays`` runs in CI (no ``slow`` marker): one episode of each of the
committed ledger's lines (84 when it was written), all of whose weights the checkout keeps (zoo/ and docs/results/): about 40 s of one
core's time (the same run by the command: 41 s, docs/results/benchmark/verify/sample.txt; 1.5 to 2 min of wall
clock on a two-core machine shared with other work), a third of it the two lines behind the safety layer. A whole
line: docs/results/benchmark/NOTE.md, section *Verify by replay*."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lccli.bench import main as bench_main
from lcmodels.bench.ledger import CHECKOUT_LEDGER, cell_key, counts, read_ledger
from lcmodels.bench.run import Runner
from lcmodels.bench.verify import WeightsIndex, sample_episodes, select_entries, verify_entry, verify_ledger

PURE_ON_PAPER = "c1d9877d563ab0c8ee03"
"""The committed ledger's line of zoo:pure-ppo on the paper's road."""


def test_every_line_whose_weights_are_here_replays():
    entries = read_ledger(CHECKOUT_LEDGER)
    verdicts = list(verify_ledger(entries, Runner(), episodes=1, seed=0))
    assert [v.status for v in verdicts if v.status == "mismatch"] == [], [v.line() for v in verdicts]
    unchecked = [v.line() for v in verdicts if v.status != "ok"]
    assert unchecked == [], "every committed line's weights are in the checkout: " + "; ".join(unchecked)
    assert len(verdicts) == len(entries) and all(v.checked == 1 for v in verdicts)


def test_the_sample_is_the_same_everywhere_and_all_means_all():
    entry = {"key": "a" * 20, "episodes": 500}
    a = sample_episodes(entry, 5, seed=0)
    assert a == sample_episodes(entry, 5, seed=0) == sorted(set(a)) and len(a) == 5 and max(a) < 500
    assert a != sample_episodes(entry, 5, seed=1) and a != sample_episodes({**entry, "key": "b" * 20}, 5)
    assert sample_episodes(entry, None) == sample_episodes(entry, 900) == list(range(500))


def _rewrite(ledger: Path, key: str, outcomes: str) -> None:
    """Change a line's letters and every figure with them, as a forger who knows the rules would."""
    lines = [json.loads(line) for line in ledger.read_text().splitlines()]
    for e in lines:
        if e["key"] == key:
            e.update(outcomes=outcomes, **counts(outcomes))
    ledger.write_text("".join(json.dumps(e) + "\n" for e in lines))


def test_a_changed_letter_is_a_mismatch_named_in_one_line(tiny_suite: Path, tmp_path: Path, capsys):
    assert bench_main(["keep", "--suite", "tiny", "--final", "--out", str(tmp_path / "final"), "-q"]) == 0
    entries = read_ledger(tiny_suite)
    assert len(entries) == 6
    capsys.readouterr()
    assert bench_main(["--verify", "--verify-episodes", "all"]) == 0
    out = capsys.readouterr().out
    assert out.count("checked 6/6 episodes, ok") == 6 and "6 line(s) ok" in out
    forged = entries[2]
    flipped = "".join("c" if i == 4 and ch == "s" else "s" if i == 4 else ch for i, ch in enumerate(forged["outcomes"]))
    _rewrite(tiny_suite, forged["key"], flipped)
    assert bench_main(["--verify", "--verify-episodes", "all"]) == 1
    captured = capsys.readouterr()
    assert "MISMATCH: episode 4" in captured.out and "5 line(s) ok" in captured.out
    (err,) = captured.err.strip().splitlines()
    assert err.startswith(f"lc-bench: error: ledger line {forged['key']} ") and "episode 4 (user seed " in err
    # one line named by its key (or 6+ of its first characters); a sample of it
    assert bench_main(["--verify", "--verify-episodes", "2", "--verify-seed", "3", entries[0]["key"][:8]]) == 0
    assert "checked 2/6 episodes, ok" in capsys.readouterr().out


def test_what_cannot_be_checked_says_why(tmp_path: Path, capsys):
    line = next(json.loads(x) for x in CHECKOUT_LEDGER.read_text().splitlines() if PURE_ON_PAPER in x)
    missing = {**line["identity"], "weights_sha256": "0" * 64}
    first, last = line["user_seeds"]
    forged = {**line, "identity": missing,
              "key": cell_key(missing, line["scenario_sha256"], [first, *[0] * (line["episodes"] - 2), last])}
    road = {**line, "scenario_sha256": "f" * 64}
    road["key"] = cell_key(road["identity"], road["scenario_sha256"], [first, *[0] * (line["episodes"] - 2), last])
    ledger = tmp_path / "ledger.jsonl"
    ledger.write_text(json.dumps(forged) + "\n" + json.dumps(road) + "\n")
    entries = read_ledger(ledger)  # well-formed lines: their keys and figures are what they hold
    index = WeightsIndex()
    verdict = verify_entry(entries[0], Runner(), episodes=1, index=index)
    assert verdict.status == "not checkable"
    assert verdict.line().endswith("not checkable: weights not present (weights_sha256 000000000000, named "
                                   "zoo:pure-ppo; zoo:pure-ppo holds other weights (343801c0c3c5), refused)")
    assert "config has changed" in verify_entry(entries[1], Runner(), episodes=1, index=index).detail
    assert bench_main(["--verify", "--ledger", str(ledger)]) == 0  # stated, not a failure
    out = capsys.readouterr().out
    assert out.count(": not checkable: ") == 2 and "2 not checkable" in out and "not from the committed ledger" in out
    for argv, message in ((["--verify", "0123456789abcdef0123"], "names no ledger line"),
                          (["--verify", "--final"], "drop --final"),
                          (["rule", "--verify-episodes", "3"], "with --verify")):  # fmt: skip
        assert bench_main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err


def test_keys_select_lines():
    entries = [{"key": "abcdef0123"}, {"key": "abcdef9999"}, {"key": "0123456789"}]
    assert select_entries(entries, []) == entries
    assert select_entries(entries, ["0123456"]) == [entries[2]]
    with pytest.raises(ValueError, match="more than one"):
        select_entries(entries, ["abcdef"])
    with pytest.raises(ValueError, match="6 or more"):
        select_entries(entries, ["abc"])
