"""Structured fuzzing of the files a user is handed: policy cards, predictor configs and resume records
(``checkpoints/latest.json``) with any field replaced by a value of any type or size. Each either loads or is
refused with a one-line ``ValueError``, never another exception, a hang, or an allocation sized by the file.

The loading runs in a child process whose address space is capped (``RLIMIT_AS``) before it imports anything:
a file that makes the loader allocate tens of gigabytes fails the test (a ``MemoryError`` reported back, or
the child's death) instead of taking the machine down.
"""

from __future__ import annotations

import copy
import json
import select
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lcmodels.policy import PolicyConfig, train_policy
from lcmodels.predictor import PredictorConfig, TrajectoryTransformer

MEMORY_LIMIT = 3 << 30
"""The child's address space: torch and stable-baselines3 take about 1 GiB of it once imported."""
EXAMPLE_TIME_LIMIT_S = 60
FUZZ = settings(max_examples=12, deadline=None, print_blob=False, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

_CHILD = f"""
import resource
resource.setrlimit(resource.RLIMIT_AS, ({MEMORY_LIMIT}, {MEMORY_LIMIT}))
import json, sys
from pathlib import Path
import torch
torch.set_num_threads(1)
from lcmodels.policy.checkpoint import load_policy
from lcmodels.policy.train import read_checkpoint_state
from lcmodels.predictor.checkpoint import load_model

LOADERS = {{"policy": load_policy, "predictor": load_model, "resume": lambda p: read_checkpoint_state(Path(p))}}
print(json.dumps(["ready", ""]), flush=True)
for line in sys.stdin:
    kind, path = line.rstrip("\\n").split("\\t")
    try:
        LOADERS[kind](path)
        answer = ["loaded", ""]
    except ValueError as exc:
        answer = ["refused", str(exc)]
    except BaseException as exc:  # what the test is after: anything but a clean refusal
        answer = ["failed", f"{{type(exc).__name__}}: {{exc}}"[:600]]
    print(json.dumps(answer), flush=True)
"""


class Loader:
    """The capped child: one process for a test module, restarted when an example kills it."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen[str] | None = None

    def _start(self) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", _CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        assert self._answer()[0] == "ready"

    def _answer(self) -> list[str]:
        assert self.proc is not None and self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], EXAMPLE_TIME_LIMIT_S)
        if not ready:
            self.close()
            return ["failed", f"still loading after {EXAMPLE_TIME_LIMIT_S} s: a hang"]
        line = self.proc.stdout.readline()
        if not line:
            err = self.proc.stderr.read() if self.proc.stderr else ""
            self.close()
            return ["failed", f"the loader died (exit {self.proc.returncode if self.proc else '?'}): {err[-600:]}"]
        return json.loads(line)

    def load(self, kind: str, path: Path) -> list[str]:
        if self.proc is None or self.proc.poll() is not None:
            self._start()
        assert self.proc is not None and self.proc.stdin is not None
        self.proc.stdin.write(f"{kind}\t{path}\n")
        self.proc.stdin.flush()
        return self._answer()

    def close(self) -> None:
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.kill()
            self.proc.wait()
            self.proc = None


@pytest.fixture(scope="module")
def loader() -> Iterator[Loader]:
    child = Loader()
    yield child
    child.close()


def check(loader: Loader, kind: str, path: Path) -> None:
    outcome, message = loader.load(kind, path)
    assert outcome in ("loaded", "refused"), message
    if outcome == "refused":
        assert message and "\n" not in message.strip(), message


# -- what a crafted file puts in a field ---------------------------------------------------------------------------
leaves = (st.none() | st.booleans() | st.integers(-3, 3) | st.sampled_from([10**9, 10**12, 10**20, 2**63, -(10**15)])
          | st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([1e308, -1e308, 1e-308, 0.5])
          | st.text(max_size=6) | st.sampled_from(["../../etc/passwd", "/etc/passwd", "step-1.safetensors"]))
values = st.recursive(leaves, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                                         max_size=3), max_leaves=5)


def deep(depth: int) -> Any:
    value: Any = []
    for _ in range(depth):
        value = [value]
    return value


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out: list[tuple] = []
    if isinstance(node, dict):
        for k, v in node.items():
            out.append((*prefix, k))
            out += _paths(v, (*prefix, k))
    return out


def mutate(data: st.DataObject, base: dict[str, Any]) -> dict[str, Any]:
    """``base`` with one to three fields replaced by any value, dropped, or added."""
    out = copy.deepcopy(base)
    for _ in range(data.draw(st.integers(1, 3), label="changes")):
        where = data.draw(st.sampled_from(_paths(out) or [("x",)]), label="field")
        node = out
        for k in where[:-1]:
            node = node[k] if isinstance(node, dict) and isinstance(node.get(k), dict) else None
            if node is None:
                break
        if node is None:
            continue
        action = data.draw(st.sampled_from(["replace", "replace", "replace", "drop", "deep"]), label="action")
        if action == "drop":
            node.pop(where[-1], None)
        elif action == "deep":
            node[where[-1]] = deep(data.draw(st.sampled_from([50, 3000]), label="depth"))
        else:
            node[where[-1]] = data.draw(values, label="value")
    return out


def to_json(obj: Any) -> str:
    """JSON text of ``obj`` however deep (``json.dumps`` recurses too): deep lists written by hand."""
    if isinstance(obj, list) and obj and all(isinstance(x, list) for x in obj) and len(obj) == 1:
        depth, node = 0, obj
        while isinstance(node, list) and len(node) == 1 and isinstance(node[0], list):
            depth, node = depth + 1, node[0]
        if depth > 100:
            return "[" * depth + to_json(node) + "]" * depth
    if isinstance(obj, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))}: {to_json(v)}" for k, v in obj.items()) + "}"
    if isinstance(obj, list):
        return "[" + ", ".join(to_json(v) for v in obj) + "]"
    return json.dumps(obj)


# -- policy cards -------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def policy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fuzz-policy") / "run"
    train_policy(PolicyConfig(scenario="tiny", obs="pure", timesteps=32, n_envs=2, n_steps=16, batch_size=32,
                              n_epochs=1, eval_episodes=0), out)
    return out / "policy.safetensors"


@FUZZ
@given(data=st.data())
def test_a_policy_card_with_any_field_changed_loads_or_is_refused(loader: Loader, policy: Path, tmp_path_factory,
                                                                  data: st.DataObject) -> None:
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    with safe_open(str(policy), framework="pt") as f:
        header = dict(f.metadata() or {})
    card = mutate(data, json.loads(header["lc_card"]))
    path = tmp_path_factory.mktemp("card") / "policy.safetensors"
    save_file(load_file(str(policy)), str(path), metadata={**header, "lc_card": to_json(card)})
    check(loader, "policy", path)


# -- predictor files ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def predictor_payload() -> dict[str, Any]:
    torch.manual_seed(0)
    model = TrajectoryTransformer(PredictorConfig(d_model=16, ff_dim=32, num_layers=1))
    return {"format": "lc-toolkit/predictor", "version": 1, "config": model.config.to_json(),
            "state_dict": {k: v.clone() for k, v in model.state_dict().items()}, "extra": "{}"}


@FUZZ
@given(data=st.data())
def test_a_predictor_config_with_any_field_changed_loads_or_is_refused(loader: Loader, predictor_payload,
                                                                       tmp_path_factory, data: st.DataObject) -> None:
    config = mutate(data, json.loads(predictor_payload["config"]))
    payload = {**predictor_payload, "config": to_json(config)}
    if data.draw(st.booleans(), label="outer field too"):
        key = data.draw(st.sampled_from(["format", "version", "config", "extra", "state_dict"]), label="outer")
        payload[key] = data.draw(leaves, label="outer value")
    path = tmp_path_factory.mktemp("pred") / "predictor.pt"
    torch.save(payload, path)
    check(loader, "predictor", path)


def test_a_predictor_sized_for_terabytes_is_refused_under_the_memory_cap(loader: Loader, predictor_payload,
                                                                        tmp_path: Path) -> None:
    for fields in ({"ff_dim": 10**10}, {"d_model": 2**20, "num_heads": 1}, {"num_layers": 10**7},
                   {"history_steps": 10**9}, {"d_model": 4096, "ff_dim": 16384, "num_layers": 64, "num_heads": 64}):
        path = tmp_path / "big.pt"
        torch.save({**predictor_payload, "config": json.dumps({**json.loads(predictor_payload["config"]),
                                                               **fields})}, path)
        outcome, message = loader.load("predictor", path)
        assert outcome == "refused", (fields, message)


# -- resume records -----------------------------------------------------------------------------------------------
RESUME = {"timesteps": 64, "wall_s": 1.5, "episodes_total": 3, "weights": "step-64.safetensors",
          "optimizer": "step-64.optim.pt", "n_updates": 4, "n_calls": 0}


@FUZZ
@given(data=st.data())
def test_a_resume_record_with_any_field_changed_loads_or_is_refused(loader: Loader, tmp_path_factory,
                                                                    data: st.DataObject) -> None:
    state = mutate(data, RESUME)
    path = tmp_path_factory.mktemp("resume") / "latest.json"
    path.write_text(to_json(state))
    outcome, message = loader.load("resume", path)
    assert outcome in ("loaded", "refused"), message
    if outcome == "loaded":  # only this tool's own file names, counts as counts
        for key, suffix in (("weights", ".safetensors"), ("optimizer", ".optim.pt")):
            assert state[key].startswith("step-") and state[key].endswith(suffix) and "/" not in state[key]
        assert all(isinstance(state.get(k, 0), int) and state.get(k, 0) >= 0
                   for k in ("timesteps", "episodes_total", "n_updates", "n_calls"))
    else:
        assert "latest.json is corrupt" in message and "\n" not in message
