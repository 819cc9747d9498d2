"""Run directories that cannot be hijacked, raced or silently corrupted (issue 11).

No code runs from a checkpoint (``weights_only`` loading, a versioned format with a checksum), one process
at a time writes a run directory (an OS file lock naming its holder), ``resume`` re-validates the
configuration and the checkpoint's counters and repairs the "finished" mark, stale temporary files are
removed, files honour the umask, ``compare`` refuses duplicate seeds and the kernel cache is private.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.training import RunDirectory, open_run
from pimbrl.training import rundir as rundir_module

from .test_training import TINY

ARGS = [
    "pendulum",
    "--steps", "200",
    "--warmup-steps", "100",
    "--update-after", "100",
    "--eval-every", "100",
    "--eval-episodes", "2",
    "--checkpoint-every", "100",
    *TINY,
]  # fmt: skip


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A finished tiny run, trained once; tests work on copies (:func:`run_copy`)."""
    path = tmp_path_factory.mktemp("safety") / "run"
    assert main(["train", *ARGS, "--run-dir", str(path)]) == 0
    return path


@pytest.fixture
def run_copy(finished_run: Path, tmp_path: Path) -> Path:
    """A private copy of the finished run."""
    dst = tmp_path / "run"
    shutil.copytree(finished_run, dst)
    return dst


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if "error:" in line]
    assert len(lines) == 1, err
    return lines[0]


def _mark_running(path: Path) -> None:
    payload = json.loads((path / "config.json").read_text())
    payload["status"] = "running"
    payload.pop("summary", None)
    (path / "config.json").write_text(json.dumps(payload))


# ---------------------------------------------------------------------- no code from data files
class _Planted:
    """Unpickling this object runs a shell command that creates ``marker``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.mark.parametrize("command", ["eval", "resume"])
def test_a_planted_pickle_checkpoint_is_refused_and_never_executed(command: str, run_copy: Path, tmp_path, capsys) -> None:
    marker = tmp_path / "pwned"
    buf = io.BytesIO()
    torch.save({"version": 1, "t": 100, "evil": _Planted(marker)}, buf)
    (run_copy / "checkpoints" / "latest.pt").write_bytes(buf.getvalue())
    assert main([command, str(run_copy)]) == 2
    assert not marker.exists(), "unpickling the checkpoint ran code"
    assert "written by another version of pimbrl" in _error_line(capsys)


def test_a_planted_pickle_with_a_valid_checksum_is_refused_and_never_executed(run_copy: Path, tmp_path, capsys) -> None:
    marker = tmp_path / "pwned"
    buf = io.BytesIO()
    torch.save({"version": rundir_module.CHECKPOINT_VERSION, "evil": _Planted(marker)}, buf)
    (run_copy / "checkpoints" / "latest.pt").write_bytes(rundir_module.pack_checkpoint(buf.getvalue()))
    assert main(["eval", str(run_copy)]) == 2
    assert not marker.exists(), "unpickling the checkpoint ran code"
    assert "holds more than tensors and plain data" in _error_line(capsys)
    with pytest.raises(rundir_module.CheckpointError):
        RunDirectory(run_copy).load_checkpoint()
    assert not marker.exists()


def test_every_part_of_a_checkpoint_loads_as_plain_data(tmp_path) -> None:
    rng = np.random.default_rng(2**100)
    rng.random(7)
    state = {"rng": rng.bit_generator.state, "x": torch.arange(3.0), "n": np.int64(5), "f": np.float32(0.5)}
    assert state["rng"]["state"]["state"] > 2**64  # a 128-bit Python int
    run_dir = RunDirectory(tmp_path)
    run_dir.save_checkpoint(state)
    loaded = run_dir.load_checkpoint()
    assert loaded["rng"] == rng.bit_generator.state and torch.equal(loaded["x"], state["x"])
    assert loaded["n"] == 5 and type(loaded["n"]) is int and loaded["f"] == 0.5


def test_a_flipped_byte_is_detected_by_resume_and_eval(run_copy: Path, capsys) -> None:
    path = run_copy / "checkpoints" / "latest.pt"
    data = bytearray(path.read_bytes())
    data[len(data) * 3 // 5] ^= 0x01
    path.write_bytes(bytes(data))
    for command in ("eval", "resume"):
        assert main([command, str(run_copy)]) == 2
        line = _error_line(capsys)
        assert "is corrupted (checksum mismatch)" in line and str(path) in line


def test_a_truncated_or_garbage_checkpoint_is_a_one_line_error(run_copy: Path, capsys) -> None:
    path = run_copy / "checkpoints" / "latest.pt"
    full = path.read_bytes()
    for data in (full[: len(full) // 2], full[:10], b"", b"\x00" * 100):
        path.write_bytes(data)
        assert main(["eval", str(run_copy)]) == 2
        assert str(path) in _error_line(capsys)


def test_a_checkpoint_of_another_format_version_is_a_clear_error(run_copy: Path, capsys) -> None:
    path = run_copy / "checkpoints" / "latest.pt"
    data = path.read_bytes()
    version = str(rundir_module.CHECKPOINT_VERSION).encode()
    path.write_bytes(data.replace(b" " + version + b" ", b" 99 ", 1))
    assert main(["resume", str(run_copy)]) == 2
    line = _error_line(capsys)
    assert "written by another version of pimbrl (checkpoint format 99" in line


# ---------------------------------------------------------------------- one process per run directory
HOLDER = """
import sys, time
from pimbrl.training import open_run
run = open_run(sys.argv[1], progress=False)
print("locked", flush=True)
time.sleep(120)
"""


@pytest.mark.slow
def test_a_second_process_on_a_run_directory_gets_a_clear_error(run_copy: Path, capsys) -> None:
    _mark_running(run_copy)
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(run_copy)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        assert main(["resume", str(run_copy), "--quiet"]) == 2
        line = _error_line(capsys)
        assert "is in use by another pimbrl process" in line and f"pid {holder.pid}" in line
        assert main(["eval", str(run_copy)]) == 0  # reading needs no lock
        capsys.readouterr()
        holder.send_signal(signal.SIGKILL)  # the OS drops the lock of a dead process
        holder.wait()
        assert main(["resume", str(run_copy), "--quiet"]) == 0
        assert json.loads((run_copy / "config.json").read_text())["status"] == "finished"
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()


@pytest.mark.slow
def test_two_racing_trains_into_one_directory_exactly_one_wins(tmp_path) -> None:
    run = tmp_path / "race"
    cmd = [sys.executable, "-m", "pimbrl.cli", "train", *ARGS, "--run-dir", str(run)]
    procs = [subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(timeout=300), p.communicate()[1]) for p in procs]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    loser = next(err for code, err in results if code == 2)
    assert "is in use by another pimbrl process" in loser or "already holds a run" in loser
    rows = RunDirectory(run).evaluations.read()
    assert [r["step"] for r in rows] == ["100", "200"]  # every row once


def test_compare_refuses_duplicate_seeds(tmp_path, capsys) -> None:
    from pimbrl.experiments.compare import plan_runs

    root = tmp_path / "cmp"
    assert main(["compare", "pendulum", "--methods", "mfrl", "--seeds", "0,0", "--run-dir", str(root), "--steps", "200"]) == 2
    assert "seed 0 is given twice" in _error_line(capsys)
    assert not root.exists()
    with pytest.raises(ValueError, match="seed 3 is given twice"):
        plan_runs("pimbrl/Pendulum-v0", ["mfrl"], [3, 1, 3], root)


# ---------------------------------------------------------------------- resume re-validates
@pytest.mark.parametrize(
    ("edit", "flags"),
    [({"utd": -1.0}, ["--utd", "-1"]), ({"agent": {"name": "td3", "gamma": 7.5}}, ["--agent.gamma", "7.5"])],
)
def test_resume_revalidates_an_edited_config(edit: dict, flags: list[str], run_copy: Path, tmp_path, capsys) -> None:
    assert main(["train", "pendulum", "--run-dir", str(tmp_path / "never"), *flags, "--quiet"]) == 2
    message = _error_line(capsys).split("error: ", 1)[1]
    payload = json.loads((run_copy / "config.json").read_text())
    for key, value in edit.items():
        if isinstance(value, dict):
            payload["config"][key].update(value)
        else:
            payload["config"][key] = value
    payload["status"] = "running"
    (run_copy / "config.json").write_text(json.dumps(payload))
    assert main(["resume", str(run_copy), "--quiet"]) == 2
    line = _error_line(capsys)
    assert message in line and "config.json" in line


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda s: s.update(t=-5), "step -5"),
        (lambda s: s.update(t=10**6), "beyond the run's total_steps"),
        (lambda s: s["collector"].update(episode=-1), "collector.episode"),
        (lambda s: s["agent"].update(n_updates=-3), "agent.n_updates"),
        (lambda s: s.pop("real"), "lacks 'real'"),
    ],
)
def test_resume_checks_the_checkpoints_counters(edit, message: str, run_copy: Path, capsys) -> None:
    run_dir = RunDirectory(run_copy)
    state = run_dir.load_checkpoint()
    edit(state)
    run_dir.save_checkpoint({k: v for k, v in state.items() if k != "version"})
    _mark_running(run_copy)
    assert main(["resume", str(run_copy), "--quiet"]) == 2
    assert message in _error_line(capsys)


# ---------------------------------------------------------------------- the finished mark, temporaries, modes
def test_a_kill_between_the_final_checkpoint_and_the_finished_mark_is_repaired(tmp_path, monkeypatch, capsys) -> None:
    run = tmp_path / "run"

    class Killed(BaseException):
        pass

    def killed(self, **fields):
        if fields.get("status") == "finished":
            raise Killed
        return original(self, **fields)

    original = RunDirectory.update_status
    monkeypatch.setattr(RunDirectory, "update_status", killed)
    with pytest.raises(Killed):
        main(["train", *ARGS, "--run-dir", str(run)])
    monkeypatch.undo()
    assert RunDirectory(run).status == "running" and RunDirectory(run).load_checkpoint()["t"] == 200
    # opening the run for writing repairs the mark, whoever opens it
    open_run(run, progress=False).run_dir.close()
    payload = json.loads((run / "config.json").read_text())
    assert payload["status"] == "finished" and payload["summary"]["steps"] == 200
    _mark_running(run)
    assert main(["resume", str(run), "--quiet"]) == 0
    assert "already finished" in capsys.readouterr().out
    payload = json.loads((run / "config.json").read_text())
    assert payload["status"] == "finished" and payload["summary"]["steps"] == 200


def test_stale_temporary_files_are_removed_when_a_run_is_opened_for_writing(run_copy: Path) -> None:
    stale = [run_copy / ".config.json.k2j3h4.tmp", run_copy / "checkpoints" / ".latest.pt.abc123.tmp"]
    for path in stale:
        path.write_bytes(b"half")
    keep = run_copy / "notes.tmp"  # not one of ours
    keep.write_text("mine")
    assert main(["eval", str(run_copy)]) == 0  # reading changes nothing
    assert all(p.exists() for p in stale)
    assert main(["resume", str(run_copy), "--quiet"]) == 0
    assert not any(p.exists() for p in stale) and keep.exists()


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o077, 0o600)])
def test_files_honour_the_umask(umask: int, mode: int, tmp_path) -> None:
    old = os.umask(umask)
    try:
        run_dir = RunDirectory(tmp_path / "run")
        run_dir.write_config({"status": "running", "config": {}})
        run_dir.save_checkpoint({"t": 0})
        rundir_module.atomic_write_bytes(tmp_path / "other.txt", b"x")
        from pimbrl.fileio import atomic_write_bytes
        from pimbrl.plotting import plt, save_figure

        atomic_write_bytes(tmp_path / "summary.json", b"{}")
        save_figure(plt.figure(), tmp_path / "figure.png")
    finally:
        os.umask(old)
    written = (
        run_dir.config_path,
        run_dir.checkpoint_path,
        tmp_path / "other.txt",
        tmp_path / "summary.json",
        tmp_path / "figure.png",
    )
    for path in written:
        assert stat.S_IMODE(path.stat().st_mode) == mode, path


# ---------------------------------------------------------------------- the compiled-kernel cache
def _plant(path: Path) -> None:
    path.mkdir(parents=True)
    os.chmod(path, 0o777)
    if os.getuid() == 0:
        os.chown(path, 65534, 65534)  # another user's directory


def test_the_kernel_cache_refuses_directories_others_can_write(tmp_path, monkeypatch) -> None:
    from pimbrl.physics import kernels

    primary, tmp = tmp_path / "cache", tmp_path / "tmp"
    _plant(primary / "kernels")
    _plant(tmp / f"pimbrl-kernels-{os.getuid()}")
    monkeypatch.setenv("PIMBRL_CACHE_DIR", str(primary))
    monkeypatch.setattr(kernels.tempfile, "gettempdir", lambda: str(tmp))
    monkeypatch.setattr(kernels.tempfile, "tempdir", str(tmp))
    monkeypatch.setattr(kernels, "_PROCESS_DIR", None)
    with pytest.warns(UserWarning, match="not caching"):
        path = kernels._write_source("probe.py", "x = 1\n")
    assert path.parent not in (primary / "kernels", tmp / f"pimbrl-kernels-{os.getuid()}")
    info = path.parent.stat()
    assert info.st_uid == os.getuid() and stat.S_IMODE(info.st_mode) == 0o700
    assert path.read_text() == "x = 1\n"


def test_the_kernel_cache_falls_back_to_a_private_per_user_directory(tmp_path, monkeypatch) -> None:
    from pimbrl.physics import kernels

    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("PIMBRL_CACHE_DIR", str(blocker / "cache"))  # cannot be created
    monkeypatch.setattr(kernels.tempfile, "gettempdir", lambda: str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    path = kernels._write_source("probe.py", "x = 2\n")
    assert path.parent == tmp_path / "tmp" / f"pimbrl-kernels-{os.getuid()}"
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    # a safe primary cache directory is used as it is
    monkeypatch.setenv("PIMBRL_CACHE_DIR", str(tmp_path / "good"))
    assert kernels._write_source("probe.py", "x = 3\n").parent == tmp_path / "good" / "kernels"
    assert not (stat.S_IMODE((tmp_path / "good" / "kernels").stat().st_mode) & 0o022)


def test_lock_file_names_its_holder(run_copy: Path) -> None:
    run = open_run(run_copy, progress=False)
    try:
        holder = json.loads((run_copy / "run.lock").read_text())
        assert holder["pid"] == os.getpid() and holder["host"] and "command" in holder
        with pytest.raises(rundir_module.RunLockedError, match=f"pid {os.getpid()}"):
            open_run(run_copy, progress=False)  # a second open, even in one process, is refused
    finally:
        run.run_dir.close()
    open_run(run_copy, progress=False).run_dir.close()  # released
