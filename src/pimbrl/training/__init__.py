"""Training: configuration and presets, the loop (one function, :func:`train`), its components, run directories."""

from .collector import Collector
from .config import METHODS, PRESETS, DynaConfig, TrainConfig, resolve_config
from .dyna import PHASES, DynaModel
from .evaluation import EvalResult, Evaluator
from .logger import RunLogger
from .loop import Run, RunSummary, UpdateSchedule, build_run, create_run, open_run, train
from .rundir import RunDirectory, steps_to_threshold
from .runs import load_run, resume_training, run_training
from .streams import STREAM_KEYS, RandomStreams

__all__ = [
    "METHODS",
    "PHASES",
    "PRESETS",
    "STREAM_KEYS",
    "Collector",
    "DynaConfig",
    "DynaModel",
    "EvalResult",
    "Evaluator",
    "RandomStreams",
    "Run",
    "RunDirectory",
    "RunLogger",
    "RunSummary",
    "TrainConfig",
    "UpdateSchedule",
    "build_run",
    "create_run",
    "load_run",
    "open_run",
    "resolve_config",
    "resume_training",
    "run_training",
    "steps_to_threshold",
    "train",
]
