"""Training: configuration and presets, the loop, evaluation, run directories."""

from .config import METHODS, PRESETS, TrainConfig, resolve_config
from .evaluation import EvalResult, Evaluator
from .loop import RunSummary, Trainer, steps_to_threshold
from .rundir import RunDirectory

__all__ = [
    "METHODS",
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
