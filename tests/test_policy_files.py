"""Policy files are data: safetensors + a JSON card, legacy pickles refused by every command (only
``tools/convert_policy.py`` reads one, when told to trust it), and the run directory's own files the only ones
``--overwrite`` touches."""

from __future__ import annotations

import base64
import importlib.util
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
from lcmodels.policy.checkpoint import META_FORMAT, card_path
from lcmodels.policy.train import RUN_OUTPUTS
from lcsim.sb3 import LaneChangeSB3VecEnv

ROOT = Path(__file__).resolve().parent.parent


def _convert_tool():
    """``tools/convert_policy.py`` as a module (the one reader of legacy ``.zip`` policies)."""
    spec = importlib.util.spec_from_file_location("convert_policy", ROOT / "tools" / "convert_policy.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
                     "format": META_FORMAT, "version": _convert_tool().LEGACY_VERSION}
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
        assert len(err.splitlines()) == 1 and "tools/convert_policy.py" in err and "Traceback" not in err, err
        assert not marker.exists()
    assert not (tmp_path / "train").exists()  # a refused start writes nothing
    with pytest.raises(SystemExit):  # no command takes the legacy flag any more
        eval_main([str(evil), "--trust-pickle", "--episodes", "1", "--no-record"])
    assert not marker.exists()
    assert _convert_tool().main([str(evil), str(tmp_path / "evil.safetensors")]) == 2  # the tool: not untrusted
    assert "--trust-pickle" in capsys.readouterr().err and not marker.exists()


def test_a_trusted_legacy_zip_converts_to_the_same_tensors_with_the_tool_only(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    tool = _convert_tool()
    loaded = load_policy(run_dir / "policy.safetensors")
    legacy = _legacy_zip(loaded.model, loaded.meta, tmp_path / "old.zip")
    for read in (load_policy, read_meta):  # the library names the tool and reads nothing more
        with pytest.raises(ValueError, match=r"tools/convert_policy\.py"):
            read(legacy)
    with pytest.raises(ValueError, match="--trust-pickle"):
        tool.load_legacy_policy(legacy)
    trusted = tool.load_legacy_policy(legacy, trust_pickle=True)
    want = loaded.model.policy.state_dict()
    assert all(torch.equal(trusted.model.policy.state_dict()[k], v) for k, v in want.items())
    dest = tmp_path / "new.safetensors"
    assert tool.main([str(legacy), str(dest)]) == 2 and not dest.exists()  # not without saying so
    assert tool.main([str(legacy), str(dest), "--trust-pickle"]) == 0
    assert tool.main([str(legacy), str(dest), "--trust-pickle"]) == 2  # nothing overwritten silently
    assert "already exists" in capsys.readouterr().err
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


# -- crafted cards: every field's type and range is checked before a network is built ------------------------
def _recard(src: Path, dest: Path, change=None, text: str | None = None) -> Path:
    """A copy of the policy file ``src`` whose card ``change`` edited (or whose card is the raw ``text``)."""
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    with safe_open(str(src), framework="pt") as f:
        header = dict(f.metadata() or {})
    card = json.loads(header["lc_card"])
    if change is not None:
        change(card)
    dest.parent.mkdir(parents=True, exist_ok=True)
    save_file(load_file(str(src)), str(dest), metadata={**header, "lc_card": text or json.dumps(card)})
    return dest


def _set(*keys_and_value):
    *keys, value = keys_and_value

    def change(card: dict) -> None:
        node = card
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value
    return change


CRAFTED_CARDS = {
    "history of 1e9 steps": _set("scenario", "history_steps", 10**9),
    "1e308 km/h": _set("scenario", "traffic", "speed_kmh", 1e308),
    "speed as text": _set("scenario", "traffic", "speed_kmh", "fast"),
    "image of 1e6 pixels a side": _set("scenario", "render", "image_size_px", 10**6),
    "n_steps a list": _set("train_config", "n_steps", [128, 128]),
    "1e9 image features": _set("train_config", "image_features", 10**9),
    "1e9 environments": _set("train_config", "n_envs", 10**9),
    "learning rate as text": _set("train_config", "learning_rate", "fast"),
    "scenario a string": _set("scenario", "paper"),
    "no train_config": lambda card: card.pop("train_config"),
    "timesteps a list": _set("timesteps", [64]),
    "timesteps 1e30": _set("timesteps", 1e30),
    "algo a list": _set("algo", ["ppo"]),
    "obs_mode an object": _set("obs_mode", {}),
    "predictor a list": _set("predictor", [1]),
    "predictor file with a folder": _set("predictor", {"file": "../../etc/passwd", "sha256": "0" * 64}),
    "predictor digest not hex": _set("predictor", {"file": "p.pt", "sha256": "zz"}),
    "tensor aliases a list": _set("tensor_aliases", ["a"]),
    "training form a number": _set("training_form", 5),
}


@pytest.mark.parametrize("what", sorted(CRAFTED_CARDS))
def test_a_crafted_card_is_refused_in_one_line_before_any_network_is_built(run_dir: Path, tmp_path: Path,
                                                                            capsys: pytest.CaptureFixture[str],
                                                                            what: str) -> None:
    bad = _recard(run_dir / "policy.safetensors", tmp_path / "bad.safetensors", CRAFTED_CARDS[what])
    for load in (read_meta, load_policy):
        with pytest.raises(ValueError) as exc:
            load(bad)
        assert str(bad) in str(exc.value) and "\n" not in str(exc.value)
    assert eval_main([str(bad), "--episodes", "1", "--no-record"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-eval: error:") and err.count("\n") == 1


def test_a_card_nested_too_deeply_is_one_line(run_dir: Path, tmp_path: Path) -> None:
    card = (run_dir / "policy.card.json").read_text().strip()
    text = card[:-1] + ', "notes": ' + "[" * 5000 + "]" * 5000 + "}"
    bad = _recard(run_dir / "policy.safetensors", tmp_path / "deep.safetensors", text=text)
    with pytest.raises(ValueError, match="nested too deeply"):
        read_meta(bad)


def test_loading_a_card_sized_for_a_huge_rollout_allocates_nothing_for_it(run_dir: Path, tmp_path: Path) -> None:
    """The card's training sizes (rollout, replay buffer) are not what inference needs: loading builds none."""
    big = _recard(run_dir / "policy.safetensors", tmp_path / "big.safetensors",
                  _set("train_config", "n_steps", 100_000))
    loaded = load_policy(big)
    assert loaded.model.rollout_buffer.buffer_size == 1


# -- a policy is not tied to the folder it was trained from ------------------------------------------------------
MY_SCENARIO = {"route_length_m": 150.0, "time_limit_s": 25.0,
               "traffic": {"num_vehicles": 6, "spawn_behind_m": 40.0, "spawn_ahead_m": 80.0}}


def test_a_policy_trained_with_a_relative_scenario_file_loads_from_any_folder(tmp_path: Path, monkeypatch,
                                                                             capsys: pytest.CaptureFixture[str]) -> None:
    from lcsim.config import ScenarioConfig

    proj, elsewhere = tmp_path / "proj", tmp_path / "elsewhere"
    proj.mkdir()
    elsewhere.mkdir()
    (proj / "my.json").write_text(json.dumps(MY_SCENARIO))
    monkeypatch.chdir(proj)
    train_policy(_tiny(scenario="my.json"), "run")
    policy = proj / "run" / "policy.safetensors"
    card = read_meta(policy)
    assert card["train_config"]["scenario"] == "my.json" and card["scenario"]["route_length_m"] == 150.0
    monkeypatch.chdir(elsewhere)
    loaded = load_policy(policy)
    assert loaded.scenario == ScenarioConfig.from_dict(card["scenario"])
    # a file of that name here, with other content, is not read: the card's fields are the scenario
    (elsewhere / "my.json").write_text(json.dumps({**MY_SCENARIO, "route_length_m": 400.0}))
    assert load_policy(policy).scenario.route_length_m == 150.0
    (elsewhere / "my.json").unlink()
    (proj / "my.json").unlink()
    copy = elsewhere / "copy" / "policy.safetensors"
    copy.parent.mkdir()
    copy.write_bytes(policy.read_bytes())
    assert eval_main([str(copy), "--episodes", "1", "--no-record"]) == 0
    capsys.readouterr()
    assert record_main(["--driver", f"policy:{copy}", "--no-images", "--out", str(elsewhere / "rec")]) == 0
    assert len(list((elsewhere / "rec").glob("my_*.mcap"))) == 1


@pytest.fixture(scope="module")
def prediction_run(tmp_path_factory: pytest.TempPathFactory, predictor_path: Path) -> tuple[Path, Path]:
    """A prediction-mode policy trained with a predictor of its own name in a folder of its own."""
    root = tmp_path_factory.mktemp("prediction")
    own = root / "models" / "my-predictor.pt"
    own.parent.mkdir()
    own.write_bytes(predictor_path.read_bytes())
    train_policy(_tiny(obs="prediction"), root / "run", predictor=own)
    return root / "run" / "policy.safetensors", own


def test_a_card_names_its_predictor_by_name_and_digest_and_the_copy_finds_it_beside_it(
        prediction_run: tuple[Path, Path], tmp_path: Path) -> None:
    from lcmodels.fileio import file_sha256

    policy, own = prediction_run
    card = read_meta(policy)
    # its name and digest, and where it lay relative to the policy (a hint): no absolute path of this machine
    assert card["predictor"] == {"file": "my-predictor.pt", "sha256": file_sha256(own),
                                 "path": "../models/my-predictor.pt"}
    run_json = json.loads((policy.parent / "run.json").read_text())
    assert run_json["predictor"]["path"] == str(own.resolve())  # the run's own record keeps where it came from
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / "policy.safetensors").write_bytes(policy.read_bytes())
    (moved / "my-predictor.pt").write_bytes(own.read_bytes())
    loaded = load_policy(moved / "policy.safetensors")
    assert loaded.predictor_path == moved / "my-predictor.pt" and loaded.predictor is not None
    # the experiment / zoo layout: predictor/predictor.pt in a folder above
    (moved / "my-predictor.pt").unlink()
    deeper = moved / "seed0" / "policy.safetensors"
    deeper.parent.mkdir()
    deeper.write_bytes(policy.read_bytes())
    (moved / "predictor").mkdir()
    (moved / "predictor" / "predictor.pt").write_bytes(own.read_bytes())
    assert load_policy(deeper).predictor_path == moved / "predictor" / "predictor.pt"
    # a file of that name with other weights is not taken for it
    (moved / "predictor" / "predictor.pt").unlink()
    (moved / "seed0" / "my-predictor.pt").write_bytes(b"other weights")
    with pytest.raises(ValueError, match=r"my-predictor\.pt, sha256 [0-9a-f]{12}\).*--predictor"):
        load_policy(deeper)


def test_a_card_naming_a_file_that_is_no_predictor_shows_nothing_of_it(prediction_run: tuple[Path, Path],
                                                                      tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from lcmodels.fileio import file_sha256

    policy, _ = prediction_run
    secret = tmp_path / "secret.txt"
    secret.write_text("password=hunter2\n")
    bad = _recard(policy, tmp_path / "bad" / "policy.safetensors", _set("predictor", {
        "file": "secret.txt", "path": str(secret), "sha256": file_sha256(secret)}))
    with pytest.raises(ValueError, match="not a usable predictor file") as exc:
        load_policy(bad)
    assert "hunter2" not in str(exc.value)
    assert eval_main([str(bad), "--episodes", "1", "--no-record"]) == 2
    captured = capsys.readouterr()
    assert "hunter2" not in captured.err + captured.out and captured.err.count("\n") == 1


# -- bad values are refused before anything is written ----------------------------------------------------------
@pytest.mark.parametrize("extra", [
    ["--set", "n_envs=999999"],
    ["--timesteps", str(10**23)],
    ["--set", f"timesteps={10**23}"],
    ["--set", "eval_seed=99999999"],
    ["--set", "eval_episodes=10000000"],
    ["--algo", "dqn", "--set", "buffer_size=1000000000000"],
    ["--set", "n_steps=1000000000"],
    ["--set", "batch_size=1"],
    ["--set", "learning_rate=1e300"],
])
def test_absurd_training_values_are_refused_before_run_json(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                            extra: list[str]) -> None:
    out = tmp_path / "run"
    assert train_policy_main(["--obs", "pure", "--scenario", "tiny", "--out", str(out), "-q", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-train-policy: error:") and err.count("\n") == 1 and not out.exists()


def test_the_root_and_the_home_directory_are_no_run_directory(tmp_path: Path, monkeypatch,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("HOME", str(tmp_path))
    for out in ("/", str(tmp_path)):
        assert train_policy_main(["--obs", "pure", "--scenario", "tiny", "--out", out, "--overwrite", "-q"]) == 2
        err = capsys.readouterr().err
        assert ("filesystem root" in err or "home directory" in err) and err.count("\n") == 1
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("state", [
    [1, 2],
    {"timesteps": "64", "wall_s": 1.0, "episodes_total": 1, "weights": "step-64.safetensors",
     "optimizer": "step-64.optim.pt"},
    {"timesteps": 64, "wall_s": [1.0], "episodes_total": 1, "weights": "step-64.safetensors",
     "optimizer": "step-64.optim.pt"},
    {"timesteps": 10**30, "wall_s": 1.0, "episodes_total": 1, "weights": "step-64.safetensors",
     "optimizer": "step-64.optim.pt"},
    {"timesteps": 64, "wall_s": 1.0, "episodes_total": -1, "weights": "step-64.safetensors",
     "optimizer": "step-64.optim.pt"},
    {"timesteps": 64, "wall_s": 1.0, "episodes_total": 1, "weights": "step-64.safetensors",
     "optimizer": "step-64.optim.pt", "n_updates": None},
])
def test_a_resume_record_of_the_wrong_types_is_corrupt(run_dir: Path, tmp_path: Path, state) -> None:
    import shutil

    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    (out / "checkpoints" / "latest.json").write_text(json.dumps(state))
    with pytest.raises(ValueError, match=r"checkpoints/latest\.json is corrupt"):
        train_policy(_tiny(timesteps=128), out)


def relabelled(src: Path, dest: Path, dtype: str = "I32") -> tuple[Path, str]:
    """A copy of the safetensors file ``src`` whose first float tensor's header says ``dtype`` (the same size
    per element: the bytes load, as numbers of another kind); and that tensor's name."""
    data = src.read_bytes()
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + n])
    name = next(k for k, v in sorted(header.items()) if k != "__metadata__" and v["dtype"] == "F32")
    header[name]["dtype"] = dtype
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (n - len(text))  # the header keeps its length: the tensors' offsets stay right
    assert len(text) == n
    dest.write_bytes(data[:8] + text + data[8 + n :])
    return dest, name


def test_a_tensor_relabelled_to_another_dtype_is_refused_not_cast(run_dir: Path, tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    bad, name = relabelled(run_dir / "policy.safetensors", tmp_path / "relabelled.safetensors")
    with pytest.raises(ValueError, match=rf"tensor {name} is stored as torch.int32, the network holds torch.float32"):
        load_policy(bad)
    assert eval_main([str(bad), "--episodes", "1", "--no-record"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-eval: error:") and "torch.int32" in err and err.count("\n") == 1


@pytest.mark.parametrize("content", ["strings", "objects", "floats", "two_d", "npz", "random", "truncated"])
def test_a_bad_train_episode_seeds_file_beside_a_policy_is_one_line(run_dir: Path, tmp_path: Path, content: str,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    from lcmodels.fileio import TRAIN_SEEDS_FILE, read_train_seeds

    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    seeds = out / TRAIN_SEEDS_FILE
    good = read_train_seeds(out)
    assert good is not None and good.dtype == np.int64 and len(good)
    if content == "strings":
        np.save(seeds, np.array(["1", "22"]))
    elif content == "objects":
        np.save(seeds, np.array([1, "x"], dtype=object), allow_pickle=True)
    elif content == "floats":
        np.save(seeds, good.astype(np.float64))
    elif content == "two_d":
        np.save(seeds, good.reshape(1, -1))
    elif content == "npz":
        with open(seeds, "wb") as fh:
            np.savez(fh, seeds=good)
    elif content == "random":
        seeds.write_bytes(np.random.default_rng(0).bytes(256))
    else:
        seeds.write_bytes(seeds.read_bytes()[:-4])
    with pytest.raises(ValueError, match=TRAIN_SEEDS_FILE):
        read_train_seeds(out)
    assert eval_main([str(out / "policy.safetensors"), "--episodes", "1", "--no-record"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lc-eval: error:") and TRAIN_SEEDS_FILE in err and err.count("\n") == 1, err
    if content == "strings":  # a run resumed beside it refuses too
        with pytest.raises(ValueError, match=TRAIN_SEEDS_FILE):
            train_policy(_tiny(timesteps=128), out)
