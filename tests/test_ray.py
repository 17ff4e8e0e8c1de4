"""Ray as the executor: the tiny preset, an evaluation and a recording give what the local executor gives,
episode for episode; without Ray, asking for it is one line that says how to install it."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from lccli.evaluate import eval_main
from lccli.experiment import experiment_main
from lccli.record import record_main

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def ray_instance():
    """A local Ray instance of 2 CPUs for the module (the commands reuse a session that is open)."""
    ray.init(num_cpus=2, include_dashboard=False, configure_logging=False, log_to_driver=False)
    yield
    ray.shutdown()


def _figures(path: Path, base: Path | None = None) -> dict:
    """A metrics file without what differs between two runs of the same work in two directories: wall times, the
    command that made it, the directory in the paths it names (``base``), and the policy's hash (its card names the predictor's
    path, which is in the run directory; so does an initial policy's hash)."""

    def strip(x, parent=""):
        if isinstance(x, dict):
            return {k: strip(v, k) for k, v in x.items()
                    if k not in ("wall_s", "seconds", "collect_s", "train_s", "policy_sha256", "command") and not (parent == "warm_start" and k == "sha256")}
        if isinstance(x, list):
            return [strip(v, parent) for v in x]
        return x.replace(str(base), "DIR") if isinstance(x, str) and base is not None else x

    return strip(json.loads(path.read_text()))


@pytest.mark.slow
def test_the_tiny_preset_on_ray_gives_the_local_figures(ray_instance, tmp_path):
    for executor in ("local", "ray"):
        assert experiment_main(["--preset", "tiny", "--out", str(tmp_path / executor), "--executor", executor,
                                "--recipe", "paper-hybrid-ppo-warm", "--recipe", "pure-ppo-dagger",
                                "--recipe", "hybrid-ppo", "-q"]) == 0  # clone, DAgger, train, the safety layer
    files = sorted(p.relative_to(tmp_path / "local") for p in (tmp_path / "local").rglob("metrics.json"))
    assert len(files) >= 10  # predictor, rule, every policy and its evaluation
    for rel in files:
        assert _figures(tmp_path / "ray" / rel, tmp_path / "ray") == _figures(tmp_path / "local" / rel,
                                                                             tmp_path / "local"), rel
    from safetensors.torch import load_file

    policies = sorted(p.relative_to(tmp_path / "local") for p in (tmp_path / "local").rglob("policy.safetensors"))
    assert len(policies) >= 5  # clone, DAgger rounds, training runs
    for rel in policies:  # the same weights (the cards name the predictor's path in each directory)
        a, b = load_file(tmp_path / "local" / rel), load_file(tmp_path / "ray" / rel)
        assert a.keys() == b.keys() and all(bool((a[k] == b[k]).all()) for k in a), rel
    for rel in sorted(p.relative_to(tmp_path / "local") for p in (tmp_path / "local").rglob("*.mcap")):
        assert (tmp_path / "ray" / rel).read_bytes() == (tmp_path / "local" / rel).read_bytes(), rel


def test_lc_eval_and_lc_record_on_ray_give_the_local_json_and_files(ray_instance, tmp_path):
    common = ["rule", "--scenario", "tiny", "--episodes", "8", "--batch", "2", "-q"]
    assert eval_main([*common, "--out", str(tmp_path / "el"), "--json-out", str(tmp_path / "local.json")]) == 0
    assert eval_main([*common, "--out", str(tmp_path / "er"), "--json-out", str(tmp_path / "ray.json"),
                      "--executor", "ray", "--shards", "3"]) == 0
    assert _figures(tmp_path / "ray.json") == _figures(tmp_path / "local.json")
    local = sorted((tmp_path / "el").glob("*.mcap"))
    assert len(local) == 8
    assert all((tmp_path / "er" / p.name).read_bytes() == p.read_bytes() for p in local)
    for executor in ("local", "ray"):
        assert record_main(["--scenario", "tiny", "--episodes", "3", "--steps", "40", "--out",
                            str(tmp_path / f"r-{executor}"), "--executor", executor]) == 0
    recorded = sorted((tmp_path / "r-local").glob("*.mcap"))
    assert len(recorded) == 3
    assert all((tmp_path / "r-ray" / p.name).read_bytes() == p.read_bytes() for p in recorded)


def test_without_ray_asking_for_it_is_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # as if it were not installed
    assert eval_main(["rule", "--scenario", "tiny", "--episodes", "2", "--no-record", "--executor", "ray"]) == 2
    assert record_main(["--scenario", "tiny", "--out", str(tmp_path / "r"), "--executor", "ray"]) == 2
    for line in capsys.readouterr().err.strip().splitlines():
        assert "pip install -e \".[ray]\"" in line and "Traceback" not in line


SWEEP = """seeds = [0, 1]
[base]
obs = "pure"
scenario = "tiny"
timesteps = 64
n_envs = 2
n_steps = 32
batch_size = 64
n_epochs = 1
eval_episodes = 4
eval_batch = 4
record_eval = false
[grid]
gamma = [0.9, 0.95]
"""


@pytest.mark.slow
def test_a_sweep_on_ray_tune_gives_the_local_table(ray_instance, tmp_path):
    from lccli.tune import main as tune_main

    sweep = tmp_path / "sweep.toml"
    sweep.write_text(SWEEP)
    for executor in ("local", "ray"):
        assert tune_main([str(sweep), "--out", str(tmp_path / executor), "--executor", executor, "-q"]) == 0
    local, remote = (json.loads((tmp_path / e / "sweep.json").read_text())["trials"] for e in ("local", "ray"))
    assert len(local) == 4 and [r["trial"] for r in local] == [r["trial"] for r in remote]
    for a, b in zip(local, remote, strict=True):
        assert {k: v for k, v in a.items() if k != "train_wall_s"} == {k: v for k, v in b.items() if k != "train_wall_s"}
    rates = [r["success_rate"] for r in local]
    assert rates == sorted(rates, reverse=True)  # sorted by held-out success
