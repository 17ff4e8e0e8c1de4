"""The model zoo: entries published from an experiment, ``zoo:NAME`` in lc-eval / lc-record / lc-view, and the
shipped entries reproducing the episodes their cards list."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest

from lccli.evaluate import eval_main
from lccli.experiment import experiment_main
from lccli.record import record_main
from lccli.view import main as view_main
from lcmodels.experiment import PRESETS, Experiment
from lcmodels.experiment.entries import experiment_card, publish_from_experiment
from lcmodels.experiment.recipe import RECIPES_DIR
from lcmodels.policy.evaluate import check_episodes
from lcmodels.zoo import (
    follower_mismatches,
    weights_sha256,
    zoo_dir,
    zoo_entries,
    zoo_entry,
)
from tests.test_experiment import md_table


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("zoo") / "run"
    assert experiment_main(["--preset", "tiny", "--recipe", "hybrid-ppo", "--recipe", "pure-ppo", "--out", str(run),
                            "-q"]) == 0  # fmt: skip
    return run


def test_an_entry_published_from_an_experiment_works_wherever_a_policy_does(
    tiny_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "zoo"
    entry = publish_from_experiment(tiny_run, "hybrid-ppo", root=root, commit="abc1234")
    assert entry.policy == root / "hybrid-ppo" / "policy.safetensors" and entry.predictor == root / "predictor" / "predictor.pt"
    publish_from_experiment(tiny_run, "pure-ppo", root=root)
    card = json.loads((root / "hybrid-ppo" / "zoo.json").read_text())
    metrics = json.loads((tiny_run / "policies" / "hybrid-ppo" / "seed0" / "eval" / "metrics.json").read_text())
    ran = json.loads((tiny_run / "invocations.json").read_text())[-1]  # its commit, when run from a checkout
    made_at = ran["commit"] + ("+changes" if ran["dirty"] else "") if ran.get("commit") else "abc1234"
    assert card["heldout"]["success_rate"] == metrics["test"]["success_rate"] and card["commit"] == made_at
    assert card["experiment_command"] == ran["command"]
    assert card["recipe"] == "hybrid-ppo" and card["training_wall_s"] > 0 and card["safety_layer"]["heldout"]
    with pytest.raises(ValueError, match="exists"):
        publish_from_experiment(tiny_run, "hybrid-ppo", root=root)  # nothing is replaced silently
    # what a recipe reached, without a zoo entry (the paper-faithful recipes' records): the card's figures
    measured, policy, reads_predictions = experiment_card(tiny_run, "hybrid-ppo", commit="abc1234")
    assert json.loads(json.dumps(measured)) == {k: card[k] for k in measured}
    assert policy.is_file() and reads_predictions and measured["experiment_command"].startswith("lc-experiment")
    with pytest.raises(ValueError, match="holds no evaluation"):
        experiment_card(tiny_run, "paper-dqn")  # a recipe the run did not train

    # The zoo moves as a folder: the hybrid policy finds the zoo's predictor relative to itself.
    moved = tmp_path / "elsewhere"
    shutil.copytree(root, moved)
    shutil.rmtree(root)
    monkeypatch.setenv("LC_ZOO", str(moved))
    assert zoo_dir() == moved and [e.name for e in zoo_entries()] == ["hybrid-ppo", "pure-ppo"]
    assert zoo_entry("zoo:hybrid-ppo").predictor == moved / "predictor" / "predictor.pt"
    assert zoo_entry("pure-ppo").predictor is None
    assert check_episodes(moved / "hybrid-ppo" / "policy.safetensors", seed=card["check"]["eval_seed"]) == \
        card["check"]["episodes"]  # fmt: skip
    # the card names the policy its safety layer followed; the zoo ships that one, so the figure holds for the pair
    follow = card["safety_layer"]["follow"]
    trained = tiny_run / "policies" / "pure-ppo" / "seed0" / "train" / "policy.safetensors"
    assert follow == {"recipe": "pure-ppo", "training_seed": 0, "weights_sha256": weights_sha256(trained)}
    assert weights_sha256(moved / "pure-ppo" / "policy.safetensors") == follow["weights_sha256"]
    assert follower_mismatches() == []

    out = tmp_path / "eval.json"
    assert eval_main(["zoo:hybrid-ppo", "--episodes", "4", "--seed", "9", "--no-record", "--json-out", str(out)]) == 0
    assert json.loads(out.read_text())["success_rate"] == metrics["test"]["success_rate"]  # the same 4 test episodes
    assert record_main(["--driver", "zoo:pure-ppo", "--episodes", "2", "--out", str(tmp_path / "rec")]) == 0
    assert len(list((tmp_path / "rec").glob("*.mcap"))) == 2
    assert view_main(["zoo:hybrid-ppo", "--save", str(tmp_path / "one.rrd")]) == 0
    assert (tmp_path / "one.rrd").stat().st_size > 10_000
    capsys.readouterr()
    with pytest.raises(SystemExit):
        eval_main(["zoo:nope", "--episodes", "2"])
    err = capsys.readouterr().err
    assert "no zoo policy 'nope'" in err and "hybrid-ppo, pure-ppo" in err
    assert view_main(["zoo:nope", "--save", str(tmp_path / "two.rrd")]) == 2
    assert "no zoo policy 'nope'" in capsys.readouterr().err

    # make demo's shape: the zoo evaluated on the test episodes, a quick recipe trained, the best entry showcased.
    demo = dataclasses.replace(PRESETS["tiny"], name="tiny-demo", recipes=("quick-pure",), zoo=True, showcase_episodes=2)
    res = Experiment(demo, tmp_path / "demo").run()
    report = res.report.read_text()
    own = f" @ {made_at}" if ran.get("commit") else ""  # pure-ppo was published without a commit of the caller's
    for name, note in (("hybrid-ppo", f" @ {made_at}"), ("pure-ppo", own)):
        z = json.loads((tmp_path / "demo" / "zoo" / name / "metrics.json").read_text())["test"]
        assert z["episodes"] == demo.test_episodes
        ci = z["success_rate_ci95"]
        cell = f"{100 * z['success_rate']:.1f} [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}] (`zoo:{name}`{note})"
        assert cell in report, cell
    assert "shipped checkpoint (zoo): success %" in report and "quick recipe (trained now): success %" in report
    # the entry whose card has a safety layer, behind it (following the zoo's pure-ppo), on the test episodes
    safe = json.loads((tmp_path / "demo" / "zoo-safety" / "hybrid-ppo" / "metrics.json").read_text())
    assert safe["val"] == {} and safe["test"]["episodes"] == demo.test_episodes and safe["test"]["planner_choices"] > 0
    assert safe["config"]["follow"] and safe["config"]["lookahead"] == card["safety_layer"]["config"]["lookahead"]
    refs = md_table(report, "## References")
    row = next(r for r in refs if r["driver"].endswith("(`zoo:hybrid-ppo+safety`)"))
    ci = safe["test"]["success_rate_ci95"]
    assert row["success %"] == f"{100 * safe['test']['success_rate']:.1f} [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"
    assert not (tmp_path / "demo" / "zoo-safety" / "pure-ppo").exists()  # its card has no safety layer
    shown = sorted(p.suffix for p in (tmp_path / "demo" / "showcase").iterdir())
    assert shown == [".mcap", ".mcap", ".rrd"]


SHIPPED = [e.name for e in zoo_entries()] if zoo_dir().is_dir() else []


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_entry_reproduces_the_episodes_its_card_lists(name: str) -> None:
    """The committed zoo: each card's listed test episodes come out the same from the shipped weights."""
    entry = zoo_entry(name)
    check = entry.card["check"]
    assert check_episodes(entry.policy, seed=check["eval_seed"], episodes=len(check["episodes"])) == check["episodes"]
    t = entry.card["heldout"]
    assert t["episodes"] >= 200 and 0.0 <= t["success_rate"] <= 1.0


def test_the_shipped_zoo_ships_the_policy_each_safety_layer_was_measured_following() -> None:
    assert follower_mismatches() == []
    assert any((e.card.get("safety_layer") or {}).get("follow") for e in zoo_entries())


def test_publishing_a_layered_policy_without_its_follower_is_refused(
    tiny_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import runpy
    import sys

    root = tmp_path / "zoo"
    tool = str(Path(__file__).resolve().parents[1] / "tools" / "publish_zoo.py")

    def publish(*args: str) -> int:
        argv, sys.argv = sys.argv, [tool, str(tiny_run), *args, "--zoo", str(root)]
        try:
            with pytest.raises(SystemExit) as done:
                runpy.run_path(tool, run_name="__main__")
        finally:
            sys.argv = argv
        return int(done.value.code)

    assert publish("hybrid-ppo") == 2
    assert "measured following pure-ppo training seed 0" in capsys.readouterr().err
    assert not (root / "hybrid-ppo").exists()  # nothing written
    # another policy under the follower's name does not make the pair either
    publish_from_experiment(tiny_run, "hybrid-ppo", name="pure-ppo", root=root)
    assert publish("hybrid-ppo") == 2 and not (root / "hybrid-ppo").exists()
    assert "measured following pure-ppo" in capsys.readouterr().err
    # the pair is published; a zoo elsewhere leaves the package's .reached.json records as they are
    records = {p: p.read_bytes() for p in (RECIPES_DIR.glob("*.reached.json"))}
    shutil.rmtree(root)
    assert publish("hybrid-ppo", "pure-ppo") == 0
    follow = json.loads((root / "hybrid-ppo" / "zoo.json").read_text())["safety_layer"]["follow"]
    assert follow["recipe"] == "pure-ppo" and follow["weights_sha256"] == weights_sha256(root / "pure-ppo" / "policy.safetensors")
    assert {p: p.read_bytes() for p in RECIPES_DIR.glob("*.reached.json")} == records


def test_the_shipped_zoo_is_small_and_holds_no_pickle() -> None:
    if not zoo_dir().is_dir():
        pytest.skip("no zoo in this checkout")
    files = [p for p in zoo_dir().rglob("*") if p.is_file()]
    assert sum(p.stat().st_size for p in files) <= 25 * 2**20
    assert {p.suffix for p in files} <= {".safetensors", ".json", ".pt", ".md"}
    assert all(p.name == "predictor.pt" for p in files if p.suffix == ".pt")  # loaded with weights_only=True


def test_publish_zoo_refuses_zoo_options_with_reached_only(tmp_path: Path) -> None:
    import subprocess
    import sys

    tool = Path(__file__).parents[1] / "tools" / "publish_zoo.py"
    for extra in (["--zoo", str(tmp_path / "z")], ["--overwrite"]):
        out = subprocess.run([sys.executable, str(tool), str(tmp_path), "paper-a2c", "--reached-only", *extra],
                             capture_output=True, text=True)  # fmt: skip
        assert out.returncode == 2 and "Traceback" not in out.stderr
        assert out.stderr.strip().splitlines()[-1].endswith("--reached-only writes none")
    assert not (tmp_path / "z").exists()


def test_every_shipped_card_passes_the_card_checks_and_finds_its_predictor_by_digest(tmp_path: Path) -> None:
    """The shipped cards hold only what a loader accepts, and each entry's predictor is found from its card alone
    (the relative path the zoo writes, else by SHA-256 in a folder above), also in a copy of the zoo elsewhere."""
    import shutil

    from lcmodels.policy.checkpoint import card_problem, find_predictor, read_meta
    from lcmodels.zoo import CHECKOUT_ZOO

    copy = tmp_path / "zoo"
    shutil.copytree(CHECKOUT_ZOO, copy)
    for card_file in sorted(copy.glob("*/policy.safetensors")):
        meta = read_meta(card_file)
        assert card_problem(meta) == ""
        if meta.get("predictor"):
            found = find_predictor(meta, card_file)
            assert found is not None and found.resolve() == (copy / "predictor" / "predictor.pt").resolve()


def test_a_card_names_the_invocation_that_trained_its_policy(tmp_path) -> None:
    """A directory several commands filled: the card's command and commit are those of the run that computed the
    recipe's last stage, not the last run's."""
    import json

    from lcmodels.experiment.entries import _invocation_of
    from lcmodels.experiment.keys import StageKey

    key = StageKey("pure-ppo", 0, "train")
    (tmp_path / "stages").mkdir()
    (tmp_path / "stages" / f"{key.record_name}.json").write_text(json.dumps({"finished": "2026-12-07T14:37:57+0000"}))
    runs = [{"started": "2026-12-07T11:21:53+0000", "command": "first", "commit": "aaaaaaa", "dirty": False},
            {"started": "2026-12-07T14:27:40+0000", "command": "second", "commit": "bbbbbbb", "dirty": True},
            {"started": "2026-12-07T14:57:48+0000", "command": "third", "commit": "ccccccc", "dirty": False}]
    (tmp_path / "invocations.json").write_text(json.dumps(runs))
    assert _invocation_of(tmp_path, key) == runs[1]
    assert _invocation_of(tmp_path, StageKey("pure-ppo", 1, "train")) is None  # no record of that stage
    (tmp_path / "invocations.json").unlink()
    assert _invocation_of(tmp_path, key) is None
