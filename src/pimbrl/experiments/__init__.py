"""Experiments of the paper: model-error comparison (and, later, comparisons and sweeps)."""

from .model_eval import DEFAULTS as MODEL_EVAL_DEFAULTS
from .model_eval import ModelEvalConfig, run_model_eval

__all__ = ["MODEL_EVAL_DEFAULTS", "ModelEvalConfig", "run_model_eval"]
