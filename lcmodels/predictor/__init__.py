"""Trajectory prediction: corpus windows in, future positions out.

Public API::

    PredictorConfig, TrajectoryTransformer          # model.py
    TrainConfig, train_predictor, evaluate          # train.py
    Predictor (load, predict_neighbours, ...)       # inference.py
    save_model, load_model                          # checkpoint.py
    constant_velocity, constant_acceleration        # baselines.py
    ade, fde, error_curve, miss_rate                # metrics.py
"""

from lcmodels.predictor.baselines import constant_acceleration, constant_velocity
from lcmodels.predictor.checkpoint import load_model, save_model
from lcmodels.predictor.inference import Predictor
from lcmodels.predictor.metrics import ade, error_curve, fde, miss_rate
from lcmodels.predictor.model import PredictorConfig, TrajectoryTransformer
from lcmodels.predictor.train import TrainConfig, evaluate, train_predictor

__all__ = [
    "Predictor",
    "PredictorConfig",
    "TrainConfig",
    "TrajectoryTransformer",
    "ade",
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
