import dataclasses
import json

import pytest

from lcsim.config import EgoConfig, PIDGains, RoadConfig, ScenarioConfig, TrafficConfig, corpus_scenario


def test_json_round_trip():
    cfg = ScenarioConfig(road=RoadConfig(num_lanes=5), ego=EgoConfig(adaptive_cruise=True))
    back = ScenarioConfig.from_json(cfg.to_json())
    assert back == cfg
    assert json.loads(cfg.to_json())["road"]["num_lanes"] == 5
    assert ScenarioConfig.from_json(corpus_scenario().to_json()) == corpus_scenario()


@pytest.mark.parametrize(("factory", "field"), [
    (lambda: RoadConfig(num_lanes=7), "num_lanes"),
    (lambda: RoadConfig(lane_width_m=-3.5), "lane_width_m"),
    (lambda: TrafficConfig(speed_kmh=0.0), "speed_kmh"),
    (lambda: TrafficConfig(num_vehicles=-1), "num_vehicles"),
    (lambda: EgoConfig(max_throttle=1.5), "max_throttle"),
    (lambda: EgoConfig(wheelbase_m=5.0), "wheelbase_m"),
    (lambda: PIDGains(kp=-1.0, ki=0.0, kd=0.0), "kp"),
    (lambda: ScenarioConfig(dt_s=0.05, decision_period_s=0.12), "decision_period_s"),
    (lambda: ScenarioConfig(time_limit_s=float("nan")), "time_limit_s"),
    (lambda: ScenarioConfig(traffic=TrafficConfig(num_vehicles=2000)), "num_vehicles"),
    (lambda: ScenarioConfig(ego=EgoConfig(start_lane=4)), "start_lane"),
    (lambda: ScenarioConfig(neighbour_selection="closest"), "neighbour_selection"),
    (lambda: ScenarioConfig(num_neighbours=17), "num_neighbours"),  # 16 lane slots
])
def test_bad_values_raise_naming_the_field(factory, field):
    with pytest.raises(ValueError, match=field):
        factory()


def test_unknown_key_is_an_error():
    data = json.loads(ScenarioConfig().to_json())
    data["traffic"]["num_vehicels"] = 3
    with pytest.raises(ValueError, match="num_vehicels"):
        ScenarioConfig.from_dict(data)


def test_configs_are_frozen():
    cfg = ScenarioConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.dt_s = 0.1  # type: ignore[misc]


def test_configs_stored_before_neighbour_selection_read_as_nearest():
    data = json.loads(ScenarioConfig().to_json())
    assert data["neighbour_selection"] == "lanes"
    del data["neighbour_selection"]  # as in recordings and checkpoints made before the field existed
    assert ScenarioConfig.from_dict(data).neighbour_selection == "nearest"
    assert ScenarioConfig(num_neighbours=12, neighbour_selection="nearest").num_neighbours == 12


# -- absurd values and files that would make a reader recurse or allocate without end --------------------------
@pytest.mark.parametrize(("data", "field"), [
    ({"traffic": {"speed_kmh": 1e308}}, "speed_kmh"),
    ({"traffic": {"num_vehicles": 10**12}}, "num_vehicles"),
    ({"traffic": {"spawn_ahead_m": float("inf")}}, "spawn_ahead_m"),
    ({"history_steps": 10**20}, "history_steps"),
    ({"history_steps": 1e20}, "history_steps"),
    ({"num_neighbours": 10**6, "neighbour_selection": "nearest"}, "num_neighbours"),
    ({"time_limit_s": 1e9}, "time_limit_s"),
    ({"dt_s": 1e-12, "decision_period_s": 5e-12}, "dt_s"),
    ({"dt_s": 0.001, "decision_period_s": 0.5, "time_limit_s": 86_400.0}, "time_limit_s"),  # 86.4 M steps
    ({"route_length_m": 1e12}, "route_length_m"),
    ({"render": {"max_vehicles_drawn": 10**9}}, "max_vehicles_drawn"),
    ({"ego": {"target_speed_kmh": 1e6}}, "target_speed_kmh"),
    ({"ego": {"pid_window": 10**9}}, "pid_window"),
    ({"ego": {"lateral_pid": {"kp": 1e300, "ki": 0.0, "kd": 0.0}}}, "kp"),
    ({"reward": {"collision": -1e300}}, "collision"),
    ({"reward": {"milestones": [0.5] * 1000 + [1.0], "milestone_rewards": [1.0] * 1001}}, "milestones"),
    ({"reward": {"milestone_rewards": ["a lot", 1, 2, 3]}}, "milestone_rewards"),
    ({"traffic": {"speed_kmh": [24.0]}}, "speed_kmh"),
    ({"traffic": {"lane_changes": "yes"}}, "lane_changes"),
    ({"road": {"lane_width_m": "wide"}}, "lane_width_m"),
    ({"sensing_range_m": True}, "sensing_range_m"),
])
def test_absurd_or_mistyped_values_are_refused_naming_the_field(data, field):
    """Every number a scenario holds has a plausible range (1e308 km/h, 1e20 steps of history, a day of
    1 ms steps are slips or crafted files, and would allocate or loop without end), every field its type."""
    with pytest.raises(ValueError) as exc:
        ScenarioConfig.from_dict(data, stored=False)
    assert field in str(exc.value) and "\n" not in str(exc.value)


def test_the_shipped_scenarios_are_within_the_bounds():
    from lcsim.registry import SCENARIOS

    for make in SCENARIOS.values():
        config = make()
        assert ScenarioConfig.from_dict(config.to_dict()) == config


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_a_deeply_nested_file_is_one_line_not_a_recursion_error(tmp_path, suffix):
    from lckit.config import read_data_file
    from lcsim.registry import scenario

    deep = "[" * 5000 + "]" * 5000
    path = tmp_path / f"deep{suffix}"
    path.write_text(f"x = {deep}\n" if suffix == ".toml" else f'{{"x": {deep}}}')
    for read in (lambda: read_data_file(path, "config file"), lambda: scenario(path)):
        with pytest.raises(ValueError, match="nested too deeply") as exc:
            read()
        assert str(path) in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(ValueError, match="nested too deeply"):
        ScenarioConfig.from_json('{"road": ' + "[" * 5000 + "]" * 5000 + "}")


def test_a_data_file_larger_than_any_config_is_refused_before_it_is_read(tmp_path):
    from lckit.config import DATA_FILE_MAX_BYTES, read_data_file

    path = tmp_path / "huge.toml"
    with open(path, "wb") as f:  # sparse: nothing is written to the disk
        f.truncate(DATA_FILE_MAX_BYTES + 1)
    with pytest.raises(ValueError, match="bytes, more than"):
        read_data_file(path, "scenario file")
