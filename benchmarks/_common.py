"""Helpers shared by the benchmark scripts: one thread everywhere, robust timing, recorded results."""

from __future__ import annotations

import os

# Pin every thread pool to one thread *before* NumPy, Numba or torch start theirs.
for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import TYPE_CHECKING  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

if TYPE_CHECKING:
    from pimbrl.training import Run

REPOSITORY = Path(__file__).resolve().parent.parent
RESULTS = REPOSITORY / "benchmarks" / "results"


def time_call(fn: Callable[[], object], min_time: float = 0.2, repeats: int = 7) -> float:
    """Fastest of ``repeats`` measurements of the mean seconds per call (each repeat >= ``min_time``/4).

    The minimum, not the median: on a shared machine, noise only ever adds time.
    """
    fn()  # warm-up (compilation, caches)
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        if time.perf_counter() - t0 >= min_time / 4 or n >= 1 << 20:
            break
        n *= 2
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        samples.append((time.perf_counter() - t0) / n)
    return min(samples)


def machine() -> dict[str, str]:
    from pimbrl.training.rundir import cpu_identity, cpu_model, source_commit

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu": cpu_model(),
        "cpu_id": cpu_identity() or "unknown",
        "numpy": np.__version__,
        "commit": source_commit() or "unknown",
        "threads": "1 (NUMBA/OMP/MKL/OPENBLAS_NUM_THREADS=1, torch.set_num_threads(1))",
    }


def add_load_argument(parser: argparse.ArgumentParser) -> None:
    """``--load``: what else ran on the cores during the measurement, in words; :func:`record` keeps it."""
    parser.add_argument("--load", default=None, help="what else ran on the cores meanwhile, in words ('idle' if nothing)")


def measurement_spec(script: Path, argv: list[str]) -> tuple[dict, str]:
    """A measurement's spec, ``{"script", "argv"}``, and its SHA-256: of the script's text and its arguments.

    A benchmark script is the spec of what it measures (what runs, on what, how often, what is kept): its
    record names the script (relative to the repository), its arguments and the hash of both, as a study
    record names its spec's hash, so a page can say which text made a figure, and a changed script shows.
    """
    where = script.resolve()
    shown = where.relative_to(REPOSITORY).as_posix() if where.is_relative_to(REPOSITORY) else where.as_posix()
    digest = hashlib.sha256(where.read_bytes() + b"\0" + json.dumps(argv).encode())
    return {"script": shown, "argv": argv}, digest.hexdigest()


def without_load(argv: list[str]) -> list[str]:
    """``argv`` less ``--load WORDS`` (or ``--load=WORDS``, or an abbreviation argparse takes, ``--lo`` and up).

    What shared the cores is kept beside the spec, not in it.
    """
    out: list[str] = []
    skip = False
    for arg in argv:
        name = arg.split("=", 1)[0]
        if skip:
            skip = False
        elif len(name) >= 4 and "--load".startswith(name):
            skip = "=" not in arg
        else:
            out.append(arg)
    return out


def record(name: str, payload: dict, load: str | None = None) -> Path:
    """Write ``payload`` to ``benchmarks/results/<name>.json`` with the machine, the time and ``load`` (if given).

    The record also names its measurement spec: the script that wrote it (the ``__main__`` module), its
    arguments but ``--load`` and their SHA-256 (:func:`measurement_spec`).
    """
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    main_file = getattr(sys.modules["__main__"], "__file__", None)
    spec: dict = {}
    if main_file:
        text, digest = measurement_spec(Path(main_file), without_load(sys.argv[1:]))
        spec = {"spec": text, "spec_sha256": digest}
    payload = {"machine": machine(), "unix_time": time.time(), **spec, **({"load": load} if load else {}), **payload}
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(payload, indent=2))
    os.replace(tmp, path)
    return path


def load_checkpointed_run(run_dir: Path) -> Run:
    """The run in ``run_dir`` at its latest checkpoint, only read; exits with a message if it has none yet."""
    from pimbrl.training import load_run

    try:
        return load_run(run_dir, require_checkpoint=True)
    except FileNotFoundError as exc:
        raise SystemExit(str(exc)) from None
