"""What a configuration will never do within its budget, and other warnings a run states when it starts.

``pimbrl train`` and ``pimbrl compare`` print these lines; scripts that plan runs read them from here.
"""

from __future__ import annotations

from .config import TrainConfig, preset_note, return_scale_warnings

__all__ = ["budget_warnings", "config_warnings"]


def budget_warnings(cfg: TrainConfig) -> list[str]:
    """What a run of ``cfg`` will never do within its budget.

    One line each: no agent update (the budget ends by ``update_after``), random actions only (by
    ``warmup_steps``), no model (methods with a model, by ``model.start_after``), and no physics-only training
    before ``update_after`` (``physics.alone_from`` below it: model phases run only from ``update_after`` on),
    with the flag to change.
    """
    n = cfg.total_steps
    out = []
    if n <= cfg.update_after:
        out.append(
            f"--steps {n} ends before the first agent update (update_after = {cfg.update_after}): the agent is never "
            f"trained; give --steps above {cfg.update_after} or a lower --update-after"
        )
    if n <= cfg.warmup_steps:
        out.append(
            f"--steps {n} ends within the random warm-up (warmup_steps = {cfg.warmup_steps}): every action is random; "
            f"give --steps above {cfg.warmup_steps} or a lower --warmup-steps"
        )
    if not cfg.model_based:
        return out
    start_after = cfg.dyna.start_after
    if n <= start_after:
        out.append(
            f"--steps {n} ends before the model is first fitted (model.start_after = {start_after}): the run never uses "
            f"a model; give --steps above {start_after} or a lower --model.start-after"
        )
    physics = getattr(cfg.method, "physics", None)
    start = None if physics is None else physics.alone_from
    if start is not None and start < cfg.update_after:
        first = (
            "the labels join then too, so no phase trains on the physics alone"
            if start_after <= cfg.update_after
            else f"the physics-only training runs from {cfg.update_after} to {start_after}"
        )
        out.append(
            f"physics.alone_from = {start} is before update_after = {cfg.update_after}, and model phases run only "
            f"from update_after on: {first}; give a lower --update-after to train the model earlier"
        )
    return out


def config_warnings(cfg: TrainConfig, preset: str | None = None) -> list[str]:
    """Everything ``pimbrl train`` and ``pimbrl compare`` warn about in a configuration.

    A system without a preset (:func:`~pimbrl.training.config.preset_note`), :func:`budget_warnings`, then the
    recipe's values kept on another return scale (:func:`~pimbrl.training.config.return_scale_warnings`).
    """
    note = preset_note(cfg.env)
    return [*([note] if note else []), *budget_warnings(cfg), *return_scale_warnings(cfg, preset)]
