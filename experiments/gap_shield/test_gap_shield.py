"""experiments/gap_shield/gap_shield.py: the gap shield vetoes exactly the lane changes into gaps shorter than asked."""

import json

import numpy as np

from lcsim.config import paper_scenario
from lcsim.core import KEEP, RUNNING, LaneChangeCore
from lcsim.drivers import RuleBasedDriver


def _drive(shield, episodes=3, decisions=60):
    core = LaneChangeCore(paper_scenario(render_image=False), episodes)
    core.reset(np.arange(episodes), [31 + k for k in range(episodes)])
    kept_changes = 0
    for _ in range(decisions):
        if not (core.outcome == RUNNING).any():
            break
        obs, mask = core.observe(), core.action_mask()
        wanted = shield.driver(obs, mask, core)
        actions = shield(obs, mask, core)
        kept_changes += int(((wanted != KEEP) & (actions != KEEP)).sum())
        assert ((actions == wanted) | (actions == KEEP)).all()  # a veto only ever turns a change into keep
        core.step(actions)
    return kept_changes


def test_shield_vetoes_every_change_into_a_short_gap_and_none_into_any_gap():
    from .gap_shield import GapShield

    strict = GapShield(RuleBasedDriver(), front_gap_m=1e9, rear_gap_m=1e9, headway_s=0.0)
    assert _drive(strict) == 0
    assert strict.changes > 0 and strict.vetoed == strict.changes  # the rule driver asked; all were vetoed
    lax = GapShield(RuleBasedDriver(), front_gap_m=-1e9, rear_gap_m=-1e9, headway_s=0.0)
    assert _drive(lax) == lax.changes > 0 and lax.vetoed == 0


def test_cli_reference_and_bad_input(capsys):
    from .gap_shield import main

    assert main(["keep", "--episodes", "2", "--batch", "2", "--front-gap-m", "-1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["shield"] is False and out["changes_asked"] is None
    assert abs(sum(out[k] for k in ("success_rate", "collision_rate", "off_road_rate", "timeout_rate")) - 1) < 1e-9
    assert main(["missing.zip"]) == 2
    assert capsys.readouterr().err.strip().count("\n") == 0
