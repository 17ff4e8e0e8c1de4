"""The model zoo: trained policies and the predictor they read, shipped in the repository (``zoo/``).

Each entry is a directory ``zoo/<name>/`` holding ``policy.safetensors`` (weights and the policy's card,
nothing that runs when loaded), ``policy.card.json`` and ``zoo.json`` (the recipe and commit it was trained
with, its training time and its held-out figures); ``zoo/predictor/predictor.pt`` is the predictor the
prediction and hybrid policies were trained with. ``zoo:NAME`` names an entry wherever a policy path is taken
(``lc-eval zoo:hybrid-ppo``, ``lc-record --driver zoo:hybrid-ppo``, ``lc-view``). ``LC_ZOO`` points elsewhere.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lckit.fileio import UnsafePathError, check_inside
from lcmodels.fileio import POLICY_FILE, file_sha256, read_json

ZOO_PREFIX = "zoo:"
ENTRY_CARD = "zoo.json"
PREDICTOR_DIR = "predictor"
ENTRY_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,99}$")
"""An entry's name: one word of letters, digits and ``._+-`` (no path, no ``..``), the name of its folder."""


CHECKOUT_ZOO = Path(__file__).resolve().parents[1] / "zoo"
"""``zoo/`` beside the package: the zoo a source checkout ships."""


def zoo_dir() -> Path:
    """``$LC_ZOO``, else :data:`CHECKOUT_ZOO`."""
    return Path(os.environ.get("LC_ZOO") or CHECKOUT_ZOO)


@dataclass(frozen=True)
class ZooEntry:
    name: str
    policy: Path
    predictor: Path | None
    """The zoo's predictor when the policy reads predictions, else None."""
    card: dict[str, Any]

    @property
    def sha256(self) -> str:
        return file_sha256(self.policy)

    @property
    def weights_sha256(self) -> str:
        return weights_sha256(self.policy)


def weights_sha256(policy: str | os.PathLike[str]) -> str:
    """SHA-256 of a ``policy.safetensors`` file's tensors alone (names, dtypes, shapes, bytes, in name order):
    the same for a trained policy and its zoo copy, whose header card differs."""
    import hashlib

    import torch
    from safetensors import safe_open

    h = hashlib.sha256()
    with safe_open(str(policy), framework="pt") as f:
        for k in sorted(f.keys()):
            t = f.get_tensor(k)
            h.update(f"{k}|{t.dtype}|{tuple(t.shape)}|".encode())
            h.update(t.contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def zoo_entries() -> list[ZooEntry]:
    """Every entry of the zoo, by name (none when there is no zoo)."""
    root = zoo_dir()
    if not root.is_dir():
        return []
    return [zoo_entry(p.name) for p in sorted(root.iterdir()) if _is_entry(p)]


def _is_entry(folder: Path) -> bool:
    return bool(ENTRY_NAME.match(folder.name)) and (folder / POLICY_FILE).is_file()


def zoo_entry(name: str) -> ZooEntry:
    """The entry ``name`` (``zoo:`` prefix optional). ``ValueError`` naming the entries there are; a name that is
    no entry's (:data:`ENTRY_NAME`: a path, ``..``) or an entry folder that leads out of the zoo is refused."""
    name = name.removeprefix(ZOO_PREFIX)
    root = zoo_dir()
    path = root / name / POLICY_FILE
    if not ENTRY_NAME.match(name) or not path.is_file():
        have = sorted(p.name for p in root.iterdir() if _is_entry(p)) if root.is_dir() else []
        raise ValueError(f"no zoo policy {name!r} in {root}; the zoo has: {', '.join(have) or 'nothing'}")
    try:
        check_inside(path, root, f"zoo:{name}")
    except UnsafePathError as exc:
        raise ValueError(str(exc)) from None
    card = read_json(root / name / ENTRY_CARD) or {}
    meta = read_json(root / name / "policy.card.json") or {}
    predictor = root / PREDICTOR_DIR / "predictor.pt"
    needs = str(meta.get("obs_mode", "")) in ("prediction", "hybrid")
    return ZooEntry(name, path, predictor if needs and predictor.is_file() else None, card)


def publish_entry(policy: str | os.PathLike[str], name: str, *, predictor: str | os.PathLike[str] | None,
                  card: dict[str, Any], root: str | os.PathLike[str] | None = None,
                  overwrite: bool = False) -> ZooEntry:  # fmt: skip
    """Copy a trained ``policy.safetensors`` into the zoo as entry ``name`` with the zoo card ``card`` (recipe,
    commit, training time, held-out figures), and ``predictor`` (the one it reads, if any) as the zoo's
    predictor. The policy's own card then names the predictor relative to itself. ``ValueError`` for an entry
    that exists (unless ``overwrite``) or a predictor other than the one the zoo holds already."""
    import json

    from safetensors import safe_open
    from safetensors.torch import save as tensors_bytes

    from lckit.fileio import write_file
    from lcmodels.fileio import write_json
    from lcmodels.policy.checkpoint import CARD_KEY, card_path

    root = Path(root) if root is not None else zoo_dir()
    if not ENTRY_NAME.match(name) or name == PREDICTOR_DIR:
        raise ValueError(f"zoo entry name {name!r} is not allowed (one word of letters, digits and ._+-)")
    dest = root / name
    if (dest / POLICY_FILE).exists() and not overwrite:
        raise ValueError(f"{dest / POLICY_FILE} exists; pass --overwrite to replace it")
    with safe_open(str(policy), framework="pt") as f:
        meta = json.loads((f.metadata() or {})[CARD_KEY])
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    if predictor is not None:
        pred_dest = root / PREDICTOR_DIR / "predictor.pt"
        sha = file_sha256(predictor)
        if pred_dest.is_file() and file_sha256(pred_dest) != sha and not overwrite:
            raise ValueError(f"the zoo's predictor {pred_dest} differs from {predictor}; the zoo holds one predictor")
        if (meta.get("predictor") or {}).get("sha256") != sha:
            raise ValueError(f"{policy} was not trained with {predictor}")
        if not pred_dest.is_file() or file_sha256(pred_dest) != sha:
            write_file(pred_dest, Path(predictor).read_bytes(), root=root)
        meta["predictor"] = {**meta["predictor"], "path": f"../{PREDICTOR_DIR}/predictor.pt"}
    text = json.dumps(meta, sort_keys=True)
    write_file(dest / POLICY_FILE, lambda f: f.write(tensors_bytes(tensors, metadata={CARD_KEY: text})), root=root)
    write_json(card_path(dest / POLICY_FILE), meta, root=root)
    write_json(dest / ENTRY_CARD, {"name": name, **card}, root=root)
    return ZooEntry(name, dest / POLICY_FILE, root / PREDICTOR_DIR / "predictor.pt" if predictor else None, card)


def follower_mismatches(entries: list[ZooEntry] | None = None) -> list[str]:
    """One line per zoo entry whose safety-layer figure was measured following a policy the zoo does not ship
    as that recipe's entry (the figure would not hold for the shipped pair); empty when the zoo is consistent."""
    entries = zoo_entries() if entries is None else entries
    by_name = {e.name: e for e in entries}
    bad = []
    for e in entries:
        follow = (e.card.get("safety_layer") or {}).get("follow")
        if not follow:
            continue
        shipped = by_name.get(follow["recipe"])
        if shipped is None or shipped.weights_sha256 != follow["weights_sha256"]:
            bad.append(f"zoo:{e.name}'s safety layer was measured following {follow['recipe']} training seed "
                       f"{follow['training_seed']}, which the zoo does not ship as zoo:{follow['recipe']}")
    return bad


__all__ = ["CHECKOUT_ZOO", "ENTRY_CARD", "ZOO_PREFIX", "ZooEntry", "follower_mismatches", "publish_entry",
           "weights_sha256", "zoo_dir", "zoo_entries", "zoo_entry"]
