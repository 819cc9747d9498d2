"""Training: configuration and presets, the loop, evaluation, run directories."""

from .config import METHODS, PRESETS, DynaConfig, TrainConfig, resolve_config
from .dyna import DynaTrainer
from .evaluation import EvalResult, Evaluator
from .loop import RunSummary, Trainer, steps_to_threshold
from .rundir import RunDirectory
from .runs import create_trainer, resume_trainer, resume_training, run_training, trainer_class

__all__ = [
    "METHODS",
    "DynaConfig",
    "DynaTrainer",
    "create_trainer",
    "resume_trainer",
    "resume_training",
    "run_training",
    "trainer_class",
    "PRESETS",
    "EvalResult",
    "Evaluator",
    "RunDirectory",
    "RunSummary",
    "TrainConfig",
    "Trainer",
    "resolve_config",
    "steps_to_threshold",
]
