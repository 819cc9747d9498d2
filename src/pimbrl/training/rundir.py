"""Run directories: resolved config, CSV logs that survive a crash, atomic checkpoints.

Layout of a run directory::

    config.json          resolved configuration, package versions, command line, status
    evaluations.csv      one row per evaluation: step, return_mean, return_min, return_max, ..., wall_s
    metrics.csv          training metrics every ``log_every`` steps (losses, update-to-data ratio, speed)
    episodes.csv         one row per training episode
    checkpoints/latest.pt  the full training state (written atomically)
    tb/                  TensorBoard events (optional)

Every file is written so that a process killed at any moment (``kill -9``) leaves a consistent directory:
checkpoints and the config are written to a temporary file, fsynced and renamed; CSV rows are appended
and flushed, and on resume each CSV is cut back to the rows of the checkpointed step (a torn last line
is dropped).
"""

from __future__ import annotations

import csv
import io
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any, ClassVar

import torch

__all__ = ["CsvLog", "RunDirectory", "atomic_write_bytes", "package_versions", "steps_to_threshold"]

CHECKPOINT_VERSION = 1


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a fsynced temporary file and an atomic rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    try:  # make the rename itself durable
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:
        pass


def steps_to_threshold(evaluations: list[dict[str, Any]], threshold: float | None) -> int | None:
    """First evaluation step whose mean return reaches ``threshold`` (``None`` if never)."""
    if threshold is None:
        return None
    for row in evaluations:
        if float(row["return_mean"]) >= threshold:
            return int(float(row["step"]))
    return None


def package_versions() -> dict[str, str]:
    """Versions of Python, pimbrl and its main dependencies, recorded in a run's configuration file."""
    import gymnasium
    import numba
    import numpy

    from .. import __version__

    return {
        "pimbrl": __version__,
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "gymnasium": gymnasium.__version__,
        "numba": numba.__version__,
    }


class CsvLog:
    """An append-only CSV file with a fixed header; rows are flushed as they are written."""

    def __init__(self, path: Path, columns: list[str]) -> None:
        self.path = path
        self.columns = columns
        self._fh: io.TextIOWrapper | None = None

    def _open(self) -> io.TextIOWrapper:
        if self._fh is None:
            new = not self.path.exists() or self.path.stat().st_size == 0
            self._fh = open(self.path, "a", newline="")  # noqa: SIM115 - kept open for appends
            if new:
                self._fh.write(",".join(self.columns) + "\n")
                self._fh.flush()
        return self._fh

    def append(self, row: dict[str, Any]) -> None:
        """Write one row (its keys outside the header are ignored, missing ones left empty) and flush."""
        fh = self._open()
        writer = csv.DictWriter(fh, fieldnames=self.columns, extrasaction="ignore", lineterminator="\n")
        writer.writerow({k: _fmt(row.get(k)) for k in self.columns})
        fh.flush()

    def truncate_after(self, step: int) -> None:
        """Keep only complete rows with ``step <= step`` (used when resuming from a checkpoint)."""
        self.close()
        if not self.path.exists():
            return
        text = self.path.read_text()
        lines = text.split("\n")
        if not text.endswith("\n"):
            lines = lines[:-1]  # a torn last line from a killed process
        kept = [lines[0] if lines and lines[0] else ",".join(self.columns)]
        for line in lines[1:]:
            if not line:
                continue
            fields = line.split(",")
            if len(fields) != len(self.columns):
                continue
            try:
                if int(float(fields[0])) <= step:
                    kept.append(line)
            except ValueError:
                continue
        atomic_write_bytes(self.path, ("\n".join(kept) + "\n").encode())

    def read(self) -> list[dict[str, str]]:
        """All rows as dictionaries of strings (none if the file does not exist)."""
        if not self.path.exists():
            return []
        with open(self.path, newline="") as fh:
            return list(csv.DictReader(fh))

    def close(self) -> None:
        """Close the file if it is open (a later append reopens it)."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, torch.Tensor):
        return repr(float(v))
    return str(v)


class RunDirectory:
    """A training run's directory (see the module docstring for its layout)."""

    EVAL_COLUMNS: ClassVar[list[str]] = [
        "step",
        "return_mean",
        "return_min",
        "return_max",
        "return_std",
        "length_mean",
        "episodes",
        "updates",
        "wall_s",
    ]
    EPISODE_COLUMNS: ClassVar[list[str]] = ["step", "episode", "return", "length"]

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.config_path = self.path / "config.json"
        self.checkpoint_path = self.path / "checkpoints" / "latest.pt"
        self.evaluations = CsvLog(self.path / "evaluations.csv", self.EVAL_COLUMNS)
        self.episodes = CsvLog(self.path / "episodes.csv", self.EPISODE_COLUMNS)
        self._metrics: CsvLog | None = None

    # ------------------------------------------------------------------ config
    def write_config(self, payload: dict[str, Any]) -> None:
        """Write ``config.json`` atomically."""
        atomic_write_bytes(self.config_path, (json.dumps(payload, indent=2, sort_keys=False) + "\n").encode())

    def read_config(self) -> dict[str, Any]:
        """The contents of ``config.json``; ``FileNotFoundError`` if this is not a run directory."""
        if not self.config_path.exists():
            raise FileNotFoundError(f"{self.path} is not a pimbrl run directory (no config.json)")
        return json.loads(self.config_path.read_text())

    @property
    def status(self) -> str | None:
        """``"running"``, ``"finished"``, or ``None`` where there is no readable run."""
        try:
            return self.read_config().get("status")
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def result(self, threshold: float | None = None) -> dict[str, Any] | None:
        """What a run has reached so far (``None`` without evaluations).

        That is its steps, steps to ``threshold`` (default: the run's own), final and best mean test
        return, wall-clock, updates and its curves.
        """
        if self.status is None:
            return None
        rows = self.evaluations.read()
        if not rows:
            return None
        payload = self.read_config()
        if threshold is None:
            threshold = payload["config"].get("threshold")
        steps = int(float(rows[-1]["step"]))
        updates = int(float(rows[-1]["updates"]))
        summary = payload.get("summary") or {}
        return {
            "finished": payload.get("status") == "finished",
            "steps": steps,
            "steps_to_threshold": steps_to_threshold(rows, threshold),
            "final_return": float(rows[-1]["return_mean"]),
            "best_return": max(float(r["return_mean"]) for r in rows),
            "wall_s": float(summary.get("wall_s", rows[-1]["wall_s"])),
            "updates": updates,
            "update_to_data": updates / max(steps, 1),
            "curve": {k: [float(r[k]) for r in rows] for k in ("step", "return_mean", "return_min", "return_max")},
        }

    def update_status(self, **fields: Any) -> None:
        """Set top-level ``fields`` of ``config.json`` (e.g. ``status``), keeping the rest."""
        payload = self.read_config()
        payload.update(fields)
        self.write_config(payload)

    # ------------------------------------------------------------------ metrics
    def metrics(self, columns: list[str]) -> CsvLog:
        """The metrics log; its columns are fixed by the first call (or the existing file's header)."""
        if self._metrics is None:
            path = self.path / "metrics.csv"
            if path.exists() and path.stat().st_size > 0:
                with open(path) as fh:
                    columns = fh.readline().strip().split(",")
            self._metrics = CsvLog(path, columns)
        return self._metrics

    def truncate_logs(self, step: int) -> None:
        """Drop the rows of every log after ``step`` (used when resuming from a checkpoint)."""
        for log in (self.evaluations, self.episodes):
            log.truncate_after(step)
        path = self.path / "metrics.csv"
        if path.exists():
            self.metrics([]).truncate_after(step)

    def close(self) -> None:
        """Close the open log files."""
        for log in (self.evaluations, self.episodes, self._metrics):
            if log is not None:
                log.close()

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, state: dict[str, Any]) -> None:
        """Write ``state`` with the checkpoint format version to ``checkpoints/latest.pt`` atomically."""
        buf = io.BytesIO()
        torch.save({"version": CHECKPOINT_VERSION, **state}, buf)
        atomic_write_bytes(self.checkpoint_path, buf.getvalue())

    def load_checkpoint(self) -> dict[str, Any]:
        """The latest checkpoint; ``FileNotFoundError`` if there is none, ``ValueError`` if its version differs."""
        if not self.checkpoint_path.exists():
            raise FileNotFoundError(f"no checkpoint in {self.path} (expected {self.checkpoint_path})")
        state = torch.load(self.checkpoint_path, map_location="cpu", weights_only=False)
        if state.get("version") != CHECKPOINT_VERSION:
            raise ValueError(
                f"checkpoint {self.checkpoint_path} has version {state.get('version')}, expected {CHECKPOINT_VERSION}"
            )
        return state
