"""The experiment's stage graph without running it: stage keys and the directory layout, what each stage needs, the
order stages run in, cycles, and the plan as a query of the graph."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import pytest

from lccli.experiment import experiment_main
from lcmodels.experiment import PRESETS, Experiment, GraphCycle, Stage, StageGraph, StageKey, build_graph
from lcmodels.experiment.graph import recipe_seeds
from lcmodels.experiment.recipe import load_recipe
from lcmodels.experiment.stages import StageContext
from lcmodels.experiment.store import record_paths

TINY = PRESETS["tiny"]
IDENTITIES = Path(__file__).parent / "tiny_stage_identities.json"


def test_stage_keys_name_the_directories_and_records_of_every_experiment_directory(tmp_path: Path) -> None:
    for key, name, path in (
        (StageKey("hybrid-ppo", 1, "shielded"), "hybrid-ppo/seed1/shielded", "policies/hybrid-ppo/seed1/shielded"),
        (StageKey("pure-ppo", 0, "eval"), "pure-ppo/seed0/eval", "policies/pure-ppo/seed0/eval"),
        (StageKey.of("corpus"), "corpus", "corpus"),
        (StageKey.of("demos", "oracle-s5000-n400"), "demos/oracle-s5000-n400", "demos/oracle-s5000-n400"),
        (StageKey.of("rule"), "rule", "rule"),
        (StageKey.of("zoo-safety", "hybrid-ppo"), "zoo-safety/hybrid-ppo", "zoo-safety/hybrid-ppo"),
        (StageKey.of("showcase"), "showcase", "showcase"),
    ):
        assert key.name == str(key) == name and key.path(tmp_path) == tmp_path / path
        assert StageKey.parse(name) == key
        complete, pending = record_paths(tmp_path, key)
        assert complete == tmp_path / "stages" / (name.replace("/", "__") + ".json")
        assert pending == tmp_path / "stages" / (name.replace("/", "__") + ".pending.json")
    assert StageKey("hybrid-ppo", 0, "train") == StageKey.parse("hybrid-ppo/seed0/train")  # a value, hashable
    assert len({StageKey("a", 0, "train"), StageKey("a", 0, "train"), StageKey("a", 1, "train")}) == 2
    for bad in (lambda: StageKey("a", None, "train"), lambda: StageKey(None, 0, "train"),
                lambda: StageKey("a", -1, "train"), lambda: StageKey("a/b", 0, "train"),
                lambda: StageKey.of("x/y"), lambda: StageKey("a", 0, "train", "part")):  # fmt: skip
        with pytest.raises(ValueError):
            bad()
    with pytest.raises(ValueError, match="not a stage name"):
        StageKey.parse("a/b/c/d")


def test_the_tiny_graph_has_every_stage_of_every_recipe_each_after_what_it_reads(tmp_path: Path) -> None:
    exp = Experiment(TINY, tmp_path / "run", seeds=2)
    graph = exp.graph()
    keys = graph.keys()
    position = {k: i for i, k in enumerate(keys)}
    for k in keys:
        assert all(position[n] < position[k] for n in graph.needed(k)), k
        assert all(k in graph.dependents(n) for n in graph.needed(k))
    recipes = {r.name: r for r in exp.recipes()}
    want = {StageKey.of("corpus"), StageKey.of("predictor"), StageKey.of("rule"), StageKey.of("oracle")}
    want |= {StageKey.of("analytic-predictor", r.predictor) for r in recipes.values() if r.predictor != "learned"}
    want |= {StageKey.of("demos", "{0.driver}-s{0.seed}-n{0.episodes}".format(r.table("demos"))) for r in recipes.values()
             if "clone" in r.stages}  # fmt: skip
    for r in recipes.values():
        for s in range(2):
            want |= {StageKey(r.name, s, st) for st in (*r.stages, "eval")}
            if r.safety is not None:
                want.add(StageKey(r.name, s, "safety"))
    assert set(keys) == want and len(keys) == len(want)
    assert graph.finals() == [StageKey(r.name, s, r.final_stage) for r in exp.recipes() for s in range(2)]
    # a recipe's stages read its previous stage; cloning reads the demonstrations; the predictor only where read
    assert graph.needed(StageKey("pure-ppo", 0, "train")) == [StageKey("pure-ppo", 0, "clone")]
    assert StageKey.of("predictor") in graph.needed(StageKey("hybrid-ppo", 0, "eval"))
    assert [k.stage for k in graph.needed(StageKey("pure-ppo-dagger", 1, "dagger"))] == ["demos", "clone"]
    # DAgger with the safety layer as the expert, first: it starts from the followed policy, no demonstrations
    for s in range(2):
        assert graph.needed(StageKey("distil-safety-ppo", s, "dagger")) == [StageKey("pure-ppo", s, "train")]
    # the safety layer's follower: the shielded and safety stages read pure-ppo's final policy of the same seed
    for s in range(2):
        follower = StageKey("pure-ppo", s, "train")
        assert follower in graph.needed(StageKey("hybrid-ppo", s, "shielded"))
        assert follower in graph.needed(StageKey("hybrid-ppo", s, "safety"))
        assert StageKey("hybrid-ppo", s, "shielded") in graph.needed(StageKey("hybrid-ppo", s, "safety"))
        assert StageKey("pure-ppo", 1 - s, "train") not in graph.upstream(StageKey("hybrid-ppo", s, "safety"))


def test_the_plan_of_a_new_directory_is_the_graph_in_the_order_one_process_runs_it(tmp_path: Path) -> None:
    exp = Experiment(dataclasses.replace(TINY, recipes=("hybrid-ppo", "paper-a2c")), tmp_path / "run")
    plan = exp.plan()
    graph = exp.graph()
    assert [s.name for s in plan] == [k.name for k in graph.keys()]
    for s in plan:
        key = StageKey.parse(s.name)
        needs = graph.needed(key)
        if not needs:
            assert s.status == "would run (new)", s
        else:  # waits for the last of the stages it reads to come
            assert s.status == f"would run (after {max(needs, key=graph.keys().index)})", s
    assert not (tmp_path / "run").exists()  # a plan writes nothing
    # what one process does first: the data, pure-ppo (the policy hybrid-ppo's layer follows), hybrid-ppo, then
    # the paper's A2C, then the references
    order = [k.recipe or k.stage for k in graph.keys()]
    assert order[:3] == ["corpus", "predictor", "demos"] and order[-1] == "oracle"
    assert order.index("pure-ppo") < order.index("hybrid-ppo") < order.index("paper-a2c") < order.index("rule")


def _pair(follow_a: str, follow_b: str, *, shielded: bool) -> list:
    """Two copies of hybrid-ppo, ``a`` and ``b``, whose safety layers follow ``follow_a`` and ``follow_b``."""
    hybrid = load_recipe("hybrid-ppo")
    stages = hybrid.stages if shielded else tuple(s for s in hybrid.stages if s != "shielded")
    return [dataclasses.replace(hybrid, name=n, stages=stages, safety=dataclasses.replace(hybrid.safety, follow=f))
            for n, f in (("a", follow_a), ("b", follow_b))]  # fmt: skip


@pytest.mark.parametrize("shielded", [True, False])
def test_safety_layers_that_follow_each_other_are_a_cycle_in_one_line(tmp_path: Path, shielded: bool,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    a, b = _pair("b", "a", shielded=shielded)
    with pytest.raises(GraphCycle) as exc:
        build_graph(TINY, [a, b], {"a": 1, "b": 1})
    msg = str(exc.value)
    assert "\n" not in msg and "a -> b -> a (safety.follow)" in msg
    assert recipe_seeds([a, b], 1, {"a": 3}) == {"a": 3, "b": 3}  # (the seeds of a loop settle all the same)
    # from the command line: one line, exit 2, nothing written
    files = []
    for r in (a, b):
        files.append(tmp_path / f"{r.name}.toml")
        files[-1].write_text(r.to_toml())
    capsys.readouterr()
    out = tmp_path / "run"
    assert experiment_main(["--preset", "tiny", "--recipe", str(files[0]), "--recipe", str(files[1]), "--out", str(out),
                            "--dry-run"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a -> b -> a" in err and "Traceback" not in err and not out.exists()


def test_stages_that_wait_on_each_other_are_named_in_one_line() -> None:
    x, y, z = StageKey.of("x"), StageKey.of("y"), StageKey.of("z")
    stages = {x: Stage(x), y: Stage(y, (("a", x), ("b", z))), z: Stage(z, (("c", y),))}
    with pytest.raises(GraphCycle, match="in a cycle, y -> z -> y "):
        StageGraph(stages)
    stages[z] = Stage(z, (("c", x),))
    assert StageGraph(stages).keys() == [x, z, y]


def test_a_layer_following_a_recipe_the_experiment_does_not_run_is_refused() -> None:
    a, _ = _pair("nowhere", "a", shielded=False)
    with pytest.raises(ValueError, match="follows 'nowhere', which the experiment does not run"):
        build_graph(TINY, [a], {"a": 1})


def test_a_stage_runs_alone_only_when_what_it_reads_is_complete(tmp_path: Path) -> None:
    exp = Experiment(TINY, tmp_path / "run")
    with pytest.raises(ValueError, match="stage predictor needs corpus, which is not complete"):
        exp.run_stage(StageKey.of("predictor"))
    with pytest.raises(ValueError, match="has no stage nowhere/seed0/train"):
        exp.run_stage(StageKey("nowhere", 0, "train"))
    assert not (tmp_path / "run" / "predictor").exists()


def test_a_predictor_stage_recorded_before_a_model_field_existed_stays_complete() -> None:
    import dataclasses as dc

    from lcmodels.experiment.kinds.predictor import predictor_config, stored_predictor_config
    from lcmodels.predictor import PredictorConfig
    from lcmodels.presets import PRESETS

    tc = predictor_config(PRESETS["quick"], 1)
    now = {k: v for k, v in dc.asdict(tc).items() if k not in ("progress", "num_threads")}
    added = [f.name for f in dc.fields(PredictorConfig) if f.name == "base" or f.name.startswith("lane_")]
    assert added, "the fields this test drops"
    old = now | {"model": {k: v for k, v in now["model"].items() if k not in added}}
    assert stored_predictor_config(old) == now
    assert stored_predictor_config({"model": "not a table"}) == {"model": "not a table"}


def test_the_ablation_recipes_differ_only_in_their_input_and_an_analytic_base_is_a_stage_of_its_own(
        tmp_path: Path) -> None:
    from lcmodels.presets import ABLATION_INPUTS, ABLATION_RECIPES, ABLATION_SEEDS

    recipes = [load_recipe(name) for name in ABLATION_RECIPES]
    assert len(recipes) == 2 * len(ABLATION_INPUTS)
    for r in recipes:  # the same stages, budgets and trunk; only what the policy reads (and the road block) differs
        base = recipes[0] if r.table("train").get("train_roads") is None else recipes[len(ABLATION_INPUTS)]
        for stage in r.stages:
            mine, theirs = r.stage_settings(stage), base.stage_settings(stage)
            differ = {k for k in mine.keys() | theirs.keys() if mine.get(k) != theirs.get(k)}
            assert differ <= {"obs", "image_net", "freeze_image"}, (r.name, differ)
        assert (r.stages, r.table("demos")) == (base.stages, base.table("demos"))
    graph = build_graph(PRESETS["ablation"], recipes, {r.name: ABLATION_SEEDS for r in recipes})
    lane = dict(graph[StageKey("ablation-lane-aware", 2, "clone")].needs)
    assert lane["predictor"] == StageKey.of("analytic-predictor", "lane-aware")
    assert dict(graph[StageKey("ablation-hybrid", 0, "train")].needs)["predictor"] == StageKey.of("predictor")
    assert "predictor" not in dict(graph[StageKey("ablation-pure", 0, "train")].needs)
    assert not graph.needed(StageKey.of("analytic-predictor", "lane-aware"))  # nothing to train: no corpus
    pure = dataclasses.replace(load_recipe("ablation-pure"), name="x")
    with pytest.raises(ValueError, match="needs an observation mode with predictions"):
        dataclasses.replace(pure, predictor="lane-aware")
    with pytest.raises(ValueError, match="predictor must be one of"):
        dataclasses.replace(recipes[2], predictor="oracle")
    assert "predictor" not in load_recipe("ablation-prediction").to_dict()  # older records keep their identity
    assert load_recipe("ablation-lane-aware").to_dict()["predictor"] == "lane-aware"


def test_every_stage_of_the_tiny_preset_keeps_the_identity_its_record_holds(tmp_path: Path) -> None:
    """A directory made before resumes as complete when each stage's identity is what its record holds: its config,
    the roles and hashes of what it reads, whether an older record is upgraded and a run resumed. Each stage of the
    tiny preset with two training seeds, its job built on stand-in results of the stages it reads, keeps the identity
    tests/tiny_stage_identities.json holds (written before the stage kinds became a table; a change there reruns
    those stages in every experiment directory)."""
    from lcmodels.presets import StageResult

    exp = Experiment(TINY, tmp_path / "run", seeds=2)
    graph = exp.graph()
    ctx = StageContext(TINY, exp.out)
    results: dict[StageKey, StageResult] = {}
    found = {}
    for key in graph.keys():
        stage = graph[key]
        job = stage.job(ctx, {role: results[k] for role, k in stage.needs})
        results[key] = StageResult(key.name, "skipped", key.path(exp.out), 0.0, 0.0, {"f": key.name})
        identity = {"needs": [[role, k.name] for role, k in stage.needs], "config": job.config, "inputs": job.inputs,
                    "upgrade": job.upgrade is not None, "resumable": job.resumable is not None}  # fmt: skip
        found[key.name] = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:16]
        assert stage.kind is not None and stage.kind.name == key.stage  # every stage is of a kind of the table
    assert found == json.loads(IDENTITIES.read_text())
    assert not (tmp_path / "run").exists()
