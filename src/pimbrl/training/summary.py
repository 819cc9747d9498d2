"""The outcome of a run, as stored in ``config.json`` when it finishes (every method's, RL or control)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["RunSummary"]


@dataclass(frozen=True)
class RunSummary:
    """Outcome of a run, as stored in ``config.json`` when it finishes."""

    steps: int
    updates: int
    final_return_mean: float | None
    best_return_mean: float | None
    steps_to_threshold: int | None
    wall_s: float
    #: model-based policy selection (``imagine.select_episodes``): the step of the policy kept, and its test return
    selected_step: int | None = None
    selected_return_mean: float | None = None
    #: what the method used to get there: real transitions (the environment's steps), imagined transitions
    #: (made by the model, in the imagined buffer), the transitions a scheme of the known equation stepped
    #: (known-scheme, identified-scheme and the hybrids: imagination and policy selection; simulator
    #: transitions a model-free method does not have) and the real simulator's steps of the fine-tuning
    #: switch's validation episodes; ``None``: unknown (resumed from a checkpoint that did not count them)
    real_transitions: int | None = None
    imagined_transitions: int | None = None
    scheme_transitions: int | None = None
    validation_transitions: int | None = None
    #: wall seconds per control step and state of acting at the last test evaluation: one batched network call
    #: for an RL policy, an optimisation for MPC (``None``: not measured)
    inference_s_per_step: float | None = None
    #: the final policy's mean return on the holdout pool (``holdout_episodes``; ``None``: not played)
    holdout_return_mean: float | None = None
    holdout_episodes: int = 0
