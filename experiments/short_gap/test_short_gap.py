"""experiments/short_gap/short_gap.py on small real episodes of the random driver (most of its crashes are short gaps)."""

import pytest

from lcmodels.analysis import CollisionBreakdown
from lcmodels.policy.evaluate import eval_user_seeds
from lcsim.config import paper_scenario
from lcsim.episodes import run_episodes
from lcsim.registry import make_driver

from .short_gap import ShortGapProbe, main


def test_the_probe_describes_every_short_gap_collision_the_breakdown_counts():
    driver = make_driver("random")
    probe, breakdown = ShortGapProbe(driver), CollisionBreakdown()
    results = run_episodes(driver, paper_scenario(render_image=False), eval_user_seeds(60, 0),
                           hooks=[breakdown, probe])
    assert breakdown.counts["short_gap"] > 0
    assert len(probe.cases) == breakdown.counts["short_gap"]
    assert probe.changes >= len(probe.cases)
    seeds = {r.user_seed for r in results if r.outcome == "collision"}
    for case in probe.cases:
        assert case["user_seed"] in seeds and case["partner"] > 0
        assert case["action"] in ("right", "left") and case["seconds_since_start"] >= 0.0
        assert case["alive_at_start"] is None  # the random driver imagines nothing


def test_a_driver_without_a_lookahead_or_an_unknown_zoo_entry_is_a_one_line_error(capsys):
    assert main(["rule", "--episodes", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("short_gap: error:") and err.count("\n") == 1, err
    with pytest.raises(SystemExit) as exc:  # argparse's own error: usage, then one error line
        main(["lookahead-blind:zoo:no-such-entry", "--episodes", "2"])
    assert exc.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1].startswith("short_gap: error: argument policy:")
