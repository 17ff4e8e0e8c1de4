"""File names and small file helpers of the model layer (no heavy imports); the generic helpers live in
:mod:`lckit.fileio`, shared with recording. The readers here take what a run folder holds as untrusted: an
array of the wrong kind or a tensor of the wrong dtype is refused with one line, never converted."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lckit.fileio import file_sha256, json_default, read_json, write_json

if TYPE_CHECKING:
    import numpy as np

POLICY_FILE = "policy.safetensors"
"""The file name a training run, a DAgger round or a conversion gives its policy (safetensors + card)."""
TRAIN_SEEDS_FILE = "train_episode_seeds.npy"
"""Beside a run's policy: the simulator seeds of its training episodes (int64), for the held-out check."""
MAX_NPY_BYTES = 1 << 30
"""The largest ``.npy`` file :func:`read_npy` reads."""


def read_npy(path: str | os.PathLike[str], *, kinds: str, ndim: int, what: str) -> np.ndarray:
    """The array in the ``.npy`` file ``path``, which must hold ``ndim`` dimensions of a dtype whose kind is one
    of ``kinds`` (numpy's letters: ``"iu"`` integers, ``"f"`` floats). ``ValueError`` naming the file and
    ``what`` it should be for anything else: strings, objects (never unpickled), an ``.npz``, a truncated or
    foreign file, one over :data:`MAX_NPY_BYTES`."""
    import numpy as np

    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_NPY_BYTES:
            raise ValueError(f"{size} bytes, more than {MAX_NPY_BYTES >> 20} MiB")
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        detail = " ".join(str(exc).split())[:120]
        raise ValueError(f"{path} is not a readable .npy file of {what} ({detail})") from None
    if not isinstance(array, np.ndarray):  # an .npz archive under an .npy name
        array.close()
        raise ValueError(f"{path} is an .npz archive, not the .npy array of {what}")
    if array.dtype.kind not in kinds or array.ndim != ndim:
        raise ValueError(f"{path} holds a {array.ndim}-d array of {array.dtype}, not the {ndim}-d array of {what} "
                         f"({'integers' if kinds == 'iu' else kinds})")  # fmt: skip
    return array


def read_train_seeds(folder: str | os.PathLike[str]) -> np.ndarray | None:
    """The training-episode seeds of the run in ``folder`` (:data:`TRAIN_SEEDS_FILE`) as int64, None when it has
    none; ``ValueError`` (:func:`read_npy`) for a file that is not a 1-d array of integers."""
    path = Path(folder) / TRAIN_SEEDS_FILE
    if not path.exists():
        return None
    seeds = read_npy(path, kinds="iu", ndim=1, what="training-episode seeds")
    if seeds.dtype.kind == "u" and len(seeds) and int(seeds.max()) > 2**63 - 1:
        raise ValueError(f"{path} holds seeds above 2**63 - 1; the simulator's are below")
    return seeds.astype("int64")


def check_dtypes(tensors: Mapping[str, Any], expected: Mapping[str, Any], where: str) -> None:
    """``ValueError`` when a tensor of ``tensors`` has another dtype than the one of the same name in ``expected``
    (a network's ``state_dict()``): loading would convert it silently (a float tensor relabelled as integers
    would load as nonsense). Names in one only, and a ``tensors`` that is no mapping, are left to
    ``load_state_dict``'s own checks."""
    if not isinstance(tensors, Mapping):
        return
    for name, tensor in tensors.items():
        want = expected.get(name)
        if want is not None and getattr(tensor, "dtype", None) != want.dtype:
            raise ValueError(f"{where}: tensor {name} is stored as {getattr(tensor, 'dtype', type(tensor).__name__)}, "
                             f"the network holds {want.dtype}; it is not converted (a file written for another "
                             "network, or altered)")  # fmt: skip


__all__ = [
    "MAX_NPY_BYTES",
    "POLICY_FILE",
    "TRAIN_SEEDS_FILE",
    "check_dtypes",
    "file_sha256",
    "json_default",
    "read_json",
    "read_npy",
    "read_train_seeds",
    "write_json",
]
