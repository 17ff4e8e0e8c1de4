"""The lane-change policy: hybrid features extractor, observation modes, training, warm start, evaluation.

Public API::

    HybridExtractor, CompactVGG, StridedCompact, VGG16      # extractor.py
    OBS_MODES, ObsMode, policy_vec_env, build_observation   # obs.py
    PolicyConfig, train_policy                              # train.py
    load_demonstrations, pretrain, bc_loss                  # warmstart.py
    evaluate, PolicyDriver, eval_user_seeds                 # evaluate.py
    save_policy, load_policy, read_meta                     # checkpoint.py
"""

from lcmodels.policy.checkpoint import load_policy, read_meta, save_policy
from lcmodels.policy.evaluate import PolicyDriver, eval_user_seeds, evaluate
from lcmodels.policy.extractor import VGG16, CompactVGG, HybridExtractor, StridedCompact
from lcmodels.policy.obs import OBS_MODES, ObsMode, build_observation, policy_vec_env
from lcmodels.policy.train import PolicyConfig, train_policy
from lcmodels.policy.warmstart import bc_loss, load_demonstrations, pretrain

__all__ = [
    "OBS_MODES",
    "VGG16",
    "CompactVGG",
    "HybridExtractor",
    "ObsMode",
    "PolicyConfig",
    "PolicyDriver",
    "StridedCompact",
    "bc_loss",
    "build_observation",
    "eval_user_seeds",
    "evaluate",
    "load_demonstrations",
    "load_policy",
    "policy_vec_env",
    "pretrain",
    "read_meta",
    "save_policy",
    "train_policy",
]
