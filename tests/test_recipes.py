"""Recipes as data: every packaged recipe reads, round-trips and builds valid stage configs; bad files and
settings are one-line errors naming the problem."""

from __future__ import annotations

from pathlib import Path

import pytest

from lcmodels.experiment.recipe import RECIPE_KINDS, Recipe, load_recipe, recipe_names
from lcmodels.presets import (
    ABLATION_RECIPES,
    BEST_RECIPES,
    OPTIONAL_RECIPES,
    PAPER_RECIPES,
    PRESETS,
    ROWS,
    listed_recipes,
)


def test_every_packaged_recipe_round_trips_file_config_file(tmp_path: Path) -> None:
    names = recipe_names()
    assert {"hybrid-ppo", "pure-ppo", "paper-hybrid-ppo", "quick-pure"} <= set(names)
    for name in names:
        r = load_recipe(name)
        text = r.to_toml()
        path = tmp_path / f"{name}.toml"
        path.write_text(text)
        again = load_recipe(path)
        assert again == r and again.to_toml() == text
    # every row of the paper's tables has a paper-faithful and a best recipe, and the paper preset runs them all
    recipes = [load_recipe(n) for n in names]
    for row in ROWS:
        assert any(r.row == row and r.kind == "paper" for r in recipes), row
    for row in ("ppo-hybrid", "a2c-hybrid", "dqn-hybrid", "ppo-pure", "ppo-image", "ppo-prediction"):
        assert any(r.row == row and r.kind == "best" for r in recipes), row
    assert set(PRESETS["paper"].recipes) == {r.name for r in recipes if r.kind in ("paper", "best")} - set(OPTIONAL_RECIPES)
    assert set(PRESETS["ablation"].recipes) == {r.name for r in recipes if r.kind == "ablation"}
    assert set(OPTIONAL_RECIPES) <= set(PRESETS["tiny"].recipes)  # the tests still run them
    assert set(OPTIONAL_RECIPES) == {r.name for r in recipes if r.optional}


def test_the_presets_lists_of_recipes_are_the_recipe_files_kinds_in_their_order() -> None:
    """Which recipes a preset runs, and in which order (the report's rows, the first recipe the paired tests'
    reference), is what each recipe file says: its kind, whether it is optional, its order. The lists are the ones
    the presets always ran."""
    paper = ("paper-hybrid-ppo", "paper-hybrid-ppo-warm", "paper-a2c", "paper-dqn", "paper-ppo-pure",
             "paper-ppo-image", "paper-ppo-prediction")  # fmt: skip
    best = ("hybrid-ppo", "pure-ppo", "pure-ppo-dagger", "prediction-ppo", "image-ppo", "a2c-hybrid", "dqn-hybrid")
    optional = ("hybrid-ppo-dagger", "attention-ppo", "roads-ppo", "drawn-roads-ppo", "distil-safety-ppo")
    ablation = tuple(f"ablation-{block}{mode}" for block in ("", "roads-")  # hybrid first: the paired tests' reference
                     for mode in ("hybrid", "pure", "image", "prediction", "lane-aware"))  # fmt: skip
    assert (listed_recipes("paper"), listed_recipes("best"), listed_recipes("best", optional=True)) == (
        paper, best, optional)
    assert (PAPER_RECIPES, BEST_RECIPES, OPTIONAL_RECIPES, ABLATION_RECIPES) == (paper, best, optional, ablation)
    assert PRESETS["paper"].recipes == (*paper, *best)
    assert PRESETS["tiny"].recipes == (*paper, *best, *optional, "quick-pure", "ablation-lane-aware")
    assert PRESETS["ablation"].recipes == ablation and PRESETS["quick"].recipes == ("quick-pure",)
    assert dict(PRESETS["ablation"].recipe_seeds) == dict.fromkeys(ablation, 3)
    for kind in RECIPE_KINDS:  # the listing reads the files as load_recipe does
        for opt in (False, True):
            loaded = sorted((r.order, r.name) for r in map(load_recipe, recipe_names())
                            if r.kind == kind and r.optional == opt)  # fmt: skip
            assert listed_recipes(kind, optional=opt) == tuple(name for _, name in loaded)


def write(tmp_path: Path, text: str, name: str = "mine") -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(f'name = "{name}"\nrow = "ppo-pure"\n' + text)
    return path


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("colour = 3\n", "unknown key(s) ['colour']"),
        ('stages = ["train"]\n[train]\ntimestep = 5\n', "unknown PolicyConfig field 'timestep'"),
        ('[policy]\ngamma = "high"\n', "PolicyConfig.gamma must be of type float"),
        ('[policy]\nseed = 3\n', "'seed' is set by the experiment"),
        ('stages = ["train", "clone"]\n', "each once and in that order"),
        ('stages = ["dagger", "train"]\n', "a dagger stage needs a clone stage"),
        ('stages = ["clone"]\n[demos]\ndriver = "nobody"\n', "demos.driver must be one of"),
        ('[demos]\nepisodes = 0\n', "demos.episodes must be >= 1"),
        ('[dagger]\nround = 2\n', "[dagger] has no key(s) ['round']"),
        ('[policy]\nfreeze_image = true\nobs = "hybrid"\n', "freeze_image needs init_policy"),
        ('kind = "fast"\n', "kind must be one of"),
        ("version = 0\n", "version must be an integer >= 1"),
        ("[policy\n", "is not valid TOML"),
        ('stages = ["train", "shielded"]\n', "a shielded stage needs a stage before it and a [safety] table"),
        ('stages = ["shielded"]\n[safety]\nfollow = "pure-ppo"\n', "a shielded stage needs a stage before it"),
        ('stages = ["train", "shielded"]\n[shielded]\npenalty = -1.0\n[safety]\nfollow = "pure-ppo"\n',
         "shielded.penalty must be >= 0"),
        ("[shielded]\ntimesteps = 0\n", "shielded.timesteps must be >= 1"),
        ("[shielded]\npenalty = nan\n", "shielded.penalty must be >= 0"),
        ('stages = ["train", "shielded"]\n[safety]\nfollow = "mine"\n', "cannot follow the recipe itself"),
        ("[shielded]\nepisodes = 3\n", "[shielded] has no key(s) ['episodes']"),
        ('[dagger]\nexpert = "runs/x/policy.safetensors"\n', "dagger.expert must be one of oracle, safety-layer"),
        ('stages = ["dagger"]\n[dagger]\nexpert = "safety-layer"\n', "needs a [safety] table naming the recipe"),
        ('stages = ["dagger"]\n[dagger]\nexpert = "safety-layer"\n[safety]\nfollow = "mine"\n',
         "needs a [safety] table naming the recipe"),
        ('[dagger]\ncorrection_weight = 0.0\n', "dagger.correction_weight must be > 0"),
        ('[dagger]\ncorrection_weight = nan\n', "dagger.correction_weight must be > 0"),
        ('[dagger]\ncorrection_weight = "high"\n', "dagger.correction_weight must be of type float"),
    ],
)
def test_a_bad_recipe_is_one_line_naming_the_file_and_the_problem(tmp_path: Path, text: str, message: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ValueError) as exc:
        load_recipe(path)
    msg = str(exc.value)
    assert message in msg and str(path) in msg and "\n" not in msg


def test_the_file_name_is_the_recipe_name_and_an_unknown_name_lists_the_recipes(tmp_path: Path) -> None:
    path = tmp_path / "other.toml"
    path.write_text('name = "mine"\nrow = "ppo-pure"\n')
    with pytest.raises(ValueError, match="differs from the file's name"):
        load_recipe(path)
    with pytest.raises(ValueError, match=r"unknown recipe 'nope'; choose one of .*hybrid-ppo"):
        load_recipe("nope")


def test_settings_override_a_recipe_as_the_fields_type_and_refuse_what_it_does_not_have() -> None:
    r = load_recipe("pure-ppo").with_settings(["train.learning_rate=1e-4", "demos.episodes=50",
                                               "policy.window_features=false", "clone.warm_start_epochs=3"])
    assert r.table("train")["learning_rate"] == 1e-4 and r.table("demos").episodes == 50 and r.policy["window_features"] is False
    cfg = r.policy_config("clone", scenario="paper", seed=0, warm_start="/d")
    assert cfg.warm_start_epochs == 3 and not cfg.window_features
    for bad, message in (("train.learning_rat=1", "PolicyConfig has no field 'learning_rat'"),
                         ("train.timesteps=many", "expected a value of type int"),
                         ("demos.episodes=-1", "demos.episodes must be >= 1"),
                         ("colour.x=1", "no table 'colour'"),
                         ("timesteps=5", "expected TABLE.KEY=VALUE")):  # fmt: skip
        with pytest.raises(ValueError) as exc:
            load_recipe("pure-ppo").with_settings([bad])
        assert message in str(exc.value) and "\n" not in str(exc.value)
    safe = load_recipe("hybrid-ppo").with_settings(["safety.samples=5", "safety.horizon=24"])  # an older key too
    assert safe.safety is not None and (safe.safety.samples, safe.safety.horizon_decisions) == (5, 24)
    assert safe.safety.follow == "pure-ppo" and safe.safety.blind and safe.safety.perceived
    for bad, message in (("safety.samples=many", "expected a value of type int"),
                         ("safety.margin_m=1", "margin_m was a research option"),
                         ("safety.blind=false", "samples > 1 needs blind")):  # fmt: skip
        with pytest.raises(ValueError) as exc:
            load_recipe("hybrid-ppo").with_settings([bad])
        assert message in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(ValueError, match=r"safety\.blind must be true: a recipe.s safety layer"):  # the privileged one
        load_recipe("hybrid-ppo").with_settings(["safety.blind=false", "safety.perceived=false", "safety.samples=1"])


def test_caps_lower_every_budget_but_seeds() -> None:
    caps = PRESETS["tiny"].cap_dict
    r = load_recipe("pure-ppo-dagger").capped(caps)
    demos, dagger = r.table("demos"), r.table("dagger")
    assert (demos.episodes, demos.seed, dagger.rounds, dagger.episodes) == (2, 5000, 1, 2)
    cfg = r.policy_config("train", scenario="tiny", seed=0, init_policy="/p", caps=caps)
    assert (cfg.timesteps, cfg.n_envs, cfg.learning_rate) == (128, 4, 3e-5)


def test_a_recipe_file_configures_lc_train_policy(tmp_path: Path) -> None:
    """lc-train-policy --config reads a recipe's [policy] table (the stage tables are the experiment's)."""
    from lcmodels.experiment.recipe import recipe_path
    from lcmodels.policy.config import PolicyConfig

    cfg = PolicyConfig.from_file(recipe_path("hybrid-ppo"), table="policy")
    assert (cfg.algo, cfg.obs, cfg.window_features) == ("ppo", "hybrid", True)
    assert isinstance(load_recipe("hybrid-ppo"), Recipe)


def test_what_a_recipe_reached_is_recorded_next_to_it_for_its_version() -> None:
    import json

    from lcmodels.experiment.recipe import RECIPES_DIR

    for path in RECIPES_DIR.glob("*.reached.json"):
        reached = json.loads(path.read_text())
        recipe = load_recipe(path.name.removesuffix(".reached.json"))
        assert reached["recipe"] == recipe.name and reached["recipe_version"] == recipe.version
        assert reached["experiment_command"].startswith("lc-experiment ") and reached["heldout"]["episodes"] >= 200


def test_safety_layers_whose_followers_loop_are_one_line_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import dataclasses

    from lccli.experiment import experiment_main

    base = load_recipe("pure-ppo")
    for name, follow in (("loop-a", "loop-b"), ("loop-b", "loop-a")):
        r = dataclasses.replace(base, name=name, safety=dataclasses.replace(load_recipe("hybrid-ppo").safety,
                                                                            follow=follow))  # fmt: skip
        (tmp_path / f"{name}.toml").write_text(r.to_toml())
    args = ["--preset", "tiny", "--recipe", str(tmp_path / "loop-a.toml"), "--recipe", str(tmp_path / "loop-b.toml")]
    assert experiment_main([*args, "--out", str(tmp_path / "run"), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "loop-a -> loop-b -> loop-a" in err and "Traceback" not in err


@pytest.mark.parametrize(("text", "message"), [
    ('stages = ["clone", "train"]\n[demos]\nepisodes = 1000000000000\n', "demos.episodes must be at most"),
    ("[train]\ntimesteps = 1000000000000000\n", "timesteps must be at most"),
    ("[policy]\nn_envs = 999999\n", "n_envs must be at most"),
    ('stages = ["clone", "dagger", "train"]\n[dagger]\nrounds = 1000000000\n', "dagger.rounds must be at most"),
    ('stages = ["clone", "dagger", "train"]\n[dagger]\nepochs = 1000000000\n', "dagger.epochs must be at most"),
    ('stages = ["train", "shielded"]\n[safety]\nfollow = "pure-ppo"\n[shielded]\ntimesteps = 10000000000000\n',
     "shielded.timesteps must be at most"),
    ("[shielded]\npenalty = 1e300\n", "shielded.penalty must be at most"),
    ("[dagger]\ncorrection_weight = 1e9\n", "dagger.correction_weight must be at most"),
    ("[safety]\nhorizon = 1000000000\n", "horizon_decisions must be at most"),
    ('stages = [{a = 1}]\n', "stages"),
    ("x = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),
])
def test_a_recipe_with_absurd_budgets_is_one_line(tmp_path: Path, text: str, message: str) -> None:
    """A recipe asking for 1e12 episodes or 1e15 steps would run for ever: refused when read, before any stage."""
    path = write(tmp_path, text)
    with pytest.raises(ValueError) as exc:
        load_recipe(path)
    assert message in str(exc.value) and str(path) in str(exc.value) and "\n" not in str(exc.value)


def test_lc_experiment_refuses_an_absurd_recipe_and_the_home_directory(tmp_path: Path, monkeypatch,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    from lccli.experiment import experiment_main

    path = write(tmp_path, '[policy]\nobs = "pure"\n[train]\ntimesteps = 1000000000000000\n')
    assert experiment_main(["--preset", "tiny", "--recipe", str(path), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "timesteps must be at most" in err and err.count("\n") == 1 and not (tmp_path / "x").exists()
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    for out in (str(home), "/"):
        assert experiment_main(["--preset", "tiny", "--out", out]) == 2
        err = capsys.readouterr().err
        assert ("home directory" in err or "filesystem root" in err) and err.count("\n") == 1
    assert not list(home.iterdir())


def test_the_a2c_recipes_get_their_rollout_length_from_the_one_place_that_fills_defaults() -> None:
    """n_steps is A2C's own default (8) without the recipe saying it, in every online stage; the learning rate is the
    algorithm's, a tenth of it from a previous stage, unless the recipe sets one."""
    from lcmodels.policy.config import PolicyConfig

    for name in ("a2c-hybrid", "paper-a2c"):
        recipe = load_recipe(name)
        assert all("n_steps" not in t for t in (recipe.policy, recipe.table("clone"), recipe.table("train")))
        cfg = recipe.policy_config("train", scenario="paper", seed=0, init_policy="p.safetensors" if
                                   recipe.stages[0] != "train" else "")  # fmt: skip
        assert cfg.n_steps == 8 and cfg.algo == "a2c"
    assert PolicyConfig.of({"algo": "a2c"}).learning_rate == 7e-4
    assert PolicyConfig.of({"algo": "a2c", "init_policy": "p.safetensors"}).n_steps == 8
    assert PolicyConfig.of({"algo": "ppo", "init_policy": "p.safetensors"}).learning_rate == 3e-5
    assert PolicyConfig.of({}, ["algo=a2c", "n_steps=16"]).n_steps == 16
    assert PolicyConfig.of({"algo": "ppo", "warm_start": "d"}, fine_tune=False).learning_rate == 3e-4
