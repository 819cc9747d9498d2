"""Creating and resuming runs: the right trainer for each method."""

from __future__ import annotations

from ..config import from_dict
from .config import TrainConfig
from .dyna import DynaTrainer
from .loop import RunSummary, Trainer
from .rundir import RunDirectory

__all__ = ["create_trainer", "resume_trainer", "resume_training", "run_training", "trainer_class"]


def trainer_class(method: str) -> type[Trainer]:
    """:class:`Trainer` for ``mfrl``, :class:`DynaTrainer` for ``mbrl`` and ``pimbrl``."""
    return Trainer if method == "mfrl" else DynaTrainer


def create_trainer(cfg: TrainConfig, path: str, progress: bool = True, command: str = "") -> Trainer:
    """A new run of ``cfg`` in ``path``."""
    return trainer_class(cfg.method).create(cfg, path, progress=progress, command=command)


def resume_trainer(path: str, progress: bool = True, inspect_only: bool = False) -> Trainer:
    """The run in ``path``, at its last checkpoint (``inspect_only``: read it without changing any file)."""
    cfg = from_dict(TrainConfig, RunDirectory(path).read_config()["config"])
    return trainer_class(cfg.method).resume(path, progress=progress, inspect_only=inspect_only)


def run_training(cfg: TrainConfig, path: str, *, progress: bool = True, command: str = "") -> RunSummary:
    """Create a new run of ``cfg`` in ``path`` and train it to the end; returns its summary."""
    return create_trainer(cfg, path, progress=progress, command=command).run()


def resume_training(path: str, *, progress: bool = True) -> RunSummary:
    """Continue the run in ``path`` from its last checkpoint to the end (a finished run returns at once)."""
    return resume_trainer(path, progress=progress).run()
