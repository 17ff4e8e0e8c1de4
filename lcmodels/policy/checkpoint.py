"""Policy checkpoints: a stable-baselines3 ``.zip`` that also carries what the policy was trained for.

The zip's ``data`` record holds ``lc_meta`` (plain JSON): format and version, algorithm, observation
mode, image network, the full scenario config, the predictor's file name and SHA-256, and the training
config. :func:`load_policy` reads it before loading any weights and refuses a checkpoint whose
observation mode, predictor or scenario differ from what the caller asks for, saying what differs.
SB3 loads the weights with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stable_baselines3 import A2C, DQN, PPO
from stable_baselines3.common.base_class import BaseAlgorithm

from lcmodels.fileio import file_sha256
from lcmodels.predictor.inference import Predictor
from lcsim.config import ScenarioConfig

META_FORMAT = "lc-toolkit/policy"
META_VERSION = 1
ALGOS: dict[str, type[BaseAlgorithm]] = {"ppo": PPO, "a2c": A2C, "dqn": DQN}


def save_policy(model: BaseAlgorithm, path: str | os.PathLike[str], meta: dict[str, Any]) -> Path:
    """Save ``model`` with ``meta`` to ``path`` (a ``.zip``), atomically (``.partial`` then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model.lc_meta = {"format": META_FORMAT, "version": META_VERSION, **meta}  # type: ignore[attr-defined]
    tmp = path.with_name(path.stem + ".partial.zip")
    model.save(tmp, include=["lc_meta"])
    tmp.replace(path)
    return path


def read_meta(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The ``lc_meta`` of a policy checkpoint; ``ValueError`` for a missing, corrupt or foreign file."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"policy checkpoint {path} does not exist")
    try:
        with zipfile.ZipFile(path) as zf:
            data = json.loads(zf.read("data"))
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError, OSError, EOFError) as exc:
        raise ValueError(f"{path} is not a readable policy checkpoint (corrupt or truncated?): {exc}") from exc
    meta = data.get("lc_meta")
    if not isinstance(meta, dict) or meta.get("format") != META_FORMAT:
        raise ValueError(f"{path} is a stable-baselines3 file but not an lc-toolkit policy checkpoint")
    if meta.get("version") != META_VERSION:
        raise ValueError(f"{path}: unsupported policy checkpoint version {meta.get('version')!r}")
    return meta


def _diff(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for k in sorted(set(a) | set(b)):
            out += _diff(a.get(k), b.get(k), f"{prefix}{k}.")
        return out
    if a != b:
        return [f"{prefix.rstrip('.')}: checkpoint {a!r}, requested {b!r}"]
    return []


def scenario_differences(have: dict[str, Any], want: ScenarioConfig,
                         ignore: tuple[str, ...] = ("render_image",)) -> list[str]:
    """Fields in which a stored scenario dict differs from ``want``, ignoring ``ignore`` (by default
    ``render_image``, which the observation mode decides). Fields the stored dict predates count with the
    value they had then (``ScenarioConfig.from_dict``)."""
    with contextlib.suppress(ValueError, TypeError):
        have = ScenarioConfig.from_dict(have).to_dict()
    have = {k: v for k, v in have.items() if k not in ignore}
    return _diff(have, {k: v for k, v in want.to_dict().items() if k not in ignore})


def compatibility_problems(meta: dict[str, Any], *, obs_mode: str | None = None,
                           predictor_sha256: str | None = None,
                           scenario: ScenarioConfig | None = None) -> list[str]:
    """What differs between a checkpoint and the requested mode, predictor and scenario (empty: compatible)."""
    problems: list[str] = []
    if obs_mode is not None and meta.get("obs_mode") != obs_mode:
        problems.append(f"observation mode: checkpoint {meta.get('obs_mode')!r}, requested {obs_mode!r}")
    pred = meta.get("predictor") or {}
    if predictor_sha256 is not None and pred.get("sha256") != predictor_sha256:
        problems.append(
            f"predictor: checkpoint trained with {pred.get('file', 'none')!r} (sha256 "
            f"{str(pred.get('sha256'))[:12]}), requested one has sha256 {predictor_sha256[:12]}"
        )
    if scenario is not None:
        problems += [f"scenario {d}" for d in scenario_differences(meta.get("scenario") or {}, scenario)]
    return problems


# Before commit 4c56e3c the sensor branch with contact features had no Flatten in front of its two
# linear layers, so they were numbered 0 and 2 instead of 1 and 3.
_OLD_CONTACT_LAYER = re.compile(r"(branches\.current\.net\.)([02])\.")


def _load_renamed(model: BaseAlgorithm, path: str | os.PathLike[str], device: str) -> bool:
    """Load the policy parameters of a checkpoint saved before a layer renumbering into ``model`` under
    today's names; False when renaming does not make every parameter fit exactly (the file is refused)."""
    from stable_baselines3.common.save_util import load_from_zip_file

    _, params, _ = load_from_zip_file(path, device=device, load_data=False)
    state = (params or {}).get("policy") or {}
    renamed = {_OLD_CONTACT_LAYER.sub(lambda m: f"{m[1]}{int(m[2]) + 1}.", k): v for k, v in state.items()}
    if renamed.keys() == state.keys() or renamed.keys() != model.policy.state_dict().keys():
        return False
    try:
        model.policy.load_state_dict(renamed, strict=True)
    except RuntimeError:  # a shape does not fit: not that network
        return False
    return True


@dataclass
class LoadedPolicy:
    model: BaseAlgorithm
    meta: dict[str, Any]
    predictor: Predictor | None
    scenario: ScenarioConfig

    @property
    def obs_mode(self) -> str:
        return str(self.meta["obs_mode"])

    @property
    def algo(self) -> str:
        return str(self.meta["algo"])


def load_policy(path: str | os.PathLike[str], *, obs_mode: str | None = None,
                predictor: str | os.PathLike[str] | None = None, scenario: ScenarioConfig | None = None,
                device: str = "cpu") -> LoadedPolicy:
    """Load a policy checkpoint and the predictor it was trained with, checking compatibility.

    Args:
        path: the ``.zip``.
        obs_mode, scenario: when given, must match the checkpoint's.
        predictor: the predictor checkpoint to use; by default the one recorded in the checkpoint
            (its path, checked by SHA-256). Must be the same file content the policy was trained with.

    Raises:
        ValueError: unreadable file or an incompatibility (the message lists every difference).
    """
    from lcmodels.policy.obs import needs_predictor

    meta = read_meta(path)
    if meta.get("training_form"):
        raise ValueError(f"{path} is a training checkpoint of a frozen-image run (it sees the image branch's "
                         "features, not the image), for resuming only: use the run's policy.zip")
    algo = meta.get("algo")
    if algo not in ALGOS:
        raise ValueError(f"{path}: unknown algorithm {algo!r} in the checkpoint")
    sha = None
    pred_path: Path | None = None
    if needs_predictor(str(meta.get("obs_mode"))):
        stored = (meta.get("predictor") or {}).get("path")
        pred_path = Path(predictor) if predictor is not None else (Path(stored) if stored else None)
        if pred_path is None or not pred_path.is_file():
            raise ValueError(
                f"{path} needs the predictor it was trained with ({stored or 'unknown'}), which is not there; "
                "pass its path with --predictor"
            )
        sha = file_sha256(pred_path)
    problems = compatibility_problems(meta, obs_mode=obs_mode, predictor_sha256=sha, scenario=scenario)
    if problems:
        raise ValueError(f"{path} does not match: " + "; ".join(problems))
    loaded_predictor = Predictor.load(pred_path) if pred_path is not None else None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            model = ALGOS[algo].load(path, device=device)
        except Exception as exc:  # SB3 raises many types for damaged archives
            raise ValueError(f"{path}: could not load the weights (corrupt?): {exc}") from exc
    for w in caught:
        # SB3 loads weights whose names do not fit the network "without exact match", leaving those
        # layers at their random start: a policy that silently is not the one saved.
        if "exact_match" in str(w.message):
            if _load_renamed(model, path, device):
                continue
            detail = next((line.strip() for line in str(w.message).splitlines() if "Missing key" in line), "")
            raise ValueError(f"{path}: its weights do not fit this version's network (saved before a change to "
                             f"it?): {detail[:200]}")
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return LoadedPolicy(model, meta, loaded_predictor, ScenarioConfig.from_dict(meta["scenario"]))
