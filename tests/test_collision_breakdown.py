"""tools/collision_breakdown.py: every collision is sorted into exactly one kind, reproducibly."""

import json

import numpy as np

from lcsim.config import TrafficConfig
from lcsim.core import LaneChangeCore

from .conftest import small_config


def test_every_collision_gets_one_kind(capsys):
    from tools.collision_breakdown import KINDS, main

    assert main(["keep", "--episodes", "6", "--batch", "3", "--json"]) == 0
    counts = json.loads(capsys.readouterr().out)
    assert sum(counts[k] for k in ("success", "collision", "off_road", "timeout")) == 6
    assert counts["collision"] > 0  # keep-lane never avoids its leader: there is something to classify
    assert sum(counts[k] for k in KINDS) == counts["collision"]
    assert counts["late_change"] == counts["short_gap"] == 0  # it never changes lanes
    assert main(["keep", "--episodes", "6", "--batch", "2", "--json"]) == 0  # batches do not matter
    assert json.loads(capsys.readouterr().out) == counts


def test_side_gap_is_closed_where_no_lane_change_is_allowed():
    from tools.collision_breakdown import side_gap_open

    core = LaneChangeCore(small_config(traffic=TrafficConfig(num_vehicles=0)), 2)
    core.reset([0, 1], [1, 2])
    assert side_gap_open(core, 12.0, 5.0).all()  # an empty road: every allowed change lands in a gap
    mask = core.action_mask()
    core.step(np.where(mask[:, 2], 2, 0))  # both start a change: none is allowed until it ends
    assert core.sim.ego_lc_active.all()
    assert not side_gap_open(core, 12.0, 5.0).any()


def test_bad_input_is_one_line(capsys):
    from tools.collision_breakdown import main

    assert main(["no/such/policy.safetensors", "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("collision_breakdown: error:") and len(err.strip().splitlines()) == 1
