"""lcmodels.analysis behind lc-eval: every collision sorted into exactly one kind, reproducibly; the oracle's
bound proven by replay."""

import json

import numpy as np

from lccli.evaluate import eval_main
from lcmodels.analysis import COLLISION_KINDS, CollisionBreakdown, side_gap_open
from lcmodels.policy.evaluate import evaluate
from lcsim.config import TrafficConfig
from lcsim.core import LaneChangeCore
from lcsim.registry import make_driver

from .conftest import small_config


def test_every_collision_gets_one_kind_whatever_the_batch():
    config = small_config()
    counts = []
    for batch in (3, 2):
        breakdown = CollisionBreakdown()
        summary, _ = evaluate(make_driver("keep"), config, episodes=6, batch=batch, hooks=[breakdown])
        counts.append((round(summary["collision_rate"] * 6), breakdown.counts))
    (collisions, kinds), again = counts
    assert collisions > 0  # keep-lane never avoids its leader: there is something to classify
    assert set(kinds) == set(COLLISION_KINDS) and sum(kinds.values()) == collisions
    assert kinds["late_change"] == kinds["short_gap"] == 0  # it never changes lanes
    assert again == (collisions, kinds)  # batches do not matter


def test_side_gap_is_closed_where_no_lane_change_is_allowed():
    core = LaneChangeCore(small_config(traffic=TrafficConfig(num_vehicles=0)), 2)
    core.reset([0, 1], [1, 2])
    assert side_gap_open(core, 12.0, 5.0).all()  # an empty road: every allowed change lands in a gap
    mask = core.action_mask()
    core.step(np.where(mask[:, 2], 2, 0))  # both start a change: none is allowed until it ends
    assert core.sim.ego_lc_active.all()
    assert not side_gap_open(core, 12.0, 5.0).any()


def test_lc_eval_breakdown_and_bound(tmp_path, capsys):
    out = tmp_path / "keep.json"
    assert eval_main(["keep", "--scenario", "tiny", "--episodes", "4", "--breakdown", "--no-record", "-q",
                      "--json-out", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert sum(summary["collision_kinds"].values()) == round(summary["collision_rate"] * 4)
    bound = tmp_path / "bound.json"
    assert eval_main(["oracle", "--bound", "--scenario", "tiny", "--episodes", "2", "--workers", "1", "-q",
                      "--json-out", str(bound)]) == 0
    data = json.loads(bound.read_text())
    assert data["summary"]["episodes"] == 2 and data["summary"]["replayed_success"] == data["summary"]["winnable"]
    assert [r["episode"] for r in data["episodes"]] == [0, 1] and all(r["nodes"] > 0 for r in data["episodes"])
    capsys.readouterr()
    for argv in (["rule", "--bound"], ["oracle", "--bound", "--json-out", str(bound)],
                 ["rule", "--breakdown", "--window-s", "0"], ["no/such/policy.safetensors", "--breakdown"]):
        assert eval_main([*argv, "--episodes", "1", "--no-record"]) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("lc-eval: error:") and len(err.strip().splitlines()) == 1, err


def test_the_bound_searched_in_processes_gives_the_rows_of_one_process():
    from lcmodels.analysis import oracle_bound
    from lcsim.registry import scenario

    config, seeds = scenario("tiny"), [3, 4, 5]
    shown: list[tuple[int, int]] = []
    (one, rows1), (two, rows2) = (oracle_bound(config, seeds, workers=w, progress=lambda k, n: shown.append((k, n)))
                                  for w in (1, 2))
    drop = {"cpu_s"}
    assert [{k: v for k, v in r.items() if k not in drop} for r in rows1] == \
           [{k: v for k, v in r.items() if k not in drop} for r in rows2]
    assert one["winnable"] == two["winnable"] and two["workers"] == 2
    assert shown == [(k, 3) for k in (1, 2, 3)] * 2
