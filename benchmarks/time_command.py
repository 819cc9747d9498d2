"""Time one shell command (the README's main job, the test tiers, CI) and record its wall-clock.

The README's figures for "how long does this take" come from here, not from memory: each entry names the
command, the directory it ran in and that checkout's commit, the CPU model, how many cores the machine had,
what else ran on them (``--load``, in words: a number that depends on it means little without it) and the exit
status. A failing command is recorded with its status, never as a timing of success. Each entry also names its
measurement spec, the command and this script, with the SHA-256 of both (as benchmarks/_common.py's records do).

    python benchmarks/time_command.py readme-main-job --cwd /tmp/fresh --load "a study's two training processes" \
        -- 'python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/pimbrl compare burgers ...'

Entries accumulate in benchmarks/results/command_timings.json (newest last); the command's own output (its
stderr merged into its stdout) goes to this process's stdout as it comes, and the entry keeps its last
non-empty line (``last_line``: for pytest, the counts of passed and skipped tests; since 2026-12-07).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
RECORD = RESULTS / "command_timings.json"


def _commit(cwd: Path) -> str:
    done = subprocess.run(["git", "-C", str(cwd), "rev-parse", "HEAD"], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{cwd} is not a git checkout (git rev-parse: {done.stderr.strip()}); give --cwd a clone")
    dirty = subprocess.run(
        ["git", "-C", str(cwd), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True
    )
    return done.stdout.strip() + ("+uncommitted changes" if dirty.stdout.strip() else "")


def _machine() -> dict[str, object]:
    # Not _common.machine(): importing _common pins every thread pool through os.environ, which the timed
    # command would inherit, so it would time something else than the README's command.
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from pimbrl.training.rundir import cpu_identity, cpu_model

    return {"cpu": cpu_model(), "cpu_id": cpu_identity(), "cores": os.cpu_count()}


def measurement_spec(command: str) -> tuple[dict[str, str], str]:
    """The spec of a timing, ``{"script", "command"}``, and the SHA-256 of this script's text and the command."""
    digest = hashlib.sha256(Path(__file__).resolve().read_bytes() + b"\0" + command.encode())
    return {"script": "benchmarks/time_command.py", "command": command}, digest.hexdigest()


def read_timings(path: Path | None = None) -> list[dict[str, object]]:
    """The recorded entries of ``path`` (default: the record), oldest first (none where the file does not exist)."""
    path = RECORD if path is None else path
    if not path.is_file():
        return []
    entries = json.loads(path.read_text())
    if not isinstance(entries, list):
        raise SystemExit(f"{path} is not a list of timing entries; move it aside and time again")
    return entries


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("name", help="what is timed, e.g. readme-main-job, fast-tier, ci")
    parser.add_argument("--cwd", type=Path, default=Path.cwd(), help="the checkout the command runs in")
    parser.add_argument("--load", required=True, help="what else ran on the cores meanwhile, in words ('idle' if nothing)")
    argv = sys.argv[1:] if argv is None else argv
    if "--" not in argv:
        parser.error("give the command after --")
    cut = argv.index("--")
    args = parser.parse_args(argv[:cut])
    command = " ".join(argv[cut + 1 :]).strip()
    if not command:
        parser.error("give the command after --")
    cwd = args.cwd.resolve()
    commit = _commit(cwd)
    start = time.time()
    t0 = time.perf_counter()
    last_line = ""
    with subprocess.Popen(
        command, shell=True, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace"
    ) as child:
        assert child.stdout is not None
        for line in child.stdout:  # passed through as it comes; the last non-empty one is kept
            sys.stdout.write(line)
            sys.stdout.flush()
            last_line = line.strip() or last_line
    status = child.returncode
    wall = time.perf_counter() - t0
    spec, digest = measurement_spec(command)
    entry = {
        "name": args.name,
        "command": command,
        "spec": spec,
        "spec_sha256": digest,
        "cwd": str(cwd),
        "commit": commit,
        "machine": _machine(),
        "load": args.load,
        "started_unix": start,
        "wall_s": round(wall, 1),
        "exit_status": status,
        "last_line": last_line,
    }
    entries = [*read_timings(), entry]
    RESULTS.mkdir(parents=True, exist_ok=True)
    tmp = RECORD.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(entries, indent=2) + "\n")
    os.replace(tmp, RECORD)
    minutes, seconds = divmod(round(wall), 60)
    print(f"{args.name}: {minutes} min {seconds} s, exit status {status} (recorded in {RECORD})", file=sys.stderr)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
