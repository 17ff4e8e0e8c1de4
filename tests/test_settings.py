"""Configuration as data: a config round-trips through its file, --set reaches every field, and an unknown
key or a bad value is one error naming it (library and command line)."""

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lccli.policy import policy_config_of, train_policy_main, train_policy_parser
from lcmodels.policy import PolicyConfig
from lcmodels.policy.plan import policy_scenario
from lcsim.config import ScenarioConfig, paper_scenario


@pytest.mark.parametrize("cfg", [PolicyConfig(), PolicyConfig(algo="dqn", obs="pure", window_features=True,
                                                              gamma=0.99, scenario="tiny"), paper_scenario()],
                         ids=["policy-defaults", "policy-changed", "scenario"])
def test_a_config_round_trips_through_toml_and_json(tmp_path, cfg):
    table = "policy" if isinstance(cfg, PolicyConfig) else None
    toml = tmp_path / "c.toml"
    toml.write_text(cfg.to_toml(table))
    back = type(cfg).from_file(toml, table=table)
    assert back == cfg and back.to_toml(table) == toml.read_text()  # file -> config -> file
    js = tmp_path / "c.json"
    js.write_text(cfg.to_json())
    assert type(cfg).from_file(js) == cfg


def test_set_reaches_every_field_nested_ones_too():
    cfg = PolicyConfig().with_settings(["gamma=0.99", "window_features=true", "n_envs=4", "image_net=vgg16"])
    assert (cfg.gamma, cfg.window_features, cfg.n_envs, cfg.image_net) == (0.99, True, 4, "vgg16")
    scenario = paper_scenario().with_settings(["traffic.num_vehicles=30", "reward.milestones=[0.5, 1.0]",
                                               "reward.milestone_rewards=[1, 2]"])
    assert scenario.traffic.num_vehicles == 30 and scenario.reward.milestones == (0.5, 1.0)


@pytest.mark.parametrize(("setting", "message"), [
    ("gama=0.9", "PolicyConfig has no field 'gama'"),
    ("gamma=high", "--set gamma=high: expected a value of type float"),
    ("gamma=2", "gamma must be in"),
    ("n_envs=2.5", "--set n_envs=2.5: expected a value of type int"),
    ("window_features=maybe", "expected true or false"),
    ("algo=sac", "PolicyConfig.algo must be one of"),
    ("no-equals-sign", "expected KEY=VALUE"),
])
def test_a_bad_setting_is_one_error_naming_it(setting, message, capsys):
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        PolicyConfig().with_settings([setting])
    assert train_policy_main(["--obs", "pure", "--set", setting, "--out", "never-written"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-train-policy: error:") and len(err.strip().splitlines()) == 1 and message in err


def test_a_bad_config_file_is_one_error_naming_it(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[policy]\ngama = 0.9\n")
    with pytest.raises(ValueError, match=r"bad\.toml: PolicyConfig: unknown field\(s\) \['gama'\]"):
        PolicyConfig.from_file(bad, table="policy")
    broken = tmp_path / "broken.toml"
    broken.write_text("gamma = \n")
    for path, message in ((bad, "gama"), (broken, "not valid TOML"), (tmp_path / "missing.toml", "does not exist")):
        assert train_policy_main(["--config", str(path), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and message in err
    assert not (tmp_path / "out").exists()


def test_defaults_then_file_then_flags_then_set(tmp_path):
    cfg_file = tmp_path / "run.toml"
    cfg_file.write_text(PolicyConfig(obs="pure", gamma=0.9, n_envs=4, seed=3).to_toml("policy"))
    parse = train_policy_parser().parse_args
    cfg = policy_config_of(parse(["--config", str(cfg_file), "--seed", "5", "--set", "n_envs=2", "--out", "x"]))
    assert (cfg.obs, cfg.gamma, cfg.seed, cfg.n_envs) == ("pure", 0.9, 5, 2)
    # a learning rate and rollout length nobody gave follow the algorithm and the start
    assert policy_config_of(parse(["--algo", "a2c", "--out", "x"])).n_steps == 8
    assert policy_config_of(parse(["--init-policy", "p.safetensors", "--out", "x"])).learning_rate == 3e-5
    assert policy_config_of(parse(["--set", "algo=dqn", "--out", "x"])).learning_rate == 1e-4
    json_file = tmp_path / "lr.json"
    json_file.write_text(json.dumps({"learning_rate": 1e-3}))
    assert policy_config_of(parse(["--config", str(json_file), "--init-policy", "p", "--out", "x"])).learning_rate == 1e-3


@settings(max_examples=80, deadline=None)
@given(st.sampled_from(sorted(PolicyConfig().to_dict())), st.text(max_size=12))
def test_any_setting_gives_a_config_or_a_value_error(key, value):
    try:
        cfg = PolicyConfig().with_settings([f"{key}={value}"])
    except ValueError:
        return
    assert isinstance(cfg, PolicyConfig) and isinstance(cfg.scenario_config(ScenarioConfig()), ScenarioConfig)
    try:  # what it names is read when a run resolves it: a scenario, or one line
        assert isinstance(policy_scenario(cfg), ScenarioConfig)
    except ValueError as exc:
        assert "\n" not in str(exc)


def test_a_setting_is_read_as_the_fields_type_not_the_files(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[policy]\ngamma = 1\n")  # an integer where the field is a float
    assert PolicyConfig.from_file(path, table="policy").with_settings(["gamma=0.99"]).gamma == 0.99
    with pytest.raises(ValueError, match="must be of type bool"):
        PolicyConfig(record_eval="no")
    with pytest.raises(ValueError, match="must be of type int"):
        PolicyConfig(n_envs=2.5)


def test_a_file_a_person_writes_gets_todays_defaults_a_stored_config_its_own(tmp_path):
    """A field missing from a stored run reads as it was before the field existed; from a config or
    scenario file a person writes, it takes today's default."""
    path = tmp_path / "c.toml"
    path.write_text("[policy]\nobs = \"pure\"\n")
    assert PolicyConfig.from_file(path, table="policy").contact_features is True  # today's default
    assert PolicyConfig.from_dict({"obs": "pure"}).contact_features is False  # a run stored before it existed
    assert policy_config_of(train_policy_parser().parse_args(["--out", "x"])).contact_features is True


def test_a_config_reads_no_file_until_a_run_resolves_it_once(tmp_path):
    """Constructing a PolicyConfig reads nothing; resolve reads the scenario it names once, and the plan keeps what
    it read (a file edited afterwards changes no run that resolved it)."""
    from lcmodels.policy.plan import resolve

    missing = PolicyConfig(scenario=str(tmp_path / "nowhere.toml"), obs="pure")
    with pytest.raises(ValueError, match=r"^PolicyConfig\.scenario: .*nowhere\.toml"):
        resolve(missing)
    path = tmp_path / "short.toml"
    path.write_text("route_length_m = 200.0\n")
    plan = resolve(PolicyConfig(scenario=str(path), obs="pure", slots=6))
    path.write_text("route_length_m = 300.0\n")
    assert plan.scenario.route_length_m == 200.0 and plan.scenario.num_neighbours == 6 and plan.roads == (plan.scenario,)
    with pytest.raises(ValueError, match="slots"):  # the view is checked without a scenario read
        PolicyConfig(slots=17)


def test_a_config_is_stored_flat_and_read_through_three_typed_views():
    """The algorithm's, the observation's and the run's fields: each field in one view, the stored form flat."""
    import dataclasses

    cfg = PolicyConfig(algo="dqn", obs="pure", slots=6, timesteps=99)
    views = (cfg.algorithm, cfg.observation, cfg.run)
    names = [f.name for view in views for f in dataclasses.fields(view)]
    assert sorted(names) == sorted(cfg.to_dict()) and len(names) == len(set(names))
    assert {k: v for view in views for k, v in dataclasses.asdict(view).items()} == cfg.to_dict()
    assert (cfg.algorithm.algo, cfg.observation.slots, cfg.run.timesteps) == ("dqn", 6, 99)
