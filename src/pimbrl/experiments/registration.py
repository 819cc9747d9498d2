"""Pre-registration: a confirmatory study's spec is committed before its first run, and stays as committed.

When a study first runs in a directory, :func:`start_study` writes ``ROOT/study.json``: the spec's SHA-256
and the time of the first start; every later start appends the SHA-256 it ran with when that differs. A
spec marked ``kind: confirmatory`` must be committed in git, without uncommitted changes, when its first
run starts (else that start is refused with a one-line error); the commit that last changed it and that
commit's time are recorded. :func:`study_label` then calls a record confirmatory only where the spec was
committed before the first run started and never changed afterwards (the record's, the registration's and
the current spec's SHA-256 all equal); everything else is labelled exploratory, with the reason.
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

from ..config import ConfigError
from ..fileio import atomic_write_bytes, read_below, strict_json
from .spec import StudySpec

__all__ = ["REGISTRATION_FILE", "committed_spec", "read_registration", "start_study", "study_label"]

#: a study directory's registration
REGISTRATION_FILE = "study.json"


def _git(directory: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["git", "-C", str(directory), *args], capture_output=True, text=True, timeout=60, check=False)


def committed_spec(path: Path) -> dict[str, Any] | None:
    """The commit that last changed the spec at ``path`` and its time, if the file is committed and clean.

    ``None`` where git is missing, the file is outside a repository, untracked, or has uncommitted changes.
    """
    directory, name = path.parent, path.name
    try:
        tracked = _git(directory, "ls-files", "--error-unmatch", "--", name)
        if tracked.returncode != 0:
            return None
        dirty = _git(directory, "status", "--porcelain", "--", name)
        if dirty.returncode != 0 or dirty.stdout.strip():
            return None
        last = _git(directory, "log", "-1", "--format=%H %ct", "--", name)
    except (OSError, subprocess.SubprocessError):
        return None
    parts = last.stdout.split()
    if last.returncode != 0 or len(parts) != 2:
        return None
    return {"commit": parts[0], "committed_unix": int(parts[1])}


def read_registration(root: str | Path) -> dict[str, Any] | None:
    """The registration of the study in ``root`` (``None`` before its first run)."""
    try:
        data = read_below(Path(root), REGISTRATION_FILE, 1 << 20)
    except FileNotFoundError:
        return None
    value = strict_json(data, Path(root) / REGISTRATION_FILE)
    return value if isinstance(value, dict) else None


def start_study(spec: StudySpec, root: str | Path) -> dict[str, Any]:
    """Record this start of ``spec`` in ``root`` (see the module docstring); returns the registration."""
    root = Path(root)
    current = read_registration(root)
    if current is not None and current.get("study") not in (None, spec.name):
        raise ConfigError(
            f"{root} holds the study {current.get('study')!r}, not {spec.name!r}; give each study its own --run-dir"
        )
    now = time.time()
    if current is None:
        current = {"study": spec.name, "kind": spec.kind, "spec_sha256": spec.sha256, "first_run_started_unix": now, "starts": []}
        if spec.kind == "confirmatory":
            registered = committed_spec(spec.path) if spec.path is not None else None
            if registered is None:
                raise ConfigError(
                    f"confirmatory spec {spec.path or spec.name} is not committed (or has uncommitted changes): commit it "
                    "before its first run (git add SPEC && git commit), or mark it kind: exploratory"
                )
            current["registered"] = registered
    starts = current.setdefault("starts", [])
    starts.append({"unix": now, "spec_sha256": spec.sha256})
    seen = current.setdefault("spec_sha256_seen", [])
    if spec.sha256 not in seen:
        seen.append(spec.sha256)
    atomic_write_bytes(root / REGISTRATION_FILE, (json.dumps(current, indent=1) + "\n").encode())
    return current


def study_label(spec: StudySpec, record: dict[str, Any]) -> tuple[str, str]:
    """``("confirmatory", why)`` or ``("exploratory", why)`` for a record of ``spec``."""
    if spec.kind != "confirmatory":
        return "exploratory", "the spec is exploratory"
    reg = record.get("registration") or {}
    registered = reg.get("registered")
    if not registered:
        return "exploratory", "the spec was not registered (committed) before its first run"
    if registered.get("committed_unix", float("inf")) > reg.get("first_run_started_unix", float("-inf")):
        return "exploratory", "the spec was committed after its first run started"
    shas = {reg.get("spec_sha256"), record.get("spec_sha256"), spec.sha256, *reg.get("spec_sha256_seen", [])}
    if len(shas) != 1:
        return "exploratory", "the spec changed after its first run started (its SHA-256 differs from the registered one)"
    return "confirmatory", f"registered at commit {registered['commit'][:10]} before the first run; unchanged since"
