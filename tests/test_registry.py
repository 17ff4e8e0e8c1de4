"""One registry of scenario and driver names (lcsim.registry), used by the gym ids and every command; a
scenario file is accepted wherever a name is."""

import json

import pytest

import lcsim
from lccli.record import record_main
from lcdata import read_episode
from lcmodels.policy import PolicyConfig
from lcmodels.policy.plan import policy_scenario
from lcsim.config import corpus_scenario, light_scenario, paper_scenario, tiny_scenario
from lcsim.registry import DRIVER_NAMES, SCENARIOS, TASK_SCENARIOS, make_driver, scenario
from lcsim.suite import SUITE_SCENARIOS


def test_every_name_means_one_scenario_everywhere():
    suite = {name: road.make for name, road in SUITE_SCENARIOS.items() if name != "paper"}
    assert SCENARIOS == {"paper": paper_scenario, "light": light_scenario, "tiny": tiny_scenario,
                         "corpus": corpus_scenario, **suite}  # and the benchmark suite's roads
    assert SUITE_SCENARIOS["paper"].make is paper_scenario
    assert set(TASK_SCENARIOS) == set(SCENARIOS) - {"corpus"}
    assert set(lcsim.ENV_IDS.values()) <= set(SCENARIOS)
    assert policy_scenario(PolicyConfig(scenario="light")).traffic == light_scenario().traffic
    with pytest.raises(ValueError, match="unknown scenario 'lane-change'"):
        scenario("lane-change")


def test_a_scenario_file_is_a_scenario(tmp_path):
    toml = tmp_path / "busy.toml"
    toml.write_text('route_length_m = 200.0\ntime_limit_s = 30.0\n[traffic]\nnum_vehicles = 12\n'
                    'spawn_behind_m = 40.0\nspawn_ahead_m = 120.0\n')
    config = scenario(toml)
    assert (config.route_length_m, config.traffic.num_vehicles) == (200.0, 12)
    assert config.road == paper_scenario().road  # what the file does not say keeps its default
    as_json = tmp_path / "busy.json"
    as_json.write_text(json.dumps(config.to_dict()))
    assert scenario(as_json) == config
    bad = tmp_path / "bad.toml"
    bad.write_text("[traffic]\nnum_vehicle = 3\n")  # misspelt
    with pytest.raises(ValueError, match=r"bad\.toml.*num_vehicle"):
        scenario(bad)
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        scenario(broken)
    with pytest.raises(ValueError, match="does not exist"):
        scenario(tmp_path / "missing.toml")
    # the commands take it where they take a name
    assert record_main(["--scenario", str(toml), "--steps", "20", "--out", str(tmp_path / "rec")]) == 0
    (path,) = (tmp_path / "rec").glob("*.mcap")
    assert path.name == "busy_rule_s0000000.mcap"
    assert read_episode(path).metadata["config"]["traffic"]["num_vehicles"] == 12
    assert policy_scenario(PolicyConfig(scenario=str(toml), obs="pure")).route_length_m == 200.0


def test_driver_names():
    for name in DRIVER_NAMES:
        assert callable(make_driver(name))
    with pytest.raises(ValueError, match="unknown driver"):
        make_driver("autopilot")
