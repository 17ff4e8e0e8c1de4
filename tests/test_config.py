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
