"""Progress display: a rich progress bar on a terminal, plain log lines otherwise.

The bar fits the terminal: on a narrow one it drops the elapsed time, then the bar itself, then the speed,
in that order, and the label names the environment briefly (``pimbrl/KuramotoSivashinsky-v0`` -> ``KS``).
"""

from __future__ import annotations

import re
import sys
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    Progress,
    ProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Column

from ..systems import get_system

__all__ = ["TrainingProgress", "short_label"]


def _short(env_id: str) -> str:
    system = get_system(env_id)
    return system.name if system is not None else env_id


def short_label(label: str) -> str:
    """``label`` with each system's id shortened to its label (``<Name>``; ``KS`` for Kuramoto-Sivashinsky)."""
    return re.sub(r"[\w.-]+/[\w.-]+-v\d+", lambda m: _short(m.group(0)), label)


def _text(template: str, width: int) -> TextColumn:
    return TextColumn(template, table_column=Column(no_wrap=True, min_width=width))


class TrainingProgress:
    """Shows steps, the last evaluation return and steps per second."""

    def __init__(self, total: int, start: int, label: str, enabled: bool = True) -> None:
        self.console = Console(stderr=True)
        self.interactive = enabled and self.console.is_terminal
        self.enabled = enabled
        self.label = short_label(label)
        self.total = total
        self._progress: Progress | None = None
        if self.interactive:
            self._progress = self.build(self.console)
            self._task = self._progress.add_task(self.label, total=total, completed=start, eval="-", sps="-")
            self._progress.start()

    def build(self, console: Console) -> Progress:
        """A progress display whose columns fit the width of ``console`` (without a task)."""
        steps = len(f"{self.total:,d}")
        # (name, width) in order of importance; each column is separated from the next by one space
        wanted = [
            ("steps", 2 * steps + 1),
            ("eval", len("eval -12345.67")),
            ("label", min(len(self.label), 32)),
            ("remaining", 7),
            ("sps", len("12,345 steps/s")),
            ("bar", 10),
            ("elapsed", 7),
        ]
        room = console.width - 1
        chosen: dict[str, int] = {}
        for name, width in wanted:
            if sum(chosen.values()) + len(chosen) + width <= room:
                chosen[name] = width
        if "bar" in chosen:  # the bar takes what is left, up to 40 columns
            chosen["bar"] = min(40, room - (sum(chosen.values()) - chosen["bar"]) - (len(chosen) - 1))
        columns: dict[str, ProgressColumn] = {
            "label": TextColumn(
                "[bold]{task.description}", table_column=Column(no_wrap=True, overflow="ellipsis", max_width=chosen.get("label"))
            ),
            "bar": BarColumn(bar_width=chosen.get("bar")),
            "steps": _text("{task.completed:,.0f}/{task.total:,.0f}", 0),
            "eval": _text("eval {task.fields[eval]}", 0),
            "sps": _text("{task.fields[sps]} steps/s", 0),
            "elapsed": TimeElapsedColumn(),
            "remaining": TimeRemainingColumn(),
        }
        order = ["label", "bar", "steps", "eval", "sps", "elapsed", "remaining"]
        return Progress(*(columns[name] for name in order if name in chosen), console=console)

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
