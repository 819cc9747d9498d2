"""Transition models, the physics-informed residual, model training and imagined environments."""

from .model_env import ModelEnv
from .networks import MODELS, ConvLSTMModel, EquivariantConvModel, MLPModel, TransitionModel, make_model
from .residual import PhysicsResidual
from .trainer import ModelTrainer, TransitionData

__all__ = [
    "MODELS",
    "ConvLSTMModel",
    "EquivariantConvModel",
    "MLPModel",
    "ModelEnv",
    "ModelTrainer",
    "PhysicsResidual",
    "TransitionData",
    "TransitionModel",
    "make_model",
]
