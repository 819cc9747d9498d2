"""Settings of `pimbrl model-eval`: plain data, importable without torch (for the command line's flags)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..config import MAX_BATCH, MAX_LR, MAX_SEED, MAX_STEPS, MAX_TRANSITIONS, at_most, non_negative, one_of, param, positive

__all__ = ["ModelEvalConfig", "defaults"]


@dataclass(frozen=True)
class ModelEvalConfig:
    """Settings of `pimbrl model-eval` (defaults per system: :func:`defaults`)."""

    transitions: int = param(
        2_000,
        "real transitions collected with a random policy (training + in-sample test)",
        [positive(), at_most(MAX_TRANSITIONS)],
    )
    test_transitions: int = param(
        500, "held-out in-sample and out-of-sample test transitions (each)", [positive(), at_most(MAX_TRANSITIONS)]
    )
    steps: int = param(2_000, "gradient steps of each model", [positive(), at_most(MAX_STEPS)])
    batch_size: int = param(256, "batch size of the data and of the physics loss", [positive(), at_most(MAX_BATCH)])
    lr: float = param(1e-3, "Adam learning rate", [positive(), at_most(MAX_LR)])
    n_intermediate: int = param(5, "PDE models: intermediate states per control step", [positive(), at_most(1_000)])
    scheme: str = param(
        "etd", "PDE residual scheme: etd or solver", (lambda v: v in ("etd", "solver"), "must be 'etd' or 'solver'")
    )
    physics_weight: float = param(1.0, "w_E, weight of the physics loss", [non_negative(), at_most(1e6)])
    imagined_length: int = param(
        3, "length of the imagined rollouts that supply unlabelled states", [non_negative(), at_most(10_000)]
    )
    refresh_every: int = param(250, "gradient steps between refreshes of the imagined states", [positive(), at_most(MAX_STEPS)])
    seed: int = param(0, "seed of data collection, initialisation and batches", [non_negative(), at_most(MAX_SEED)])
    threads: int = param(1, "torch threads", [positive(), at_most(256)])
    # the study (pimbrl.experiments.model_study): used when ``labels`` is given
    labels: tuple[int, ...] = param(
        (),
        "study: numbers of labelled transitions to compare, e.g. 0,100,300,1000",
        (lambda v: all(0 <= n <= MAX_TRANSITIONS for n in v), f"must be numbers in [0, {MAX_TRANSITIONS:,}]"),
    )
    seeds: int = param(1, "study: seeds (seed, seed + 1, ...)", [positive(), at_most(1_000)])
    seed_states: int = param(
        500, "study: observed states the physics loss may start from without labels", [positive(), at_most(MAX_TRANSITIONS)]
    )
    sources: str = param("train,imagined", "physics-loss sources: train, imagined, symmetry, scaled, noise, box")
    units: str = param("substep", "units of the physics loss: substep or step", one_of("substep", "step"))
    model: str = param("convlstm", "PDE model: convlstm or equivariant", one_of("convlstm", "equivariant"))
    models: str = param(
        "",
        "study: the models to compare, comma-separated (default: all of data, physics, physics-true, "
        "physics-learned, physics-only, physics-only-learned that the study has)",
    )
    env_coefficients: str = param(
        "", "study: the environment's physical coefficients where they differ from the paper's, e.g. nu=0.013"
    )
    physics_prior: str = param(
        "",
        "study: coefficients of the physics loss's prior where they differ from the environment's, e.g. nu=0.01 "
        "(adds the model physics-true, trained with the environment's own)",
    )
    learn_coefficients: str = param(
        "", "study: coefficients fitted to the labels from the prior, e.g. nu (adds the model physics-learned)"
    )
    coefficient_lr: float = param(1e-2, "study: Adam learning rate of the learned coefficients", [positive(), at_most(MAX_LR)])
    rollout_lengths: tuple[int, ...] = param(
        (1,),
        "study: chained model steps at which the error is measured, e.g. 1,3,8",
        (lambda v: len(v) > 0 and all(1 <= n <= 10_000 for n in v), "must be numbers in [1, 10,000]"),
    )


def defaults(env_id: str) -> dict[str, Any]:
    """The model-study settings the system ``env_id`` declares (``System.model_eval``; none for other ids)."""
    from ..systems import get_system

    system = get_system(env_id)
    return dict(system.model_eval) if system is not None else {}
