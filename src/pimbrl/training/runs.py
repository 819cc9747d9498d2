"""Entry points: train a new run, resume one, open one for inspection."""

from __future__ import annotations

from pathlib import Path

from .config import TrainConfig
from .loop import Run, RunSummary, create_run, open_run, train

__all__ = ["load_run", "resume_training", "run_training"]


def run_training(cfg: TrainConfig, path: str | Path, *, progress: bool = True, command: str = "") -> RunSummary:
    """Create a new run of ``cfg`` in ``path`` and train it to the end; returns its summary."""
    return train(create_run(cfg, path, progress=progress, command=command))


def resume_training(path: str | Path, *, progress: bool = True) -> RunSummary:
    """Continue the run in ``path`` from its last checkpoint to the end (a finished run returns at once)."""
    return train(open_run(path, progress=progress))


def load_run(path: str | Path) -> Run:
    """The run in ``path`` at its last checkpoint, for evaluation and figures; no file is changed."""
    return open_run(path, progress=False, inspect_only=True)
