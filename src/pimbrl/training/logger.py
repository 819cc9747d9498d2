"""What a run records: evaluations, episodes, metrics, phase timings, TensorBoard and the progress display.

:class:`RunLogger` writes the CSV logs of a :class:`~pimbrl.training.rundir.RunDirectory`, averages the
agent's and the model's update metrics between two rows of ``metrics.csv``, times the phases of the loop
(``time/<phase>_s``, cumulative seconds), keeps the wall-clock across resumes and remembers the first
step at which the mean test return reached the run's threshold.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import torch

from .evaluation import EvalResult
from .progress import TrainingProgress
from .rundir import RunDirectory

__all__ = ["RunLogger"]

BASE_COLUMNS = ["step", "wall_s", "steps_per_s", "episodes", "agent_updates", "update_to_data", "real_buffer"]


class RunLogger:
    """Logs of one run.

    Args:
        run_dir: the run directory.
        columns: the extra columns of ``metrics.csv`` (agent and model metrics, then phase timings).
        phases: names of the timed phases.
        threshold: the return that counts as solved (``None``: none).
        tensorboard: also write TensorBoard events.
        progress: show a progress bar on a terminal (log lines otherwise).
    """

    def __init__(
        self,
        run_dir: RunDirectory,
        columns: Sequence[str],
        phases: Sequence[str],
        threshold: float | None,
        tensorboard: bool = False,
        progress: bool = True,
    ) -> None:
        self.run_dir = run_dir
        self.columns = [*BASE_COLUMNS, *columns, *(f"time/{p}_s" for p in phases)]
        self.threshold = threshold
        self.tensorboard = tensorboard
        self.show_progress = progress
        self.phase_s = dict.fromkeys(phases, 0.0)
        self.first_threshold_step: int | None = None
        self.last_eval: float | None = None
        self.wall_offset = 0.0
        self._sums: dict[str, float] = {}
        self._counts: dict[str, int] = {}
        self._session_start = time.perf_counter()
        self._tick = (0, self._session_start)
        self._tb: Any = None
        self.progress = TrainingProgress(1, 0, "", enabled=False)

    # ------------------------------------------------------------------ session
    def open(self, t: int, total: int, label: str) -> None:
        """Start a training session at step ``t`` (progress display, TensorBoard, speed measurement)."""
        self._session_start = time.perf_counter()
        self._tick = (t, self._session_start)
        self.progress = TrainingProgress(total, t, label, enabled=self.show_progress)
        if self.tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError as exc:  # pragma: no cover - depends on the environment
                raise RuntimeError("tensorboard=True needs the tensorboard package: pip install 'pimbrl[tensorboard]'") from exc
            self._tb = SummaryWriter(log_dir=str(self.run_dir.path / "tb"), purge_step=t if t > 0 else None)

    def close(self) -> None:
        """End the session (files closed, progress display stopped)."""
        self.progress.close()
        self.run_dir.close()
        if self._tb is not None:
            self._tb.close()
            self._tb = None

    @property
    def wall_s(self) -> float:
        """Seconds of training, over all sessions of the run."""
        return self.wall_offset + (time.perf_counter() - self._session_start)

    @contextlib.contextmanager
    def timed(self, phase: str) -> Iterator[None]:
        """Add the time spent inside to ``phase``."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.phase_s[phase] += time.perf_counter() - t0

    def message(self, text: str) -> None:
        """A log line (above the progress bar on a terminal)."""
        self.progress.message(text)

    # ------------------------------------------------------------------ records
    def accumulate(self, metrics: Mapping[str, torch.Tensor | float]) -> None:
        """Add one update's metrics to the running means of the next ``metrics.csv`` row."""
        for k, v in metrics.items():
            self._sums[k] = self._sums.get(k, 0.0) + float(v)
            self._counts[k] = self._counts.get(k, 0) + 1

    def evaluation(self, t: int, result: EvalResult, updates: int) -> None:
        """One row of ``evaluations.csv``; notes the first step at the threshold."""
        row = {"step": t, **result.summary(), "updates": updates, "wall_s": self.wall_s}
        self.run_dir.evaluations.append(row)
        self.last_eval = result.mean
        if self.threshold is not None and self.first_threshold_step is None and result.mean >= self.threshold:
            self.first_threshold_step = t
        self._scalars(
            t, {"eval/return_mean": result.mean, "eval/return_min": row["return_min"], "eval/return_max": row["return_max"]}
        )
        self.progress.update(t, eval_return=result.mean)
        self.message(
            f"step {t:>8,d}  eval return {result.mean:10.3f} (min {row['return_min']:.3f}, max {row['return_max']:.3f})  "
            f"updates {updates:,d}  {self.wall_s:7.1f} s"
        )

    def episode(self, t: int, episode: int, episode_return: float, length: int) -> None:
        """One row of ``episodes.csv``."""
        self.run_dir.episodes.append({"step": t, "episode": episode, "return": episode_return, "length": length})
        self._scalars(t, {"train/episode_return": episode_return})

    def metrics(self, t: int, counters: Mapping[str, Any]) -> None:
        """Write one row of ``metrics.csv`` (and the scalars, where TensorBoard is on) and reset the sums.

        The row holds ``counters`` (episodes, updates, buffer sizes, model state), the means of the
        accumulated update metrics, the speed since the last row and the phase timings.
        """
        now = time.perf_counter()
        sps = (t - self._tick[0]) / max(now - self._tick[1], 1e-9)
        self._tick = (t, now)
        row: dict[str, Any] = {"step": t, "wall_s": self.wall_s, "steps_per_s": sps, **counters}
        for k in sorted(self._sums):
            row[k] = self._sums[k] / max(self._counts[k], 1)
        row.update({f"time/{p}_s": v for p, v in self.phase_s.items()})
        self.run_dir.metrics(self.columns).append(row)
        self._scalars(t, {k: v for k, v in row.items() if k != "step" and isinstance(v, (int, float))})
        self._sums.clear()
        self._counts.clear()
        self.progress.update(t, sps=sps)

    def _scalars(self, t: int, values: Mapping[str, float]) -> None:
        if self._tb is not None:
            for k, v in values.items():
                self._tb.add_scalar(k, float(v), t)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Running means, phase timings, wall-clock, threshold step and last evaluation."""
        return {
            "sums": dict(self._sums),
            "counts": dict(self._counts),
            "phase_s": dict(self.phase_s),
            "wall_s": self.wall_s,
            "first_threshold_step": self.first_threshold_step,
            "last_eval": self.last_eval,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self._sums = dict(state["sums"])
        self._counts = dict(state["counts"])
        self.phase_s.update(state["phase_s"])
        self.wall_offset = float(state["wall_s"])
        self.first_threshold_step = state["first_threshold_step"]
        self.last_eval = state["last_eval"]
        self._session_start = time.perf_counter()
