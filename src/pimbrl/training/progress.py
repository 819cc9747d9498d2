"""Progress display: a rich progress bar on a terminal, plain log lines otherwise."""

from __future__ import annotations

import sys
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

__all__ = ["TrainingProgress"]


class TrainingProgress:
    """Shows steps, the last evaluation return and steps per second."""

    def __init__(self, total: int, start: int, label: str, enabled: bool = True) -> None:
        self.console = Console(stderr=True)
        self.interactive = enabled and self.console.is_terminal
        self.enabled = enabled
        self.label = label
        self._progress: Progress | None = None
        if self.interactive:
            self._progress = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("eval {task.fields[eval]}"),
                TextColumn("{task.fields[sps]} steps/s"),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
                console=self.console,
            )
            self._task = self._progress.add_task(label, total=total, completed=start, eval="-", sps="-")
            self._progress.start()

    def update(self, step: int, sps: float | None = None, eval_return: float | None = None) -> None:
        """Move the bar to ``step`` and show the speed and last evaluation return if given (no-op without a bar)."""
        if self._progress is None:
            return
        fields: dict[str, Any] = {}
        if sps is not None:
            fields["sps"] = f"{sps:,.0f}"
        if eval_return is not None:
            fields["eval"] = f"{eval_return:.2f}"
        self._progress.update(self._task, completed=step, **fields)

    def message(self, text: str) -> None:
        """A log line (shown above the bar on a terminal, printed otherwise)."""
        if not self.enabled:
            return
        if self._progress is not None:
            self._progress.console.print(text)
        else:
            print(text, file=sys.stderr, flush=True)

    def close(self) -> None:
        """Stop the bar, if there is one."""
        if self._progress is not None:
            self._progress.stop()
            self._progress = None
