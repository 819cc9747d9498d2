"""Experiments of the paper, each behind one `pimbrl` command.

* :mod:`.model_eval` — the model-error comparison, data-only against physics-informed (`pimbrl model-eval`);
* :mod:`.compare` — every method and seed on one environment, one figure and one table (`pimbrl compare`);
* :mod:`.sweep` — grids of runs, in-process or on Ray (`pimbrl sweep`);
* :mod:`.figures` — the paper's figures from run directories (`pimbrl figure`).

The package namespace exports the model-eval entry points (imported on first access: the settings,
:mod:`.model_eval_config`, import without torch); import the others from their modules
(``pimbrl.experiments.compare``, ...). Ray is imported only when a sweep runs on it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .model_eval_config import ModelEvalConfig
from .model_eval_config import defaults as model_eval_defaults

if TYPE_CHECKING:
    from .model_eval import run_model_eval

__all__ = ["ModelEvalConfig", "model_eval_defaults", "run_model_eval"]


def __getattr__(name: str) -> Any:
    if name == "run_model_eval":
        from .model_eval import run_model_eval

        return run_model_eval
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
