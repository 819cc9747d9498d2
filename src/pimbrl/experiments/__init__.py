"""Experiments of the paper, each behind one `pimbrl` command.

* :mod:`.model_eval` — the model-error comparison, data-only against physics-informed (`pimbrl model-eval`);
* :mod:`.compare` — every method and seed on one environment, one figure and one table (`pimbrl compare`);
* :mod:`.sweep` — grids of runs, in-process or on Ray (`pimbrl sweep`);
* :mod:`.figures` — the paper's figures from run directories (`pimbrl figure`).

The package namespace exports the model-eval entry points; import the others from their modules
(``pimbrl.experiments.compare``, ...). Ray is imported only when a sweep runs on it.
"""

from .model_eval import DEFAULTS as MODEL_EVAL_DEFAULTS
from .model_eval import ModelEvalConfig, run_model_eval

__all__ = ["MODEL_EVAL_DEFAULTS", "ModelEvalConfig", "run_model_eval"]
