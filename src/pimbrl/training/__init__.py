"""Training: configuration and presets, the loop (one function, :func:`train`), its components, run directories.

The names below are imported on first access: the configuration (:mod:`.config`, :mod:`.cli_args`)
imports without torch, so that the command line starts fast; the loop and its components import torch.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .collector import Collector
    from .config import POLICIES, Experimental, TrainConfig, recipe_of, resolve_config
    from .dyna import PHASES, DynaModel
    from .evaluation import EvalResult, Evaluator
    from .logger import RunLogger
    from .loop import Run, RunSummary, UpdateSchedule, build_run, create_run, open_run, train
    from .methods import (
        MBRL,
        METHODS,
        MFRL,
        AccuracyCheck,
        CoefficientFit,
        Finetune,
        Hybrid,
        IdentifiedScheme,
        Imagination,
        KnownScheme,
        ModelFit,
        PhysicsLoss,
        PiHybrid,
        PiMBRL,
    )
    from .rundir import RunDirectory, steps_to_threshold
    from .runs import load_run, resume_training, run_training
    from .stopping import RunStopped
    from .streams import STREAM_KEYS, RandomStreams

#: public name -> the submodule that defines it
_WHERE = {
    "Collector": "collector",
    "METHODS": "methods",
    "MFRL": "methods",
    "MBRL": "methods",
    "PiMBRL": "methods",
    "KnownScheme": "methods",
    "IdentifiedScheme": "methods",
    "Hybrid": "methods",
    "PiHybrid": "methods",
    "ModelFit": "methods",
    "AccuracyCheck": "methods",
    "Imagination": "methods",
    "Finetune": "methods",
    "PhysicsLoss": "methods",
    "CoefficientFit": "methods",
    "Experimental": "config",
    "recipe_of": "config",
    "TrainConfig": "config",
    "resolve_config": "config",
    "PHASES": "dyna",
    "POLICIES": "config",
    "DynaModel": "dyna",
    "EvalResult": "evaluation",
    "Evaluator": "evaluation",
    "RunLogger": "logger",
    "Run": "loop",
    "RunSummary": "loop",
    "UpdateSchedule": "loop",
    "build_run": "loop",
    "create_run": "loop",
    "open_run": "loop",
    "train": "loop",
    "RunDirectory": "rundir",
    "steps_to_threshold": "rundir",
    "load_run": "runs",
    "resume_training": "runs",
    "run_training": "runs",
    "RunStopped": "stopping",
    "STREAM_KEYS": "streams",
    "RandomStreams": "streams",
}

__all__ = [
    "MBRL",
    "METHODS",
    "MFRL",
    "PHASES",
    "POLICIES",
    "STREAM_KEYS",
    "AccuracyCheck",
    "CoefficientFit",
    "Collector",
    "DynaModel",
    "EvalResult",
    "Evaluator",
    "Experimental",
    "Finetune",
    "Hybrid",
    "IdentifiedScheme",
    "Imagination",
    "KnownScheme",
    "ModelFit",
    "PhysicsLoss",
    "PiHybrid",
    "PiMBRL",
    "RandomStreams",
    "Run",
    "RunDirectory",
    "RunLogger",
    "RunStopped",
    "RunSummary",
    "TrainConfig",
    "UpdateSchedule",
    "build_run",
    "create_run",
    "load_run",
    "open_run",
    "recipe_of",
    "resolve_config",
    "resume_training",
    "run_training",
    "steps_to_threshold",
    "train",
]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
