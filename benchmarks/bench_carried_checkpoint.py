"""How large a study's interrupted runs are when carried in its archive: checkpoint parts, raw and xz-compressed.

A run interrupted at a session's end is carried to the next machine in the study's archive, its checkpoint
xz-compressed (``pimbrl study archive SPEC --checkpoints``), and not carried where that is over 90 MiB.
Whether a long arm can span sessions therefore depends on its checkpoint late in the run, which this script
estimates without training that far: it trains each named arm's first planned run to ``--steps`` real
steps (stopped as a time limit stops it, with a checkpoint), measures every part of the checkpoint raw and
compressed as the carry compresses it, and extrapolates the replay buffers to their capacity (the networks
and optimisers do not grow). The extrapolation assumes the late rows compress as the early ones do; the
record gives beside it the size with the buffers not compressed at all (the rest compressed on its own).

    python benchmarks/bench_carried_checkpoint.py benchmarks/confirmatory/confirmatory-ks.yaml \\
        pimbrl redq --steps 1600 --load "two study runs"

Prints a table and writes ``benchmarks/results/carried_checkpoint_<study>.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import lzma
import os
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

import _common  # one thread per process, set before torch starts its pools
import torch

from pimbrl.experiments.carry import MAX_CARRIED_BYTES
from pimbrl.experiments.engine import plan_study
from pimbrl.experiments.spec import load_spec
from pimbrl.training import RunDirectory, RunStopped, create_run, train

PRESET = 9  # the carry's xz preset (pimbrl.experiments.carry)


def _bytes(value: Any) -> int:
    if isinstance(value, torch.Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, dict):
        return sum(_bytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(_bytes(v) for v in value)
    return 0


def _packed(value: Any) -> int:
    buf = io.BytesIO()
    torch.save(value, buf)
    return len(lzma.compress(buf.getvalue(), preset=PRESET))


def _without_buffers(state: dict) -> dict:
    """``state`` with every replay buffer's rows left out (its counters kept)."""
    out: dict = {}
    for key, value in state.items():
        if isinstance(value, dict) and {"size", "capacity", "data"} <= set(value):
            out[key] = {k: v for k, v in value.items() if k != "data"}
        elif isinstance(value, dict):
            out[key] = _without_buffers(value)
        else:
            out[key] = value
    return out


def _buffers(state: dict, where: str = "") -> list[tuple[str, dict]]:
    """Every replay buffer in a checkpoint's state (a dict with ``size``, ``capacity`` and ``data``)."""
    found = []
    for key, value in state.items():
        if isinstance(value, dict):
            if {"size", "capacity", "data"} <= set(value):
                found.append((f"{where}{key}", value))
            else:
                found.extend(_buffers(value, f"{where}{key}."))
    return found


def measure(spec_path: Path, arm: str, steps: int, folder: Path) -> dict:
    spec = load_spec(spec_path)
    planned = [r for r in plan_study(spec, folder) if r.arm == arm]
    if not planned:
        raise SystemExit(f"{spec_path} plans no arm {arm!r}")
    run = planned[0]

    def stop(name: str, r: Any) -> None:
        if name == "act" and r.t == steps:
            os.kill(os.getpid(), signal.SIGTERM)

    t0 = time.perf_counter()
    with contextlib.suppress(RunStopped):  # stopped as a time limit stops a run: with a checkpoint
        train(create_run(run.config, run.path, progress=False), on_event=stop, stop_on_signal=True)
    wall = time.perf_counter() - t0
    raw = (run.path / "checkpoints" / "latest.pt").read_bytes()
    state = RunDirectory(run.path).load_checkpoint()
    packed = len(lzma.compress(raw, preset=PRESET))
    buffers = []
    for name, buf in _buffers(state):
        rows, capacity = int(buf["size"]), int(buf["capacity"])
        size = _bytes(buf["data"])
        buffers.append(
            {
                "name": name,
                "rows": rows,
                "capacity": capacity,
                "bytes": size,
                "packed": _packed(buf["data"]),
                "row_bytes": size // max(rows, 1),
            }
        )
    rest_raw = len(raw) - sum(b["bytes"] for b in buffers)
    rest_packed = _packed(_without_buffers(state))  # the networks, optimisers and counters, compressed alone
    full_raw = rest_raw + sum(b["row_bytes"] * b["capacity"] for b in buffers)
    full_packed = rest_packed + sum(b["packed"] * b["capacity"] / max(b["rows"], 1) for b in buffers)
    uncompressed_buffers = rest_packed + sum(b["row_bytes"] * b["capacity"] for b in buffers)
    return {
        "arm": arm,
        "steps": int(state.get("t", 0)),
        "train_s": round(wall, 1),
        "checkpoint_bytes": len(raw),
        "checkpoint_packed": packed,
        "buffers": buffers,
        "full_raw": int(full_raw),
        "full_packed_estimate": int(full_packed),
        "full_packed_buffers_uncompressed": int(uncompressed_buffers),
        "carried_if_under": MAX_CARRIED_BYTES,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("spec", type=Path)
    parser.add_argument("arms", nargs="+")
    parser.add_argument("--steps", type=int, default=1600, help="real steps to train each arm's first run to")
    _common.add_load_argument(parser)
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for arm in args.arms:
            row = measure(args.spec, arm, args.steps, Path(folder))
            rows.append(row)
            mb = 1e6
            now = f"at {row['steps']:,} steps {row['checkpoint_bytes'] / mb:.1f} MB, xz {row['checkpoint_packed'] / mb:.1f} MB"
            full = f"full buffers {row['full_raw'] / mb:.0f} MB, xz about {row['full_packed_estimate'] / mb:.0f} MB"
            plain = row["full_packed_buffers_uncompressed"] / mb
            bound = f"{plain:.0f} MB with the buffers uncompressed; carried under {MAX_CARRIED_BYTES / mb:.0f} MB"
            print(f"{arm:>14}: {now}; {full} ({bound})")
    name = f"carried_checkpoint_{load_spec(args.spec).name}"
    print(f"recorded {_common.record(name, {'steps': args.steps, 'rows': rows}, load=args.load)}")


if __name__ == "__main__":
    main()
