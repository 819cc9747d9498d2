"""Pre-registration: a confirmatory study's spec is committed before its first run, and stays as committed.

When a study first runs in a directory, :func:`start_study` writes ``ROOT/study.json``: the spec's SHA-256
and the time of the first start; every later start appends its time and SHA-256 (the study engine skips a
start with nothing left to train whose spec this directory has already seen). A
spec marked ``kind: confirmatory`` must be registered when its first run starts, else that start is
refused with a one-line error: its bytes are those of a commit (read with ``git show``, whatever the index
says), the only commit that ever changed the file (a spec edited after it was committed is a new spec, in
a new file, so that running, looking and re-committing cannot re-register it), and none of its runs exist
yet. The commit, its time and the SHA-256 of the files the spec imports (a user's system) are recorded.
:func:`study_label` then calls a record confirmatory only where the spec was committed before the first run
started and never changed afterwards (the record's, the registration's and the current spec's SHA-256 all
equal), the imported files are unchanged, and every run is made, finished and of the spec's settings;
everything else is labelled exploratory, with the reason.
"""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..config import ConfigError
from ..fileio import atomic_write_bytes, read_below, strict_json
from .spec import StudySpec

__all__ = [
    "REGISTRATION_FILE",
    "check_start",
    "committed_spec",
    "imports_sha256",
    "read_registration",
    "start_study",
    "study_label",
]

#: a study directory's registration
REGISTRATION_FILE = "study.json"


def _git(directory: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["git", "-C", str(directory), *args], capture_output=True, text=True, timeout=60, check=False)


def committed_spec(path: Path, sha256: str) -> dict[str, Any] | None:
    """The commit that registered the spec at ``path``, if the spec is registrable; else ``None``.

    Registrable: the file is tracked, its bytes (SHA-256 ``sha256``) are those of the commit that last changed
    it (read with ``git show``, whatever the index says), and that commit is the only one that ever changed it
    (a spec edited after being committed is a new spec: give it a new file). ``None`` also where git is
    missing or the file is outside a repository.
    """
    import hashlib

    directory, name = path.parent, path.name
    try:
        history = _git(directory, "--literal-pathspecs", "log", "--format=%H %ct", "--follow", "--", name)
        if history.returncode != 0:
            return None
        commits = [line.split() for line in history.stdout.splitlines() if line.strip()]
        if len(commits) != 1 or len(commits[0]) != 2:
            return None
        commit, when = commits[0]
        prefix = _git(directory, "rev-parse", "--show-prefix").stdout.strip()
        blob = subprocess.run(
            ["git", "-C", str(directory), "show", f"{commit}:{prefix}{name}"], capture_output=True, timeout=60, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if blob.returncode != 0 or hashlib.sha256(blob.stdout).hexdigest() != sha256:
        return None
    return {"commit": commit, "committed_unix": int(when)}


def imports_sha256(spec: StudySpec) -> dict[str, str]:
    """The SHA-256 of each file the spec imports (a user's system is part of what a study ran).

    Keyed by the file's absolute path, in the spec's order. :func:`study_label` compares the digests in that
    order, not the paths: the spec's SHA-256 already pins its import list, and a record reported from another
    clone or machine reads the same files from another folder.
    """
    import hashlib

    out = {}
    for item in spec.imports:
        path = Path(item)
        if path.suffix == ".py" and path.is_file():
            out[item] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def read_registration(root: str | Path) -> dict[str, Any] | None:
    """The registration of the study in ``root`` (``None`` before its first run)."""
    try:
        data = read_below(Path(root), REGISTRATION_FILE, 1 << 20)
    except FileNotFoundError:
        return None
    value = strict_json(data, Path(root) / REGISTRATION_FILE)
    return value if isinstance(value, dict) else None


def check_start(
    spec: StudySpec, root: str | Path, runs: Sequence[Any] = (), registration: dict[str, Any] | None = None
) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """What :func:`start_study` refuses, checked without writing anything.

    Returns the directory's registration (``None``: the study's first start) and, for a confirmatory study's
    first start, the commit that registered its spec. Refused: a directory of another study; a confirmatory
    spec not committed unchanged; a confirmatory first start where a planned run already exists.
    ``registration``: the one the directory will hold by the start (an archive's, restored first), else
    the directory's own.
    """
    root = Path(root)
    current = registration if registration is not None else read_registration(root)
    if current is not None and current.get("study") not in (None, spec.name):
        raise ConfigError(
            f"{root} holds the study {current.get('study')!r}, not {spec.name!r}; give each study its own --run-dir"
        )
    if current is not None or spec.kind != "confirmatory":
        return current, None
    registered = committed_spec(spec.path, spec.sha256) if spec.path is not None else None
    if registered is None:
        raise ConfigError(
            f"confirmatory spec {spec.path or spec.name} is not registered: commit it, unchanged, in a commit of its "
            "own before its first run (git add SPEC && git commit; a spec changed after it was committed is a new "
            "spec: give it a new file), or mark it kind: exploratory"
        )
    existing = [str(r.path) for r in runs if (Path(r.path) / "config.json").exists()]
    if existing:
        raise ConfigError(
            f"confirmatory study {spec.name}: {existing[0]} already holds a run made before the study was registered; "
            "give the study a new --run-dir"
        )
    return None, registered


def start_study(spec: StudySpec, root: str | Path, runs: Sequence[Any] = ()) -> dict[str, Any]:
    """Record this start of ``spec`` in ``root`` (see the module docstring); returns the registration.

    ``runs``: the study's planned runs (:class:`~pimbrl.experiments.engine.StudyRun`); a confirmatory study's
    first start refuses a directory where any of them already exists (made before the registration).
    """
    root = Path(root)
    current, registered = check_start(spec, root, runs)
    now = time.time()
    if current is None:
        current = {"study": spec.name, "kind": spec.kind, "spec_sha256": spec.sha256, "first_run_started_unix": now, "starts": []}
        if registered is not None:
            current["registered"] = registered
            current["imports_sha256"] = imports_sha256(spec)
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
    registered_imports = reg.get("imports_sha256") or {}
    if not isinstance(registered_imports, dict) or list(registered_imports.values()) != list(imports_sha256(spec).values()):
        return "exploratory", "a file the spec imports (a system's code) changed after the first run started"
    if record.get("missing") or record.get("mismatched") or any(not r.get("finished") for r in record.get("runs", [])):
        return "exploratory", "runs are missing, unfinished or of other settings"
    return "confirmatory", f"registered at commit {registered['commit'][:10]} before the first run; unchanged since"
