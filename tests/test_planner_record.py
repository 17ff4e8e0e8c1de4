"""What the safety layer thought: its report per decision, recorded (/planner/decision), read back and drawn."""

from __future__ import annotations

import pathlib

import numpy as np
import pandas as pd
import pytest

from lccli.record import record_main
from lccli.view import main as view_main
from lcdata import EpisodeWriter, read_episode, topics
from lcdata.proto import lc_pb2
from lcdata.viewer.streams import SERIES_RGB
from lcsim.core import RUNNING, LaneChangeCore
from lcsim.planning import LookaheadDriver, SafetyLayerConfig
from tests.conftest import small_config
from tests.test_view import BACKGROUNDS, blueprint_views, contrast, lab, read_rrd

LAYER = SafetyLayerConfig(horizon_decisions=4, samples=2)
RECORD = ["--scenario", "tiny", "--steps", "60", "--no-images", "--driver", "safety-layer:rule",
          "--set", "safety.horizon_decisions=4", "--set", "safety.samples=2"]  # fmt: skip


def drive(imagined_paths: int) -> tuple[list[np.ndarray], list, list[np.ndarray], LaneChangeCore]:
    """Two episodes behind the layer: the actions, the reports, the egos' (x, y) at each decision, the core."""
    core = LaneChangeCore(small_config(render_image=False, time_limit_s=5.0), 2)
    core.reset(np.arange(2), [5, 6])
    layer = LookaheadDriver(LAYER, imagined_paths=imagined_paths)
    actions, reports, egos = [], [], []
    while (core.outcome == RUNNING).any():
        egos.append(np.stack([core.sim.x[:, 0], core.sim.y[:, 0]], axis=-1))
        actions.append(layer(core.observe(), core.action_mask(), core))
        reports.append(layer.last_report)
        core.step(actions[-1])
    return actions, reports, egos, core


def test_the_report_says_what_the_layer_scored_and_keeping_paths_changes_nothing() -> None:
    plain, plain_reports, _, a = drive(0)
    kept, reports, egos, b = drive(2)
    assert all(np.array_equal(x, y) for x, y in zip(plain, kept, strict=True)) and len(plain) == len(kept)
    assert np.array_equal(a.outcome, b.outcome) and np.array_equal(a.sim.x, b.sim.x) and np.array_equal(a.sim.y, b.sim.y)
    assert sum(int(r.choice.sum()) for r in reports) > 0
    for action, report, plain_report, ego in zip(kept, reports, plain_reports, egos, strict=True):
        np.testing.assert_array_equal(report.scores, plain_report.scores)
        assert plain_report.paths is None
        scored = report.scores[np.isfinite(report.scores)]
        assert ((scored >= 0) & (scored <= 1)).all()
        np.testing.assert_array_equal(report.executed, action)
        paths = report.paths
        if not report.choice.any():
            assert paths is None
            continue
        assert paths is not None and paths.offsets[-1] == len(paths.xy)
        for e in np.flatnonzero(report.choice):
            mine = paths.of(e)
            for candidate in np.flatnonzero(np.isfinite(report.scores[e])):
                rows = mine.action == candidate
                assert sorted(mine.future[rows]) == [0, 1]  # samples = K = 2: every future kept
                assert report.scores[e, candidate] == mine.survived[rows].mean()
            counts = np.diff(mine.offsets)
            assert ((counts >= 2) & (counts <= LAYER.horizon_decisions + 2)).all()
            np.testing.assert_array_equal(mine.xy[mine.offsets[:-1]], np.repeat(ego[e][None], len(counts), axis=0))
        assert not np.isin(paths.env, np.flatnonzero(~report.choice)).any()
    # one future of the two kept: the first, once per candidate scored, and still the same decisions
    one, one_reports, _, c = drive(1)
    assert all(np.array_equal(x, y) for x, y in zip(plain, one, strict=True)) and np.array_equal(a.sim.x, c.sim.x)
    for report in one_reports:
        if report.paths is not None:
            assert (report.paths.future == 0).all() and len(report.paths.env) == np.isfinite(report.scores).sum()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[pathlib.Path, pathlib.Path]:
    """One short episode of the rule-based driver behind the layer, with 2 imagined paths per candidate and
    without."""
    out = tmp_path_factory.mktemp("thought")
    assert record_main([*RECORD, "--imagined-paths", "2", "--out", str(out / "paths")]) == 0
    assert record_main([*RECORD, "--out", str(out / "plain")]) == 0
    (with_paths,) = (out / "paths").glob("*.mcap")
    (plain,) = (out / "plain").glob("*.mcap")
    return with_paths, plain


def test_recorded_decisions_read_back(recorded: tuple[pathlib.Path, pathlib.Path]) -> None:
    ep, plain = read_episode(recorded[0]), read_episode(recorded[1])
    assert topics.PLANNER_DECISION in ep.topics and ep.metadata["driver"] == "lookahead-perceived"
    steps, decisions = ep.steps, ep.decisions
    choice = steps[["mask_right", "mask_keep", "mask_left"]].sum(axis=1).to_numpy() > 1
    assert len(decisions) > 0 and decisions["step"].tolist() == steps["step"][choice].tolist()  # one row a choice
    assert decisions["decision"].tolist() == steps["decision"][choice].tolist()
    scores = decisions[["score_right", "score_keep", "score_left"]].to_numpy()
    masks = steps[["mask_right", "mask_keep", "mask_left"]].to_numpy()[choice]
    np.testing.assert_array_equal(np.isfinite(scores), masks)  # scored where allowed, NaN elsewhere
    assert ((scores[masks] >= 0) & (scores[masks] <= 1)).all()
    assert decisions["executed"].tolist() == steps["action"][choice].tolist()
    assert (decisions["overridden"] <= (decisions["proposed"] != decisions["executed"])).all()
    assert (decisions["paths"] == 2 * masks.sum(axis=1)).all()
    # the paths start where the ego is at its decision, and stop at the horizon
    paths = ep.imagined_paths
    assert len(paths) and paths.groupby(["step", "path"]).size().max() <= 4 + 2
    ego = ep.tracks[ep.tracks["is_ego"]].set_index("step")
    starts = paths[paths["k"] == 0]
    np.testing.assert_array_equal(starts[["x", "y"]].to_numpy(), ego.loc[starts["step"], ["x", "y"]].to_numpy())
    # the same episode without the paths: the same decisions, the same traffic, no path
    assert plain.imagined_paths.empty and (plain.decisions["paths"] == 0).all()
    pd.testing.assert_frame_equal(plain.decisions.drop(columns="paths"), decisions.drop(columns="paths"))
    pd.testing.assert_frame_equal(plain.steps, steps)
    pd.testing.assert_frame_equal(plain.tracks.drop(columns="episode"), ep.tracks.drop(columns="episode"))


def test_the_viewer_draws_what_the_layer_thought(recorded: tuple[pathlib.Path, pathlib.Path],
                                                  tmp_path: pathlib.Path) -> None:  # fmt: skip
    out = tmp_path / "thought.rrd"
    assert view_main([str(recorded[0]), "--save", str(out)]) == 0
    rrd = read_rrd(out)
    assert {"plots/planner/right", "plots/planner/keep", "plots/planner/left", "plots/planner/overridden",
            "log/planner", "world/planner/imagined", "world/planner/crashes"} <= set(rrd)  # fmt: skip
    ep = read_episode(recorded[0])
    strips = {}
    for static, batch in rrd["world/planner/imagined"]:
        if not static:
            counts = np.asarray(batch.column("LineStrips2D:strips").value_lengths().fill_null(0))
            strips.update(zip(batch.column("step").to_numpy().tolist(), counts.tolist(), strict=True))
    assert set(strips) == set(ep.steps["step"])  # emptied at the decisions without a choice
    assert {s: n for s, n in strips.items() if n} == dict(zip(ep.decisions["step"], ep.decisions["paths"], strict=True))
    assert "plots/planner" in {v["origin"] for v in blueprint_views(out)}
    # the candidates' colours read on both themes and apart from each other (and from the overrides' marks)
    colours = [SERIES_RGB[k] for k in ("right", "keep", "left", "overridden")]
    for i, rgb in enumerate(colours):
        assert all(contrast(rgb, background) >= 3.0 for background in BACKGROUNDS.values())
        assert all(np.linalg.norm(lab(rgb) - lab(other)) > 25 for other in colours[i + 1 :])
    # recorded without imagined paths: the scores, no path
    assert view_main([str(recorded[1]), "--save", str(tmp_path / "plain.rrd")]) == 0
    plain = read_rrd(tmp_path / "plain.rrd")
    assert "plots/planner/keep" in plain and not [e for e in plain if e.startswith("world/planner")]


@pytest.mark.parametrize(
    ("fields", "why"),
    [
        ({"scores": [0.5, 1.0]}, "2 scores, not 3"),
        ({"executed": 7}, "are not 0, 1 or 2"),
        ({"path_action": [0], "path_future": [0], "path_survived": [True], "path_offsets": [0, 10**12],
          "path_xy": [0.0, 0.0]}, "path offsets that do not run from 0"),
        ({"path_action": [0, 1], "path_future": [0], "path_survived": [True], "path_offsets": [0, 1],
          "path_xy": [0.0, 0.0]}, "2 paths with 1 futures"),
        ({"path_xy": [1.0, 2.0]}, "path fields without paths"),
    ],
)  # fmt: skip
def test_a_decision_whose_counts_do_not_add_up_is_refused(tmp_path: pathlib.Path, fields: dict, why: str) -> None:
    path = tmp_path / "bad.mcap"
    message = {"step": 10, "t": 0.5, "scores": [np.nan, 1.0, 0.0], **fields}
    with EpisodeWriter(path, metadata={"driver": "crafted"}, start_time_ns=0) as w:
        w._write(topics.PLANNER_DECISION, 0.5, lc_pb2.PlannerDecision(**message).SerializeToString())
    ep = read_episode(path)
    for table in ("decisions", "imagined_paths"):
        with pytest.raises(ValueError, match=why) as caught:
            getattr(ep, table)
        assert str(path) in str(caught.value) and "corrupt data" in str(caught.value)


def test_lc_record_refuses_paths_of_a_driver_that_imagines_none(tmp_path: pathlib.Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    for argv, why in ((["--driver", "rule", "--imagined-paths", "1"], "rule imagines no futures"),
                      (["--driver", "lookahead-blind", "--imagined-paths", "17"], "must be at most 16"),
                      (["--driver", "safety-layer:keep"], "guards a policy or the rule-based driver")):  # fmt: skip
        assert record_main(["--scenario", "tiny", "--out", str(tmp_path), *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("lc-record: error: ") and err.count("\n") == 1 and why in err, err
    assert not list(tmp_path.iterdir())
