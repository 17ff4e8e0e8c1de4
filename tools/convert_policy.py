"""Convert a legacy policy (a stable-baselines3 ``.zip`` written by lc-toolkit before policies became
data) into the ``.safetensors`` policy format, once, for a file you trust.

Loading a ``.zip`` unpickles objects stored in it, which runs whatever code its author put there. This script is
the one place of the project that reads such a file, and only with ``--trust-pickle``; every command refuses one
and names this script. The converted file holds only tensors and a JSON card, and acts exactly as the original
(same tensors).

    python tools/convert_policy.py runs/old/policy.zip runs/old/policy.safetensors --trust-pickle
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import warnings
import zipfile
from pathlib import Path
from typing import Any

from lckit.fileio import loads_json
from lcmodels.policy.checkpoint import (
    META_FORMAT,
    LoadedPolicy,
    card_fields_problem,
    card_path,
    open_policy,
    save_policy,
)
from lcsim.config import ScenarioConfig

LEGACY_VERSION = 1
"""The card version of a legacy ``.zip`` (in its ``data`` record, ``lc_meta``)."""
LEGACY_DATA_MAX_BYTES = 64 << 20
"""The largest JSON record of a stable-baselines3 ``.zip`` read (its ``data``: a few hundred KiB)."""
TRUST_HINT = ("loading a stable-baselines3 .zip runs whatever code its author put in it (pickle): pass "
              "--trust-pickle only if you trust where it came from")

# Before commit 4c56e3c the sensor branch with contact features had no Flatten in front of its two
# linear layers, so they were numbered 0 and 2 instead of 1 and 3 (legacy .zip files only).
_OLD_CONTACT_LAYER = re.compile(r"(branches\.current\.net\.)([02])\.")


def read_legacy_meta(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The card (``lc_meta``) of a legacy ``.zip``, read from its JSON ``data`` record (nothing unpickled).
    ``ValueError`` for a missing, corrupt or foreign file, or an unusable card."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"policy file {path} {'is a directory' if path.is_dir() else 'does not exist'}")
    try:
        with zipfile.ZipFile(path) as zf:
            info = zf.getinfo("data")
            if info.file_size > LEGACY_DATA_MAX_BYTES:
                raise ValueError(f"its data record is {info.file_size} bytes")
            data = loads_json(zf.read("data"))
    except (zipfile.BadZipFile, KeyError, ValueError, OSError, EOFError) as exc:
        raise ValueError(f"{path} is not a readable legacy policy (corrupt or truncated?): {exc}") from None
    meta = data.get("lc_meta") if isinstance(data, dict) else None
    if not isinstance(meta, dict) or meta.get("format") != META_FORMAT:
        raise ValueError(f"{path} is a stable-baselines3 file but not an lc-toolkit policy checkpoint")
    if meta.get("version") != LEGACY_VERSION:
        raise ValueError(f"{path}: unsupported policy checkpoint version {str(meta.get('version'))[:40]!r}")
    problem = card_fields_problem(meta)
    if not problem and "scenario" in meta:  # (the oldest records predate it)
        try:
            ScenarioConfig.from_dict(meta["scenario"])
        except ValueError as exc:
            problem = f"scenario: {' '.join(str(exc).split())[:300]}"
    if not problem and not isinstance(meta.get("train_config", {}), dict):
        problem = "train_config must be an object"  # (stable-baselines3 rebuilds the network from its own record)
    if problem:
        raise ValueError(f"{path}: its policy record is unusable: {problem}")
    return meta


def _load_renamed(model: Any, path: Path, device: str) -> bool:
    """Load the policy parameters of a legacy checkpoint saved before a layer renumbering into ``model``
    under today's names; False when renaming does not make every parameter fit exactly (refused)."""
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


def _unpickle(path: Path, algo: str, device: str) -> Any:
    """stable-baselines3's own load of a legacy ``.zip`` (it unpickles: trusted files only)."""
    from lcmodels.policy.network import ALGOS

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
    return model


def load_legacy_policy(path: str | os.PathLike[str], *, predictor: str | os.PathLike[str] | None = None,
                       device: str = "cpu", trust_pickle: bool = False) -> LoadedPolicy:  # fmt: skip
    """A legacy ``.zip`` policy with its predictor, checked as a policy file is (the predictor's digest). Loading
    it runs code stored in it: ``trust_pickle`` must say that its source is trusted (``ValueError`` otherwise,
    before anything is unpickled)."""
    path = Path(path)
    meta = read_legacy_meta(path)
    if not trust_pickle:
        raise ValueError(f"{path} refused: {TRUST_HINT}")
    return open_policy(path, meta, lambda m, _future: _unpickle(path, str(m["algo"]), device), predictor=predictor)


def convert_legacy_policy(src: str | os.PathLike[str], dest: str | os.PathLike[str], *,
                          predictor: str | os.PathLike[str] | None = None, trust_pickle: bool = False,
                          overwrite: bool = False) -> Path:  # fmt: skip
    """Convert a legacy stable-baselines3 ``.zip`` policy into a ``.safetensors`` policy with the same tensors.

    Loading ``src`` runs code stored in it: ``trust_pickle`` must say that its source is trusted.
    ``ValueError`` for a refused or unreadable ``src``, or an existing ``dest`` without ``overwrite``.
    """
    dest = Path(dest)
    if dest.suffix != ".safetensors":
        raise ValueError(f"{dest}: the file name must end in .safetensors")
    if dest.exists() and not overwrite:
        raise ValueError(f"{dest} already exists; pass --overwrite or choose another name")
    loaded = load_legacy_policy(src, predictor=predictor, trust_pickle=trust_pickle)
    meta = {k: v for k, v in loaded.meta.items() if k not in ("format", "version")}
    if "train_config" not in meta:
        raise ValueError(f"{src} predates stored training configs: no card can describe its network")
    meta.setdefault("timesteps", int(loaded.model.num_timesteps))
    meta["converted_from"] = Path(src).name
    return save_policy(loaded.model, dest, meta)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="convert_policy.py", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src", type=Path, help="the legacy policy .zip")
    p.add_argument("dest", type=Path, help="the .safetensors policy to write")
    p.add_argument("--predictor", type=Path, default=None,
                   help="the predictor the policy was trained with, when it is no longer where the file says")
    p.add_argument("--trust-pickle", action="store_true",
                   help="required: say that you trust the file's source (loading it runs code stored in it)")
    p.add_argument("--overwrite", action="store_true", help="replace DEST when it exists")
    args = p.parse_args(argv)
    try:
        dest = convert_legacy_policy(args.src, args.dest, predictor=args.predictor, trust_pickle=args.trust_pickle,
                                     overwrite=args.overwrite)
    except (ValueError, OSError) as exc:
        print(f"convert_policy.py: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    print(f"wrote {dest} (and its card {card_path(dest)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
