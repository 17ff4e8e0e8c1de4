"""Policy files that are data: weights as tensors (safetensors) plus a JSON card, never pickles.

A policy is one ``.safetensors`` file: the tensors of the policy network and, in the file's header, the
card (``lc_card``, plain JSON): format and version, algorithm, observation mode, image network, the full
scenario config, the predictor's file name and SHA-256, the training config and step count. A copy of the
card is written beside it (``<stem>.card.json``) for people; loading reads only the file itself.

:func:`load_policy` reads the card before any weights, refuses a policy whose observation mode,
predictor or scenario differ from what the caller asks for (saying what differs), then rebuilds the
network from the card and fills it with the tensors: nothing in the file can run code.

stable-baselines3's own ``.zip`` (what this project wrote before) unpickles objects when loaded, so any
code its author put there runs: nothing here loads one. :func:`read_meta` refuses it in one line that names
``tools/convert_policy.py``, the one place that reads such a file (behind its ``--trust-pickle``) and turns it
into a ``.safetensors`` policy once.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file
from safetensors.torch import save as tensors_bytes
from stable_baselines3.common.base_class import BaseAlgorithm

from lckit.fileio import loads_json, write_file
from lcmodels.fileio import check_dtypes, file_sha256, write_json
from lcmodels.policy.network import ALGOS
from lcmodels.predictor.inference import Predictor
from lcsim.config import ScenarioConfig

META_FORMAT = "lc-toolkit/policy"
META_VERSION = 2
"""2: safetensors with the card in the header (1 was a stable-baselines3 ``.zip``: tools/convert_policy.py)."""
CARD_KEY = "lc_card"
CONVERT_COMMAND = "python tools/convert_policy.py OLD.zip NEW.safetensors --trust-pickle"
"""What turns a legacy stable-baselines3 ``.zip`` policy into a policy file, once, for a file one trusts."""


def legacy_refusal(path: str | os.PathLike[str]) -> str:
    """The one line that refuses the legacy ``.zip`` ``path`` and names the command that converts it."""
    return (f"{path} is a legacy stable-baselines3 .zip, which no command loads (loading one runs whatever code "
            f"is stored in it); if you trust where it came from, convert it once: {CONVERT_COMMAND}")


def card_path(path: str | os.PathLike[str]) -> Path:
    """Where the human-readable copy of a policy file's card lives (``policy.card.json``)."""
    path = Path(path)
    return path.with_name(path.stem + ".card.json")


def save_policy(model: BaseAlgorithm, path: str | os.PathLike[str], meta: dict[str, Any], *,
                state: dict[str, torch.Tensor] | None = None) -> Path:  # fmt: skip
    """Save ``model``'s policy network (``state``: these tensors in place of its own) with the card ``meta`` to
    ``path`` (a ``.safetensors``), atomically (``.partial`` then rename), and the card's copy beside it. Returns
    ``path``. ``OSError`` when the file cannot be written (a full disk): no ``.partial`` stays, the file there is
    as it was."""
    path = Path(path)
    card = {**{k: v for k, v in meta.items() if k not in ("format", "version", "tensor_aliases")},
            "format": META_FORMAT, "version": META_VERSION}
    tensors, aliases = _unique_tensors(model.policy.state_dict() if state is None else state)
    if aliases:
        card["tensor_aliases"] = aliases
    # One metadata entry: safetensors writes the metadata map in no fixed order, so one key keeps the bytes
    # of the same policy the same.
    text = json.dumps(card, sort_keys=True)
    write_file(path, lambda f: f.write(tensors_bytes(tensors, metadata={CARD_KEY: text})), errors=(SafetensorError,))
    write_json(card_path(path), card)
    return path


def _unique_tensors(state: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """The state dict with every tensor stored once (modules a policy shares, like its features extractor,
    appear under several names), and the other names of each: ``{alias: name kept}``, sorted."""
    kept: dict[tuple[int, int, tuple[int, ...], tuple[int, ...], torch.dtype], str] = {}
    tensors: dict[str, torch.Tensor] = {}
    aliases: dict[str, str] = {}
    for name in sorted(state):
        t = state[name].detach().cpu()
        key = (t.untyped_storage().data_ptr(), t.storage_offset(), tuple(t.shape), tuple(t.stride()), t.dtype)
        if key in kept:
            aliases[name] = kept[key]
        else:
            kept[key] = name
            tensors[name] = t.contiguous()
    return tensors, aliases


def read_meta(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The card of a policy file, read without loading any weights.

    ``ValueError`` for a missing, truncated, corrupt or foreign file, and for a legacy stable-baselines3 ``.zip``
    (:func:`legacy_refusal`: it names the command that converts one).
    """
    path = Path(path)
    if not path.is_file():
        what = "is a directory" if path.is_dir() else "does not exist"
        raise ValueError(f"policy file {path} {what}")
    if zipfile.is_zipfile(path):
        raise ValueError(legacy_refusal(path))
    try:
        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
    except (SafetensorError, OSError, ValueError) as exc:
        size = path.stat().st_size
        raise ValueError(f"{path} is not a readable policy file ({size} bytes; truncated, corrupt or not a "
                         f".safetensors policy): {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
                         ) from None
    if CARD_KEY not in header:
        raise ValueError(f"{path} is a safetensors file but not an lc-toolkit policy (no {CARD_KEY} card)")
    try:
        meta = loads_json(header[CARD_KEY])
    except ValueError as exc:
        raise ValueError(f"{path}: its policy card is not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != META_FORMAT:
        raise ValueError(f"{path}: its card is not an lc-toolkit policy card")
    if meta.get("version") != META_VERSION:
        raise ValueError(f"{path}: unsupported policy file version {str(meta.get('version'))[:40]!r}")
    problem = card_problem(meta)
    if problem:
        raise ValueError(f"{path}: its policy card is unusable: {problem}")
    return meta


_SHA256 = re.compile(r"[0-9a-f]{64}")
MAX_CARD_TIMESTEPS = 10**12
"""The largest step count a card may state (a run's is at most ``PolicyConfig``'s bound plus a rollout)."""


def _plain_name(value: Any) -> bool:
    """Whether ``value`` is a file name without a folder (what a card may name beside the policy)."""
    return (isinstance(value, str) and 0 < len(value) <= 255 and not {"/", "\\", "\0"} & set(value)
            and value not in (".", ".."))


def card_problem(meta: dict[str, Any]) -> str:
    """What makes a policy card unusable (``""`` when nothing does): the schema of every field a loader reads,
    checked before any network is built. The plain fields as :func:`card_fields_problem` checks them;
    ``scenario`` a :class:`~lcsim.config.ScenarioConfig` (every field's type and plausible range, ``from_dict``);
    ``train_config`` a :class:`~lcmodels.policy.config.PolicyConfig` validated against that scenario
    (``from_card``: the scenario file it names is not read)."""
    from lcmodels.policy.config import PolicyConfig

    problem = card_fields_problem(meta)
    if problem:
        return problem
    try:
        scenario = ScenarioConfig.from_dict(meta.get("scenario"))
    except ValueError as exc:
        return f"scenario: {_short(exc)}"
    try:
        PolicyConfig.from_card(meta.get("train_config"), scenario)
    except ValueError as exc:
        return f"train_config: {_short(exc)}"
    return ""


def card_fields_problem(meta: dict[str, Any]) -> str:
    """What makes the plain fields of a policy card unusable (``""`` when nothing does): ``algo`` and
    ``obs_mode`` known names, ``image_net`` one too when given; ``predictor`` none or a file name with a SHA-256;
    ``timesteps`` a count; ``tensor_aliases`` names; ``scenario_name`` and ``converted_from`` strings."""
    from lcmodels.policy.names import ALGORITHMS, IMAGE_FEATURES, IMAGE_NETS, OBS_MODES

    if meta.get("algo") not in ALGORITHMS:
        return f"algo must be one of {', '.join(ALGORITHMS)}, got {str(meta.get('algo'))[:40]!r}"
    if meta.get("obs_mode") not in OBS_MODES:
        return f"obs_mode must be one of {', '.join(OBS_MODES)}, got {str(meta.get('obs_mode'))[:40]!r}"
    if "image_net" in meta and meta["image_net"] not in IMAGE_NETS:
        return f"image_net must be one of {', '.join(IMAGE_NETS)}, got {str(meta['image_net'])[:40]!r}"
    for key in ("scenario_name", "converted_from"):
        if key in meta and not (isinstance(meta[key], str) and len(meta[key]) <= 4096):
            return f"{key} must be a string, got {str(meta[key])[:40]!r}"
    steps = meta.get("timesteps", 0)
    if not isinstance(steps, int) or isinstance(steps, bool) or not 0 <= steps <= MAX_CARD_TIMESTEPS:
        return f"timesteps must be an integer in [0, {MAX_CARD_TIMESTEPS}], got {str(steps)[:40]!r}"
    if meta.get("training_form") not in (None, IMAGE_FEATURES):
        return f"training_form must be {IMAGE_FEATURES!r}, got {str(meta['training_form'])[:40]!r}"
    aliases = meta.get("tensor_aliases", {})
    if not isinstance(aliases, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in aliases.items()):
        return "tensor_aliases must map tensor names to tensor names"
    pred = meta.get("predictor")
    if pred is not None:
        if not isinstance(pred, dict):
            return f"predictor must be an object or null, got {type(pred).__name__}"
        if "file" in pred and not _plain_name(pred["file"]):
            return f"predictor.file must be a file name, got {str(pred['file'])[:40]!r}"
        if pred.get("sha256") is not None and not (isinstance(pred["sha256"], str) and _SHA256.fullmatch(pred["sha256"])):
            return "predictor.sha256 must be 64 hexadecimal digits"
        if "path" in pred and not (isinstance(pred["path"], str) and 0 < len(pred["path"]) <= 4096):
            return "predictor.path must be a path"
    return ""


def _short(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:300]


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


@dataclass
class LoadedPolicy:
    model: BaseAlgorithm
    meta: dict[str, Any]
    predictor: Predictor | None
    scenario: ScenarioConfig
    predictor_path: Path | None = None
    """The file ``predictor`` was loaded from."""

    @property
    def obs_mode(self) -> str:
        return str(self.meta["obs_mode"])

    @property
    def algo(self) -> str:
        return str(self.meta["algo"])


def load_weights(model: BaseAlgorithm, path: str | os.PathLike[str], device: str = "cpu",
                 meta: dict[str, Any] | None = None) -> None:
    """Fill ``model``'s policy network with the tensors of the policy file ``path`` (no code runs);
    ``meta``: its card when the caller has read it. ``ValueError`` when they do not fit the network exactly."""
    try:
        state = load_file(str(path), device=device)
        aliases = (meta if meta is not None else read_meta(path)).get("tensor_aliases")
        if aliases is None:  # a file written by safetensors' save_model names its shared tensors in the header
            with safe_open(str(path), framework="pt") as f:
                aliases = {k: v for k, v in (f.metadata() or {}).items() if k != CARD_KEY and v in state}
        for alias, name in aliases.items():
            state[alias] = state[name]
        check_dtypes(state, model.policy.state_dict(), str(path))
        model.policy.load_state_dict(state, strict=True)
    except (RuntimeError, SafetensorError, OSError, KeyError) as exc:
        detail = " ".join(str(exc).split())[:200]
        raise ValueError(f"{path}: its tensors do not fit the network its card describes: {detail}") from None


def policy_model(meta: dict[str, Any], *, future_steps: int = 10, device: str = "cpu") -> BaseAlgorithm:
    """A fresh network of the architecture a policy card describes (its training config, scenario and
    observation mode), ready for :func:`load_weights`. ``future_steps``: the predictor's horizon."""
    from lcmodels.policy.config import PolicyConfig
    from lcmodels.policy.network import build_model
    from lcmodels.policy.obs import policy_observation_space

    try:
        scenario = ScenarioConfig.from_dict(meta["scenario"])
        cfg = PolicyConfig.from_card(meta["train_config"], scenario)  # the card's scenario, not the file it names
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"the policy card's training config or scenario is unusable: {_short(exc)}") from None
    space = policy_observation_space(scenario, str(meta["obs_mode"]), future_steps,
                                     cfg.image_features if meta.get("training_form") else None)
    return build_model(cfg, None, None, device, observation_space=space)


PREDICTOR_FILE = Path("predictor") / "predictor.pt"
"""Where an experiment directory (and the zoo) keeps its predictor."""


def find_predictor(meta: dict[str, Any], policy: str | os.PathLike[str]) -> Path | None:
    """The predictor a policy's card names, found by its SHA-256 (the card carries the digest, so a policy copied
    anywhere finds the predictor copied with it): the card's ``path`` when the file there has that digest (a path
    relative to the policy file, as in a zoo entry; an absolute one, from an older card, only as a hint that is
    never required), else, in the policy's folder and each folder above it, a file of the card's name, a
    ``predictor.pt``, or a ``predictor/predictor.pt`` (an experiment's and the zoo's layout) with that digest. A
    card without a SHA-256 (older files) gets its relative ``path`` inside the policy's folder only. ``None``
    when none fits."""
    info = meta.get("predictor") or {}
    if not isinstance(info, dict):
        return None
    stored, sha, name = info.get("path"), info.get("sha256"), info.get("file")
    policy = Path(policy)
    if sha is None:  # nothing to check a file against: only a relative path that stays inside the policy's folder
        if isinstance(stored, str) and stored and not Path(stored).is_absolute() and ".." not in Path(stored).parts:
            p = policy.parent / stored
            return p if p.is_file() else None
        return None
    candidates: list[Path] = []
    if isinstance(stored, str) and stored:
        candidates.append(Path(stored) if Path(stored).is_absolute() else policy.parent / stored)
    names = [n for n in (name, "predictor.pt") if _plain_name(n)]
    for folder in policy.resolve().parents:
        candidates += [folder / n for n in dict.fromkeys(names)] + [folder / PREDICTOR_FILE]
    seen: set[Path] = set()
    for candidate in candidates:
        try:
            key = candidate.resolve()
            if key in seen or not candidate.is_file():
                continue
            seen.add(key)
            if file_sha256(candidate) == sha:
                return candidate
        except OSError:  # unreadable: not it
            continue
    return None


def load_policy(path: str | os.PathLike[str], *, obs_mode: str | None = None,
                predictor: str | os.PathLike[str] | None = None, scenario: ScenarioConfig | None = None,
                device: str = "cpu") -> LoadedPolicy:
    """Load a policy file and the predictor it was trained with, checking compatibility.

    Args:
        path: the ``.safetensors`` policy.
        obs_mode, scenario: when given, must match the policy's.
        predictor: the predictor checkpoint to use; by default the one recorded in the card (its path,
            checked by SHA-256). Must be the same file content the policy was trained with.

    Raises:
        ValueError: unreadable file (a legacy ``.zip`` too: :func:`legacy_refusal`), or an incompatibility (the
            message lists every difference).
    """
    path = Path(path)

    def network(meta: dict[str, Any], future_steps: int) -> BaseAlgorithm:
        model = policy_model(meta, future_steps=future_steps, device=device)
        load_weights(model, path, device, meta)
        model.num_timesteps = meta.get("timesteps", 0)
        return model

    return open_policy(path, read_meta(path), network, obs_mode=obs_mode, predictor=predictor, scenario=scenario)


def open_policy(path: Path, meta: dict[str, Any], network: Callable[[dict[str, Any], int], BaseAlgorithm], *,
                obs_mode: str | None = None, predictor: str | os.PathLike[str] | None = None,
                scenario: ScenarioConfig | None = None) -> LoadedPolicy:  # fmt: skip
    """The policy whose card ``meta`` was read from ``path``, after the checks of :func:`load_policy` (a
    training checkpoint refused, the algorithm known, the predictor found and of the card's digest, the mode and
    scenario asked for); ``network(meta, future_steps)`` makes its network with its weights (``future_steps``:
    the predictor's horizon)."""
    from lcmodels.policy.names import needs_predictor

    if meta.get("training_form"):
        raise ValueError(f"{path} is a training checkpoint of a frozen-image run (it sees the image branch's "
                         "features, not the image), for resuming only: use the run's policy file")
    algo = meta.get("algo")
    if algo not in ALGOS:
        raise ValueError(f"{path}: unknown algorithm {algo!r} in the checkpoint")
    sha = None
    pred_path: Path | None = None
    if needs_predictor(str(meta.get("obs_mode"))):
        info = meta.get("predictor") or {}
        named = info.get("file") or (Path(info["path"]).name if info.get("path") else "unknown")
        pred_path = Path(predictor) if predictor is not None else find_predictor(meta, path)
        if pred_path is None or not pred_path.is_file():
            digest = f", sha256 {info['sha256'][:12]}" if info.get("sha256") else ""
            raise ValueError(
                f"{path} needs the predictor it was trained with ({named}{digest}), which is neither beside it nor "
                "in a folder above it; pass its path with --predictor"
            )
        card_sha = (meta.get("predictor") or {}).get("sha256")  # find_predictor took only a file of that hash
        sha = card_sha if predictor is None and card_sha else file_sha256(pred_path)
    problems = compatibility_problems(meta, obs_mode=obs_mode, predictor_sha256=sha, scenario=scenario)
    if problems:
        raise ValueError(f"{path} does not match: " + "; ".join(problems))
    loaded_predictor = None
    if pred_path is not None:
        if predictor is not None:
            loaded_predictor = Predictor.load(pred_path)
        else:  # a file the card named: nothing about its content is shown, only that it is no predictor
            try:
                loaded_predictor = Predictor.load(pred_path)
            except ValueError:
                raise ValueError(f"{path}: the predictor its card names ({pred_path}) is not a usable predictor "
                                 "file; pass the right one with --predictor") from None
    model = network(meta, loaded_predictor.future_steps if loaded_predictor is not None else 10)
    return LoadedPolicy(model, meta, loaded_predictor, ScenarioConfig.from_dict(meta["scenario"]), pred_path)
