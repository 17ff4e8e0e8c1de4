"""The safety layer's one config: its spellings (new and older), its tables, its settings and its identity."""

import dataclasses

import pytest

from lcmodels.policy.driverspec import safety_layer_of, split_safety_layer
from lcsim.planning import PRIVILEGED, LookaheadDriver, SafetyLayerConfig
from lcsim.planning.safety import REFERENCE
from lcsim.registry import make_driver


def test_the_defaults_are_the_layer_a_car_could_have():
    layer = SafetyLayerConfig()
    assert layer.blind and layer.perceived and layer.samples == 1 and layer.horizon_decisions == 16
    assert layer.follow == ""
    assert LookaheadDriver().config == layer and LookaheadDriver().name == "lookahead-perceived"
    assert not PRIVILEGED.blind and not PRIVILEGED.perceived


def test_every_spelling_of_a_driver_behind_the_layer_means_one_config():
    assert split_safety_layer("safety-layer:runs/p.safetensors") == ("runs/p.safetensors", SafetyLayerConfig())
    assert split_safety_layer("lookahead-blind:runs/p.safetensors") == (
        "runs/p.safetensors", SafetyLayerConfig(perceived=False))  # fmt: skip
    assert split_safety_layer("lookahead:runs/p.safetensors") == ("runs/p.safetensors", PRIVILEGED)
    assert split_safety_layer("lookahead-blind") == ("rule", SafetyLayerConfig(perceived=False))
    assert split_safety_layer("lookahead") == ("rule", PRIVILEGED)
    assert split_safety_layer("safety-layer:rule") == ("rule", SafetyLayerConfig())
    for alone in ("rule", "oracle", "runs/p.safetensors", "policy:runs/p.safetensors", "safety-layer:"):
        assert split_safety_layer(alone) == (alone, None)
    # the built-in planners are the rule-based driver behind those layers
    assert make_driver("lookahead").config == PRIVILEGED
    assert make_driver("lookahead-blind").config == SafetyLayerConfig(perceived=False)


def test_a_safety_table_reads_older_keys_and_refuses_research_options_with_where_they_went():
    table = {"follow": "pure-ppo", "horizon": 32, "samples": 3, "perceived": True}  # hybrid-ppo's before
    layer = SafetyLayerConfig.from_table(table)
    assert layer == SafetyLayerConfig(follow="pure-ppo", horizon_decisions=32, samples=3)
    assert SafetyLayerConfig.from_table({"margin_m": 0.0, "driver_draws": False, "known_drivers": []}) == (
        SafetyLayerConfig())  # neutral values a stored table spelt out
    with pytest.raises(ValueError, match=r"\[safety\]: margin_m was a research option.*experiments.imagined_drivers"):
        SafetyLayerConfig.from_table({"margin_m": 1.0})
    with pytest.raises(ValueError, match="has no setting 'horizn'"):
        SafetyLayerConfig.from_table({"horizn": 3})
    with pytest.raises(ValueError, match="horizon_decisions must be of type int"):
        SafetyLayerConfig.from_table({"horizon_decisions": 2.5})
    with pytest.raises(ValueError, match="samples > 1 needs blind"):
        SafetyLayerConfig.from_table({"samples": 2}, base=PRIVILEGED)


def test_named_settings_are_read_as_their_fields_types():
    layer = SafetyLayerConfig().with_named_settings(["safety.horizon_decisions=32", "safety.samples=3",
                                                     "safety.follow=rule", "safety.horizon=8"])  # fmt: skip
    assert layer == SafetyLayerConfig(horizon_decisions=8, samples=3, follow="rule")
    assert SafetyLayerConfig().with_named_settings(["safety.perceived=false", "safety.blind=false"]) == PRIVILEGED
    for bad, message in (("safety.samples=many", "expected a value of type int"),
                         ("safety.margin_m=1", "research option"), ("safety.wide=1", "no setting 'wide'"),
                         ("safety.blind=false", "perceived needs blind")):  # fmt: skip
        with pytest.raises(ValueError, match=message):
            SafetyLayerConfig().with_named_settings([bad])


def test_ledger_settings_name_what_differs_from_the_privileged_layer_however_spelt():
    """The ledger identifies a safety layer by these: the entries written before the one config keep their keys."""
    old = {"blind": True, "horizon_decisions": 32, "perceived": True, "samples": 3}  # the ledger's layer
    assert safety_layer_of("safety-layer:p", {"horizon_decisions": 32, "samples": 3}).ledger_settings() == old
    assert safety_layer_of("lookahead-blind:p", {"horizon_decisions": 32, "samples": 3,
                                                 "perceived": True}).ledger_settings() == old  # fmt: skip
    assert safety_layer_of("lookahead-blind:p").ledger_settings() == {"blind": True}
    assert safety_layer_of("lookahead:p", {"horizon_decisions": 16}).ledger_settings() == {}
    assert safety_layer_of("safety-layer:p", follow="rule").follow == "rule"
    assert safety_layer_of("rule") is None
    # a setting added later needs its neutral value here, or the ledger would not tell two layers apart
    assert set(REFERENCE) == {f.name for f in dataclasses.fields(SafetyLayerConfig)} - {"follow"}
    with pytest.raises(ValueError, match="drives behind none"):
        safety_layer_of("rule", {"samples": 2})
    with pytest.raises(ValueError, match="drives behind none"):
        safety_layer_of("runs/p.safetensors", follow="rule")


def test_the_config_round_trips_through_json_and_toml():
    import tomllib

    layer = SafetyLayerConfig(follow="zoo:pure-ppo", horizon_decisions=32, samples=3)
    assert SafetyLayerConfig.from_json(layer.to_json()) == layer
    assert SafetyLayerConfig.from_table(tomllib.loads(layer.to_toml())) == layer
    assert dataclasses.replace(layer, follow="") != layer


def test_lc_eval_takes_the_layer_from_a_config_file_as_from_the_flags_and_the_older_spellings(tmp_path):
    """The same safety layer three ways (a [safety] table in --config, --set, the older flags): the same figures."""
    import json

    from lccli.evaluate import eval_main

    config = tmp_path / "eval.toml"
    config.write_text('batch = 2\n[safety]\nhorizon_decisions = 2\nsamples = 2\nperceived = false\n')
    common = ["--scenario", "tiny", "--episodes", "2", "--no-record", "-q"]
    runs = {
        "file": ["safety-layer:rule", "--config", str(config)],
        "set": ["safety-layer:rule", "--set", "batch=2", "--set", "safety.horizon_decisions=2",
                "--set", "safety.samples=2", "--set", "safety.perceived=false"],
        "older": ["lookahead-blind", "--batch", "2", "--lookahead-horizon", "2", "--lookahead-samples", "2"],
    }  # fmt: skip
    out = {}
    for name, argv in runs.items():
        assert eval_main([*argv, *common, "--json-out", str(tmp_path / f"{name}.json")]) == 0, name
        summary = json.loads((tmp_path / f"{name}.json").read_text())
        out[name] = {k: v for k, v in summary.items() if k not in ("command", "wall_s")}
    assert out["file"] == out["set"] == out["older"]
    assert out["file"]["safety_layer"] == SafetyLayerConfig(horizon_decisions=2, samples=2, perceived=False).to_dict()
    assert out["file"]["driver"] == "lookahead-blind"
    bad = tmp_path / "bad.toml"
    bad.write_text("[safety]\nmargin_m = 1.0\n")
    assert eval_main(["safety-layer:rule", "--config", str(bad), *common]) == 2
