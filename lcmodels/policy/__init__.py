"""The lane-change policy: hybrid features extractor, observation modes, training, warm start, evaluation.

Public API (each name imported when first used, so that ``import lcmodels.policy.config`` and the commands'
``--help`` load no torch, numba or stable-baselines3)::

    ALGORITHMS, IMAGE_NETS, OBS_MODES, ObsMode              # names.py (plain constants)
    HybridExtractor, CompactVGG, StridedCompact, VGG16      # extractor.py
    policy_vec_env, build_observation                       # obs.py
    PolicyConfig                                            # config.py
    train_policy                                            # train.py
    load_demonstrations, pretrain, bc_loss                  # warmstart.py
    PolicyDriver, eval_user_seeds                           # evaluate.py (and its evaluate())
    save_policy, load_policy, read_meta                     # checkpoint.py
"""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {
    "ALGORITHMS": "names", "IMAGE_NETS": "names", "OBS_MODES": "names", "ObsMode": "names",
    "HybridExtractor": "extractor", "CompactVGG": "extractor", "StridedCompact": "extractor", "VGG16": "extractor",
    "policy_vec_env": "obs", "build_observation": "obs",
    "PolicyConfig": "config",
    "train_policy": "train",
    "load_demonstrations": "warmstart", "pretrain": "warmstart", "bc_loss": "warmstart",
    "PolicyDriver": "evaluate", "eval_user_seeds": "evaluate",
    "save_policy": "checkpoint", "load_policy": "checkpoint", "read_meta": "checkpoint",
}  # fmt: skip

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_WHERE})
