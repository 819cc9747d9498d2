"""Settings of `pimbrl model-eval`: plain data, importable without torch (for the command line's flags).

The physics loss is the training's own :class:`~pimbrl.training.methods.PhysicsLoss` (``--physics.weight``,
``--physics.sources``, ``--physics.units``), with its defaults: a model-eval run measures the physics loss a
PiMBRL run trains with.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from ..config import MAX_BATCH, MAX_LR, MAX_SEED, MAX_STEPS, MAX_TRANSITIONS, at_most, non_negative, one_of, param, positive
from ..training.methods import NETWORKS, PhysicsLoss

__all__ = ["PHYSICS_FLAGS", "ModelEvalConfig", "defaults"]


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
    network: str = param(
        "auto", "the network: convlstm or equivariant for a PDE, mlp for an ODE; auto: the paper's", one_of(*NETWORKS)
    )
    models: str = param(
        "",
        "study: the models to compare, comma-separated (default: all of data, physics, physics-true, "
        "physics-learned, physics-only, physics-only-learned that the study has)",
    )
    env_coefficients: dict[str, float] = param(
        {}, "study: the environment's physical coefficients where they differ from the paper's (--env-coefficients nu=0.013)"
    )
    physics_prior: dict[str, float] = param(
        {},
        "study: coefficients of the physics loss's prior where they differ from the environment's (--physics-prior "
        "nu=0.01; adds the model physics-true, trained with the environment's own)",
    )
    learn_coefficients: dict[str, Any] = param(
        {}, "study: coefficients fitted to the labels from the prior (--learn-coefficients nu; adds the model physics-learned)"
    )
    coefficient_lr: float = param(1e-2, "study: Adam learning rate of the learned coefficients", [positive(), at_most(MAX_LR)])
    rollout_lengths: tuple[int, ...] = param(
        (1,),
        "study: chained model steps at which the error is measured, e.g. 1,3,8",
        (lambda v: len(v) > 0 and all(1 <= n <= 10_000 for n in v), "must be numbers in [1, 10,000]"),
    )
    physics: PhysicsLoss = dataclasses.field(
        default_factory=PhysicsLoss, metadata={"help": "the physics loss (--physics.*), as in training", "prefix": "physics"}
    )


#: the physics-loss settings that model-eval reads (the schedule of a training run has no meaning here)
PHYSICS_FLAGS = ("weight", "units", "sources")


def defaults(env_id: str) -> dict[str, Any]:
    """The model-study settings the system ``env_id`` declares (``System.model_eval``; none for other ids)."""
    from ..systems import get_system

    system = get_system(env_id)
    return dict(system.model_eval) if system is not None else {}
