"""Policy files are data: safetensors + a JSON card, legacy pickles refused unless trusted, and the run
directory's own files the only ones ``--overwrite`` touches."""

from __future__ import annotations

import base64
import json
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from lccli.evaluate import eval_main
from lccli.policy import train_policy_main
from lccli.record import record_main
from lcmodels.policy import PolicyConfig, load_policy, read_meta, train_policy
from lcmodels.policy.checkpoint import LEGACY_VERSION, META_FORMAT, card_path, convert_legacy_policy
from lcmodels.policy.train import RUN_OUTPUTS
from lcsim.sb3 import LaneChangeSB3VecEnv


def _tiny(**kw) -> PolicyConfig:
    base = dict(scenario="tiny", obs="pure", timesteps=64, n_envs=2, n_steps=32, batch_size=64, n_epochs=1,
                eval_episodes=0, checkpoint_every=64)
    base.update(kw)
    return PolicyConfig(**base)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("policy") / "run"
    train_policy(_tiny(), out)
    return out


def _legacy_zip(model, meta: dict, path: Path) -> Path:
    """A policy as this project wrote them before: stable-baselines3's own ``.zip`` with ``lc_meta``."""
    model.lc_meta = {**{k: v for k, v in meta.items() if k not in ("format", "version")},
                     "format": META_FORMAT, "version": LEGACY_VERSION}
    model.save(path, include=["lc_meta"])
    return path


class _WritesMarker:
    """Unpickling this writes a file: what a crafted policy.zip can make any unpickling loader do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "code ran"))


def _crafted_zip(run_dir: Path, path: Path, marker: Path) -> Path:
    """A legacy-looking policy whose ``data`` record carries a pickled payload, as SB3 stores objects."""
    legacy = _legacy_zip(load_policy(run_dir / "policy.safetensors").model,
                         read_meta(run_dir / "policy.safetensors"), path.with_name("clean.zip"))
    payload = base64.b64encode(pickle.dumps(_WritesMarker(marker))).decode()
    with zipfile.ZipFile(legacy) as zin, zipfile.ZipFile(path, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "data":
                record = json.loads(data)
                record["policy_class"] = {":type:": "<class 'type'>", ":serialized:": payload}
                data = json.dumps(record).encode()
            zout.writestr(item, data)
    return path


def test_policy_file_is_safetensors_with_its_card_and_loads_to_the_same_actions(run_dir: Path) -> None:
    path = run_dir / "policy.safetensors"
    raw = path.read_bytes()
    header_len = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8 : 8 + header_len])
    card = json.loads(header["__metadata__"]["lc_card"])
    assert card == read_meta(path) == json.loads(card_path(path).read_text())
    assert (card["format"], card["algo"], card["obs_mode"], card["timesteps"]) == (META_FORMAT, "ppo", "pure", 64)
    assert not zipfile.is_zipfile(path)
    every_tensor = {k for k, v in header.items() if k != "__metadata__" and "dtype" in v}
    loaded = load_policy(path)
    assert every_tensor and every_tensor <= set(loaded.model.policy.state_dict())
    again = load_policy(path)
    env = LaneChangeSB3VecEnv(4, loaded.scenario)
    env.seed(3)
    obs = {"current": env.reset()["current"]}
    a, _ = loaded.model.predict(obs, deterministic=True)
    b, _ = again.model.predict(obs, deterministic=True)
    assert np.array_equal(a, b)
    for k, v in loaded.model.policy.state_dict().items():
        assert torch.equal(v, again.model.policy.state_dict()[k])


def test_the_same_training_writes_the_same_policy_bytes(run_dir: Path, tmp_path: Path) -> None:
    """No time, no unordered map in the file: the same run gives the same SHA-256, checkable by anyone."""
    again = tmp_path / "again"
    train_policy(_tiny(), again)
    assert (again / "policy.safetensors").read_bytes() == (run_dir / "policy.safetensors").read_bytes()
    assert read_meta(run_dir / "policy.safetensors")["tensor_aliases"]  # PPO's shared extractor, stored once


def test_a_crafted_policy_zip_is_refused_and_its_code_never_runs(run_dir: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    marker = tmp_path / "marker.txt"
    evil = _crafted_zip(run_dir, tmp_path / "evil_policy.zip", marker)
    # The file is a real attack: stable-baselines3's own loader runs the payload.
    from stable_baselines3.common.save_util import load_from_zip_file

    load_from_zip_file(evil)
    assert marker.read_text() == "code ran"
    marker.unlink()
    capsys.readouterr()
    commands = [
        lambda: eval_main([str(evil), "--episodes", "1", "--no-record"]),
        lambda: eval_main([f"lookahead:{run_dir / 'policy.safetensors'}", "--lookahead-follow", str(evil),
                           "--episodes", "1", "--no-record"]),
        lambda: record_main(["--driver", f"policy:{evil}", "--out", str(tmp_path / "rec")]),
        lambda: train_policy_main(["--obs", "pure", "--scenario", "tiny", "--init-policy", str(evil),
                                   "--out", str(tmp_path / "train"), "-q"]),
    ]
    for command in commands:
        assert command() == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--trust-pickle" in err and "Traceback" not in err, err
        assert not marker.exists()
    assert not (tmp_path / "train").exists()  # a refused start writes nothing


def test_a_trusted_legacy_zip_loads_and_converts_to_the_same_tensors(run_dir: Path, tmp_path: Path) -> None:
    loaded = load_policy(run_dir / "policy.safetensors")
    legacy = _legacy_zip(loaded.model, loaded.meta, tmp_path / "old.zip")
    with pytest.raises(ValueError, match="--trust-pickle"):
        load_policy(legacy)
    trusted = load_policy(legacy, trust_pickle=True)
    want = loaded.model.policy.state_dict()
    assert all(torch.equal(trusted.model.policy.state_dict()[k], v) for k, v in want.items())
    dest = tmp_path / "new.safetensors"
    with pytest.raises(ValueError, match="--trust-pickle"):
        convert_legacy_policy(legacy, dest)  # not without saying so
    convert_legacy_policy(legacy, dest, trust_pickle=True)
    with pytest.raises(ValueError, match="already exists"):
        convert_legacy_policy(legacy, dest, trust_pickle=True)  # nothing overwritten silently
    converted = load_policy(dest).model.policy.state_dict()
    assert converted.keys() == want.keys() and all(torch.equal(converted[k], v) for k, v in want.items())


@pytest.mark.parametrize("damage", ["empty", "ten_bytes", "half", "random", "foreign_card"])
def test_damaged_policy_files_are_refused_with_one_line(run_dir: Path, tmp_path: Path, damage: str) -> None:
    from safetensors.torch import save_file

    good = (run_dir / "policy.safetensors").read_bytes()
    bad = tmp_path / "bad.safetensors"
    if damage == "foreign_card":
        save_file({"w": torch.zeros(2)}, str(bad), metadata={"lc_card": json.dumps({"format": "other"})})
    else:
        data = {"empty": b"", "ten_bytes": good[:10], "half": good[: len(good) // 2],
                "random": np.random.default_rng(0).bytes(4096)}[damage]
        bad.write_bytes(data)
    with pytest.raises(ValueError) as info:
        load_policy(bad)
    assert str(bad) in str(info.value) and "weights_only" not in str(info.value)
    assert eval_main([str(bad), "--episodes", "1", "--no-record"]) == 2


def test_overwrite_removes_only_the_runs_own_files_after_every_check(run_dir: Path, tmp_path: Path) -> None:
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    (out / "notes.txt").write_text("mine")
    (out / "checkpoints" / "my-copy.bin").write_bytes(b"mine too")
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    other = _tiny(seed=1)
    with pytest.raises(ValueError, match="another configuration"):
        train_policy(other, out)
    # --overwrite with an input that fails a later check: nothing is touched
    with pytest.raises(ValueError, match="init_policy"):
        train_policy(_tiny(seed=1, init_policy=str(tmp_path / "missing.safetensors")), out, overwrite=True)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    train_policy(other, out, overwrite=True)
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "checkpoints" / "my-copy.bin").read_bytes() == b"mine too"
    assert json.loads((out / "run.json").read_text())["config"]["seed"] == 1
    assert read_meta(out / "policy.safetensors")["train_config"]["seed"] == 1
    # a directory the tool did not write is never taken over, --overwrite or not
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("years of work")
    assert train_policy_main(["--obs", "pure", "--scenario", "tiny", "--timesteps", "64", "--out", str(foreign),
                              "--overwrite", "-q"]) == 2
    assert [p.name for p in foreign.iterdir()] == ["thesis.tex"]
    assert RUN_OUTPUTS  # the layout --overwrite removes is declared in one place


def test_refused_starts_write_nothing(tmp_path: Path, run_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    cases = [
        ["--init-policy", str(tmp_path / "missing.safetensors")],
        ["--warm-start", str(empty)],
        ["--predictor", str(tmp_path / "p.pt")],
        ["--init-policy", str(run_dir / "policy.safetensors"), "--algo", "a2c"],
    ]
    for i, extra in enumerate(cases):
        out = tmp_path / f"out{i}"
        assert train_policy_main(["--obs", "pure", "--scenario", "tiny", "--timesteps", "64", "--out", str(out),
                                  "-q", *extra]) == 2, extra
        assert not out.exists(), extra
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err, err


def test_corrupt_checkpoint_state_names_the_file(run_dir: Path, tmp_path: Path) -> None:
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    (out / "checkpoints" / "latest.json").write_text('{"timesteps": 64,')
    with pytest.raises(ValueError, match=r"checkpoints/latest\.json is corrupt"):
        train_policy(_tiny(timesteps=128), out)


@pytest.mark.parametrize("name", ["../../victim.txt", "VICTIM_ABS", "sub/step-64.safetensors", ["x"]])
def test_a_crafted_resume_record_cannot_name_files_outside_its_folder(run_dir: Path, tmp_path: Path, name) -> None:
    import json
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    victim = tmp_path / "victim.txt"
    victim.write_text("the user's")
    state_file = out / "checkpoints" / "latest.json"
    state = json.loads(state_file.read_text())
    state["weights"] = str(victim) if name == "VICTIM_ABS" else name
    state_file.write_text(json.dumps(state))
    with pytest.raises(ValueError, match="not a checkpoint file name"):
        train_policy(_tiny(timesteps=128), out)
    assert victim.read_text() == "the user's"


def test_overwrite_refuses_to_start_from_what_it_would_remove(run_dir: Path, tmp_path: Path) -> None:
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    with pytest.raises(ValueError, match="inside"):
        train_policy(_tiny(gamma=0.9, init_policy=str(out / "policy.safetensors")), out, overwrite=True)
    assert (out / "policy.safetensors").read_bytes() == (run_dir / "policy.safetensors").read_bytes()


def test_a_run_whose_scenario_file_changed_is_not_resumed(tmp_path: Path) -> None:
    scenario_file = tmp_path / "s.json"
    scenario_file.write_text(json.dumps({"route_length_m": 150.0, "time_limit_s": 25.0,
                                         "traffic": {"num_vehicles": 6, "spawn_behind_m": 40.0, "spawn_ahead_m": 80.0}}))
    train_policy(_tiny(scenario=str(scenario_file)), tmp_path / "run")
    scenario_file.write_text(json.dumps({"route_length_m": 150.0, "time_limit_s": 25.0,
                                         "traffic": {"num_vehicles": 2, "spawn_behind_m": 40.0, "spawn_ahead_m": 80.0}}))
    with pytest.raises(ValueError, match="scenario's content differs"):
        train_policy(_tiny(scenario=str(scenario_file), timesteps=128), tmp_path / "run")


def test_overwrite_leaves_none_of_the_previous_runs_tensorboard(run_dir: Path, tmp_path: Path) -> None:
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    old = {p.name for p in (out / "tb").rglob("events.out.tfevents.*")}
    assert old
    train_policy(_tiny(seed=2), out, overwrite=True)
    assert not old & {p.name for p in (out / "tb").rglob("events.out.tfevents.*")}
