"""The typed driver spec: one grammar for every spelling, and the ledger's identities unchanged by it."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import pytest

from lcmodels.policy.driverspec import DriverSpec, parse_driver_spec, split_policy_spec
from lcsim.planning import PRIVILEGED, SafetyLayerConfig

LEDGER = Path(__file__).resolve().parents[1] / "docs" / "results" / "benchmark" / "ledger.jsonl"


def test_every_spelling_parses_to_what_it_means():
    blind = SafetyLayerConfig(perceived=False)
    assert parse_driver_spec("rule") == DriverSpec(text="rule", kind="driver", name="rule")
    assert parse_driver_spec("lookahead-blind") == DriverSpec(text="lookahead-blind", kind="driver", name="rule",
                                                              layer=blind)  # fmt: skip
    assert parse_driver_spec("lookahead").layer == PRIVILEGED
    assert parse_driver_spec("safety-layer:rule").layer == SafetyLayerConfig()
    for text, layer in (("safety-layer:runs/p.safetensors", SafetyLayerConfig()),
                        ("lookahead-blind:runs/p.safetensors", blind), ("lookahead:runs/p.safetensors", PRIVILEGED),
                        ("runs/p.safetensors", None), ("policy:runs/p.safetensors", None)):  # fmt: skip
        spec = parse_driver_spec(text)
        assert (spec.kind, spec.path, spec.layer, spec.text) == (
            "policy",
            Path("runs/p.safetensors"),
            layer,
            text,
        )
    assert parse_driver_spec("my_pkg.drivers:drive").kind == "callable"
    zoo = parse_driver_spec("safety-layer:zoo:pure-ppo")
    assert zoo.kind == "policy" and zoo.path.is_file() and zoo.path.parent.name == "pure-ppo"
    assert pickle.loads(pickle.dumps(zoo)) == zoo  # shipped to the workers that evaluate shards


def test_the_words_that_name_a_policy_file():
    assert split_policy_spec("lookahead-blind:runs/p.safetensors") == (
        "lookahead-blind:",
        "runs/p.safetensors",
    )
    assert split_policy_spec("safety-layer:runs/p.safetensors") == ("safety-layer:", "runs/p.safetensors")
    assert split_policy_spec("rule") is None and split_policy_spec("policy:") is None


def test_settings_and_follower_go_into_the_layer_once():
    spec = parse_driver_spec(
        "lookahead-blind:runs/p.safetensors", safety_table={"horizon": 32}, follow="rule"
    )
    assert spec.layer == SafetyLayerConfig(perceived=False, horizon_decisions=32, follow="rule")
    assert spec.follow == parse_driver_spec("rule")
    layer = SafetyLayerConfig(samples=3)
    assert parse_driver_spec("safety-layer:runs/p.safetensors", safety_table=layer).layer == layer


@pytest.mark.parametrize(("text", "kw", "message"), [
    ("rule", {"safety_table": {"samples": 2}}, "drives behind none"),
    ("runs/p.safetensors", {"follow": "rule"}, "drives behind none"),
    ("rule", {"safety_table": SafetyLayerConfig()}, "apply to a driver behind it"),
    ("safety-layer:keep", {}, "guards a policy or the rule-based driver"),
    ("safety-layer:rule", {"follow": "keep"}, "applies to a policy behind the safety layer"),
    ("zoo:no-such-entry", {}, "no zoo policy"),
])  # fmt: skip
def test_what_the_layer_may_not_guard_is_refused_in_one_place(text, kw, message):
    with pytest.raises(ValueError, match=message):
        parse_driver_spec(text, **kw)


def _ledger_layer(ident: dict) -> SafetyLayerConfig:
    from lcsim.planning.safety import REFERENCE

    return SafetyLayerConfig(**{**REFERENCE, **ident["lookahead"]})


def test_every_driver_the_ledger_holds_keeps_its_identity():
    """Each spelling the committed ledger holds, resolved again, gives the identity written with it byte for byte
    (its key: the ledger's cells stay found)."""
    from lcmodels.bench.run import resolve_driver

    seen = set()
    for line in LEDGER.read_text().splitlines():
        row = json.loads(line)
        ident, about = row["identity"], row["about"]
        if (row["label"], json.dumps(ident, sort_keys=True)) in seen:
            continue
        seen.add((row["label"], json.dumps(ident, sort_keys=True)))
        if ident["kind"] == "safety-layer":
            layer = _ledger_layer(ident)
            spec = parse_driver_spec(row["label"], safety_table=layer, follow=about.get("follow"))
        else:
            spec = parse_driver_spec(row["label"])
        got = resolve_driver(spec).identity
        assert json.dumps(got, sort_keys=True) == json.dumps(ident, sort_keys=True), row["label"]
    assert len(seen) >= 20
