"""Entry points: train a new run, resume one, open one for inspection."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ..config import ConfigError, validate
from .config import TrainConfig, config_to_dict
from .control_run import ControlRun
from .loop import Run, RunSummary, create_run, open_run, read_run_config, train
from .rundir import RunDirectory

__all__ = ["extend_run", "load_run", "resume_training", "run_training"]


def run_training(cfg: TrainConfig, path: str | Path, *, progress: bool = True, command: str = "") -> RunSummary:
    """Create a new run of ``cfg`` in ``path`` and train it to the end; returns its summary."""
    return train(create_run(cfg, path, progress=progress, command=command))


def resume_training(path: str | Path, *, progress: bool = True) -> RunSummary:
    """Continue the run in ``path`` from its last checkpoint to the end (a finished run returns at once)."""
    return train(open_run(path, progress=progress))


def extend_run(path: str | Path, total_steps: int) -> None:
    """Raise a run's ``total_steps`` so that resuming it continues past its old end (e.g. MFRL to a threshold).

    Only ``config.json`` changes: ``total_steps`` and, for a finished run, its status (running again; the old
    summary is dropped and written anew at the new end). The run continues from its final checkpoint; where
    the old end is an episode boundary it makes exactly the steps of a run given the larger budget from the
    start (tested), where it falls inside an episode it starts a new one there (checkpoints do not hold an
    episode in progress). The real buffer, sized to the old budget, grows to the new one. A learning-rate
    decay (``experimental.lr_decay_after``) ends at ``total_steps``, so past its start the extended run's rates follow the
    new, longer line and are not those of a run given the larger budget from the start.

    Raises:
        ConfigError: if ``total_steps`` is not larger than the run's, or beyond the allowed maximum.
    """
    run_dir = RunDirectory(path)
    payload = run_dir.read_config()  # not a run directory: FileNotFoundError, before any lock file is made
    run_dir.lock(f"extend to {total_steps} steps")
    try:
        run_dir.check_entries(writing=True)  # a run that cannot be resumed is not changed either
        for log in (run_dir.evaluations, run_dir.episodes, run_dir.selection):
            log.read()  # a damaged log is reported before the run is changed (resume would refuse it after)
        cfg = read_run_config(run_dir)
        if cfg.control:
            raise ConfigError(
                f"{path} is a {cfg.method.name} run: it has no step budget to raise (its real steps are its "
                "identification's); start a new run with other settings instead"
            )
        if total_steps <= cfg.total_steps:
            raise ConfigError(f"--total-steps {total_steps:,d} must be larger than the run's total_steps {cfg.total_steps:,d}")
        longer = dataclasses.replace(cfg, total_steps=int(total_steps))
        validate(longer)
        payload["config"] = config_to_dict(longer)
        payload.pop("summary", None)
        if payload.get("status") == "finished":
            payload["status"] = "running"
        run_dir.write_config(payload)
    finally:
        run_dir.unlock()


def load_run(path: str | Path, *, require_checkpoint: bool = False) -> Run:
    """The run in ``path`` at its last checkpoint, for evaluation and figures; no file is changed.

    A run with no checkpoint yet opens at step 0 (its untrained agent), or, with ``require_checkpoint``,
    raises ``FileNotFoundError`` saying there is nothing to evaluate yet.
    """
    run = open_run(path, progress=False, inspect_only=True)
    if isinstance(run, ControlRun):
        raise ValueError(
            f"{path} is a {run.cfg.method.name} run: it has no agent to evaluate; its test return is in evaluations.csv "
            "and its summary in config.json"
        )
    if require_checkpoint and not run.run_dir.checkpoint_path.exists():
        raise FileNotFoundError(f"{path} has no checkpoint yet: nothing to evaluate (train or resume it first)")
    return run
