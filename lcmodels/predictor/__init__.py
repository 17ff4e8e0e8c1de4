"""Trajectory prediction: corpus windows in, future positions out.

Design choices (where the paper is silent):

- Samples are agent-centric (``lcdata.corpus``): origin at the agent's position at the last observed
  step, x axis along its heading estimated from positions only (backward difference, skipping
  standing points). The policy-time API re-centres every neighbour with the same functions.
- The model predicts the residual over the constant-velocity extrapolation, standardised with
  training-split statistics (stored as buffers, so they travel with the weights); its output layer
  starts at zero, so an untrained model is the CV baseline.
- One token per vehicle (the agent + K = 8 nearest at t0), each an MLP embedding of its H-step
  history (position, backward-difference velocity and acceleration, presence). The agent token is
  the query of ``num_layers`` transformer layers attending over all tokens (absent ones masked);
  full self-attention among all tokens is available (``num_context_layers``, off by default) but
  costs several times more at inference. All F steps are decoded at once.
- Loss and early stopping use the ADE in metres (validation split); splits are by episode.
- Miss rate counts final errors above ``TrainConfig.miss_threshold_m`` (0.5 m by default).

Public API::

    PredictorConfig, TrajectoryTransformer          # model.py
    TrainConfig, train_predictor, evaluate          # train.py
    Predictor (load, predict_neighbours, ...)       # inference.py
    save_model, load_model                          # checkpoint.py
    constant_velocity, constant_acceleration        # baselines.py
    ade, fde, error_curve, miss_rate                # metrics.py
"""

from lcmodels.predictor.baselines import constant_acceleration, constant_velocity
from lcmodels.predictor.checkpoint import ANALYTIC_BASES, analytic_model, load_model, save_model
from lcmodels.predictor.inference import Predictor
from lcmodels.predictor.metrics import ade, error_curve, fde, miss_rate
from lcmodels.predictor.model import PredictorConfig, TrajectoryTransformer
from lcmodels.predictor.train import TrainConfig, evaluate, train_predictor

__all__ = [
    "ANALYTIC_BASES",
    "Predictor",
    "PredictorConfig",
    "TrainConfig",
    "TrajectoryTransformer",
    "ade",
    "analytic_model",
    "constant_acceleration",
    "constant_velocity",
    "error_curve",
    "evaluate",
    "fde",
    "load_model",
    "miss_rate",
    "save_model",
    "train_predictor",
]
