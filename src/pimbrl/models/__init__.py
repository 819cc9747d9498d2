"""Transition models, the physics-informed residual, model training and imagined environments."""

from .factory import MODELS, make_model
from .hybrid import HybridModel, PhysicsModel
from .model_env import ModelEnv
from .networks import ConvLSTMModel, EquivariantConvModel, MLPModel, TransitionModel
from .residual import PhysicsResidual
from .reward import LearnedReward
from .trainer import ModelTrainer, TransitionData

__all__ = [
    "MODELS",
    "ConvLSTMModel",
    "EquivariantConvModel",
    "HybridModel",
    "LearnedReward",
    "MLPModel",
    "ModelEnv",
    "ModelTrainer",
    "PhysicsModel",
    "PhysicsResidual",
    "TransitionData",
    "TransitionModel",
    "make_model",
]
