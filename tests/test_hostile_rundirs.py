"""Run directories and caches are hostile input (issue 32).

A run directory may come from someone else. No symlink inside it is followed (the lock, the CSV logs, the
checkpoints folder), no FIFO or device is read, every JSON field read has its type checked and every number
must be finite, the env id in a run is a registered id (never Gymnasium's ``module:id``, which imports
code), a driver never moves or reports as finished a run whose lock is held, the KS pool cache is checked
like the kernel cache, and a file-size limit (EFBIG) is a one-line error that keeps the last checkpoint.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import resource
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from pimbrl.cli import main
from pimbrl.systems import KSPoolConfig
from pimbrl.training import RunDirectory

from . import test_run_safety
from .test_run_safety import _error_line, _mark_running

# the fixtures of the issue-11 safety tests: a finished tiny run (trained once per module) and a copy per test
finished_run = test_run_safety.finished_run
run_copy = test_run_safety.run_copy

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@contextlib.contextmanager
def within(seconds: int) -> Iterator[None]:
    """Fail (instead of hanging the suite) if the block takes longer than ``seconds``."""

    def expired(signum, frame):
        raise TimeoutError(f"took longer than {seconds} s (a hang)")

    old = signal.signal(signal.SIGALRM, expired)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _edit_config(run: Path, edit) -> None:
    payload = json.loads((run / "config.json").read_text())
    edit(payload)
    (run / "config.json").write_text(json.dumps(payload))


# ---------------------------------------------------------------------- 1. the lock file
@pytest.mark.parametrize("extra", [[], ["--total-steps", "300"]])
def test_a_symlinked_lock_file_never_overwrites_its_target(extra: list[str], run_copy: Path, tmp_path, capsys) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (run_copy / "run.lock").unlink()
    (run_copy / "run.lock").symlink_to("../victim.txt")
    assert main(["resume", str(run_copy), "--quiet", *extra]) == 2
    assert victim.read_text() == "precious\n"
    line = _error_line(capsys)
    assert "run.lock" in line and "symbolic link" in line


def test_a_hard_linked_lock_file_is_never_truncated(run_copy: Path, tmp_path, capsys) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (run_copy / "run.lock").unlink()
    os.link(victim, run_copy / "run.lock")
    assert main(["resume", str(run_copy), "--quiet", "--total-steps", "300"]) == 2
    assert victim.read_text() == "precious\n"
    assert "run.lock" in _error_line(capsys)


# ---------------------------------------------------------------------- 2. other symlinks in a run
def test_a_symlinked_metrics_log_creates_nothing_outside_the_run(run_copy: Path, tmp_path, capsys) -> None:
    (run_copy / "metrics.csv").unlink()
    (run_copy / "metrics.csv").symlink_to("../new.csv")
    assert main(["resume", str(run_copy), "--quiet", "--total-steps", "300"]) == 2
    assert not (tmp_path / "new.csv").exists()
    line = _error_line(capsys)
    assert "metrics.csv" in line and "symbolic link" in line


@pytest.mark.parametrize("name", ["metrics.csv", "episodes.csv", "evaluations.csv"])
def test_a_hard_linked_log_is_never_appended_to(name: str, run_copy: Path, tmp_path, capsys) -> None:
    victim = tmp_path / "victim.csv"
    victim.write_bytes((run_copy / name).read_bytes())
    before = _digest(victim)
    (run_copy / name).unlink()
    os.link(victim, run_copy / name)
    assert main(["resume", str(run_copy), "--quiet", "--total-steps", "300"]) == 2
    assert _digest(victim) == before
    assert name in _error_line(capsys)


def test_a_symlinked_episode_log_is_not_copied_into_the_run(run_copy: Path, tmp_path, capsys) -> None:
    other = tmp_path / "other.csv"
    other.write_text("secret,data\n1,2\n")
    original = (run_copy / "episodes.csv").read_text()
    (run_copy / "episodes.csv").unlink()
    (run_copy / "episodes.csv").symlink_to(other)
    _mark_running(run_copy)
    assert main(["resume", str(run_copy), "--quiet"]) == 2
    assert "episodes.csv" in _error_line(capsys)
    assert other.read_text() == "secret,data\n1,2\n"
    assert (run_copy / "episodes.csv").is_symlink()  # refused before anything changed
    assert "secret" not in original


def test_a_symlinked_checkpoints_folder_has_nothing_deleted_in_it(run_copy: Path, tmp_path, capsys) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "latest.pt").write_bytes((run_copy / "checkpoints" / "latest.pt").read_bytes())
    stale = elsewhere / ".latest.pt.abc123.tmp"
    stale.write_bytes(b"someone's file")
    import shutil

    shutil.rmtree(run_copy / "checkpoints")
    (run_copy / "checkpoints").symlink_to(elsewhere)
    _mark_running(run_copy)
    assert main(["resume", str(run_copy), "--quiet"]) == 2
    assert stale.exists()
    assert "checkpoints" in _error_line(capsys)
    assert main(["eval", str(run_copy)]) == 2  # a reader refuses it too
    assert "checkpoints" in _error_line(capsys)


@pytest.mark.parametrize("name", ["config.json", "evaluations.csv", "checkpoints/latest.pt"])
def test_reading_a_run_follows_no_symlink(name: str, run_copy: Path, tmp_path, capsys) -> None:
    target = tmp_path / "target"
    target.write_bytes((run_copy / name).read_bytes())  # the same contents: only the link is wrong
    (run_copy / name).unlink()
    (run_copy / name).symlink_to(target)
    commands = [["eval", str(run_copy)]]
    if name != "checkpoints/latest.pt":  # plot reads no checkpoint
        commands.append(["plot", str(run_copy), "--out", str(tmp_path / "c.png")])
    for command in commands:
        assert main(command) == 2
        line = _error_line(capsys)
        assert Path(name).name in line and "symbolic link" in line


# ---------------------------------------------------------------------- 3. no module named by a run is imported
@pytest.mark.parametrize("command", ["eval", "resume", "plot"])
def test_a_module_named_in_config_json_is_never_imported(command: str, run_copy: Path, tmp_path, monkeypatch, capsys) -> None:
    marker = tmp_path / "imported"
    planted = tmp_path / "planted"
    planted.mkdir()
    name = f"pimbrl_planted_{command}"
    (planted / f"{name}.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    monkeypatch.syspath_prepend(str(planted))
    monkeypatch.chdir(planted)

    def edit(payload):
        payload["config"]["env"] = f"{name}:pimbrl/Pendulum-v0"

    _edit_config(run_copy, edit)
    assert main([command, str(run_copy), *(["--out", str(tmp_path / "c.png")] if command == "plot" else [])]) == 2
    assert not marker.exists(), "a module named in config.json was imported"
    assert name not in sys.modules
    line = _error_line(capsys)
    assert "module" in line and "registered" in line


def test_a_run_of_an_unregistered_environment_is_a_one_line_error(run_copy: Path, capsys) -> None:
    _edit_config(run_copy, lambda p: p["config"].__setitem__("env", "nobody/Nothing-v0"))
    assert main(["eval", str(run_copy)]) == 2
    assert "nobody/Nothing-v0" in _error_line(capsys)


# ---------------------------------------------------------------------- 4. malformed run files
@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda p: p.__setitem__("versions", ["torch"]), "versions"),
        (lambda p: p.__setitem__("versions", {"kernel": 5}), "versions"),
        (lambda p: p.__setitem__("summary", "fast"), "summary"),
        (lambda p: p.__setitem__("status", 3), "status"),
        (lambda p: p.__setitem__("command", ["x"]), "command"),
        (lambda p: p.__setitem__("replicate_of", {"probe": "seed0"}), "replicate_of"),  # no source named
        (lambda p: p.__setitem__("replicate_of", "seed0"), "replicate_of"),
    ],
)
@pytest.mark.parametrize("command", ["eval", "resume", "compare"])
def test_wrong_json_types_in_config_json_are_one_line_errors(
    edit, field: str, command: str, tmp_path, finished_run, capsys
) -> None:
    import shutil

    run = tmp_path / "C" / "mfrl" / "seed0"
    shutil.copytree(finished_run, run)
    _edit_config(run, edit)
    argv = {
        "eval": ["eval", str(run)],
        "resume": ["resume", str(run), "--quiet"],
        "compare": ["compare", "pendulum", "--methods", "mfrl", "--seeds", "1", "--run-dir", str(tmp_path / "C"), "--no-run"],
    }[command]
    assert main(argv) == 2
    line = _error_line(capsys)
    assert field in line and "config.json" in line


@pytest.mark.parametrize(
    "edit",
    [lambda p: p.pop("config"), lambda p: p["config"].__setitem__("env", 7), lambda p: p.__setitem__("config", [1, 2])],
)
def test_plot_of_a_config_without_a_config_or_env_is_a_one_line_error(edit, run_copy: Path, tmp_path, capsys) -> None:
    _edit_config(run_copy, edit)
    assert main(["plot", str(run_copy), "--out", str(tmp_path / "c.png")]) == 2
    assert "config.json" in _error_line(capsys)


def test_non_finite_json_numbers_are_refused(run_copy: Path, capsys) -> None:
    text = (run_copy / "config.json").read_text().replace('"eval_seed": 2021', '"eval_seed": NaN')
    assert "NaN" in text
    (run_copy / "config.json").write_text(text)
    assert main(["eval", str(run_copy)]) == 2
    assert "NaN" in _error_line(capsys)


def _replace_cell(path: Path, column: str, value: str, row: int = 1) -> None:
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row].split(",")
    cells[header.index(column)] = value
    lines[row] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "1e400"])
@pytest.mark.parametrize("command", ["resume", "compare", "plot"])
def test_a_non_finite_step_in_evaluations_is_a_one_line_error(value: str, command: str, tmp_path, finished_run, capsys) -> None:
    import shutil

    run = tmp_path / "C" / "mfrl" / "seed0"
    shutil.copytree(finished_run, run)
    _replace_cell(run / "evaluations.csv", "step", value)
    argv = {
        "resume": ["resume", str(run), "--quiet", "--total-steps", "300"],
        "compare": ["compare", "pendulum", "--methods", "mfrl", "--seeds", "1", "--run-dir", str(tmp_path / "C"), "--no-run"],
        "plot": ["plot", str(run), "--out", str(tmp_path / "c.png")],
    }[command]
    assert main(argv) == 2
    line = _error_line(capsys)
    assert "evaluations.csv" in line and "step" in line


def test_compare_never_writes_nan_into_its_summary(tmp_path, finished_run, capsys) -> None:
    import shutil

    run = tmp_path / "C" / "mfrl" / "seed0"
    shutil.copytree(finished_run, run)
    _replace_cell(run / "evaluations.csv", "return_mean", "nan")
    code = main(["compare", "pendulum", "--methods", "mfrl", "--seeds", "1", "--run-dir", str(tmp_path / "C"), "--no-run"])
    assert code == 2
    assert "return_mean" in _error_line(capsys)
    summary = tmp_path / "C" / "summary.json"
    if summary.exists():  # whatever is written is valid, strict JSON
        json.loads(summary.read_text(), parse_constant=lambda c: pytest.fail(f"{c} in summary.json"))


@pytest.mark.parametrize("name", ["config.json", "checkpoints/latest.pt", "evaluations.csv"])
@pytest.mark.parametrize("command", ["eval", "resume"])
def test_a_fifo_in_a_run_is_refused_without_hanging(name: str, command: str, run_copy: Path, capsys) -> None:
    (run_copy / name).unlink()
    os.mkfifo(run_copy / name)
    with within(10):
        assert main([command, str(run_copy), *(["--quiet"] if command == "resume" else [])]) == 2
    line = _error_line(capsys)
    assert Path(name).name in line and "regular file" in line


def test_a_device_in_a_run_is_refused_without_reading_it(run_copy: Path, capsys) -> None:
    (run_copy / "config.json").unlink()
    (run_copy / "config.json").symlink_to("/dev/zero")
    with within(10):
        assert main(["eval", str(run_copy)]) == 2
    assert "config.json" in _error_line(capsys)


@pytest.mark.slow
def test_a_file_size_limit_is_a_one_line_error_that_keeps_the_checkpoint(run_copy: Path) -> None:
    checkpoint = run_copy / "checkpoints" / "latest.pt"
    before = _digest(checkpoint)
    limit = checkpoint.stat().st_size // 2  # the next checkpoint cannot be written; the small files can

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = subprocess.run(
        [sys.executable, "-m", "pimbrl.cli", "resume", str(run_copy), "--quiet", "--total-steps", "400"],
        preexec_fn=cap,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert len(lines) == 1 and "too large" in lines[0].lower() and "resume" in lines[0], proc.stderr
    assert _digest(checkpoint) == before  # the last checkpoint is intact
    assert main(["resume", str(run_copy), "--quiet"]) == 0  # and the run goes on without the limit


# ---------------------------------------------------------------------- 5. a driver never moves a run in use
def test_compare_rerun_never_moves_a_run_whose_lock_is_held(tmp_path, finished_run, capsys) -> None:
    import shutil

    root = tmp_path / "C"
    run = root / "mfrl" / "seed0"
    shutil.copytree(finished_run, run)
    holder = RunDirectory(run)
    holder.lock("a training process")
    try:
        code = main(
            ["compare", "pendulum", "--methods", "mfrl", "--seeds", "1", "--run-dir", str(root), "--steps", "150", "--rerun"]
        )
        assert code == 2
        line = _error_line(capsys)
        assert "in use" in line and str(run) in line
        assert run.is_dir() and not list((root / "mfrl").glob("seed0.replaced-*"))
        result = RunDirectory(run).result()
        assert result is not None and result["finished"] is False  # never summarised as finished while held
    finally:
        holder.close()
    assert RunDirectory(run).result()["finished"] is True


def test_compare_follows_no_link_between_its_folder_and_a_run(tmp_path, capsys) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    root = tmp_path / "C"
    root.mkdir()
    (root / "mfrl").symlink_to(elsewhere)  # DIR/mfrl leads out of the comparison's folder
    code = main(["compare", "pendulum", "--methods", "mfrl", "--seeds", "1", "--run-dir", str(root), "--steps", "150"])
    assert code == 2
    line = _error_line(capsys)
    assert "mfrl" in line and "symbolic link" in line
    assert list(elsewhere.iterdir()) == []


# ---------------------------------------------------------------------- 6. caches
#: a pool small enough to generate anew in each test
SMALL_POOL = KSPoolConfig(n_train=4, n_test=2, batch=8, seed=7)


@pytest.fixture
def pool_cache(tmp_path, monkeypatch):
    from pimbrl.systems import ks as ks_states

    monkeypatch.setenv("PIMBRL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(ks_states, "_MEMO", {})
    return ks_states


def _pool_path(ks_states, config, split: str) -> Path:
    from pimbrl.systems import KuramotoSivashinsky

    key = ks_states._cache_key(KuramotoSivashinsky(), config)
    return ks_states.cache_dir() / "ks_pools" / f"ks_pool_{key}_{split}.npz"


@pytest.mark.parametrize(
    "poison",
    [
        lambda s, t, r: (np.full_like(s, np.nan), t, r),
        lambda s, t, r: (np.full_like(s, 1e300), t, r),
        lambda s, t, r: (s[:, :10], t, r),
        lambda s, t, r: (s.astype(np.float32), t, r),
        lambda s, t, r: (s, t[:, :2], r),
        lambda s, t, r: (s, t, r[:-1]),
        lambda s, t, r: (s[:0], t[:0], r[:0]),
    ],
)
def test_a_poisoned_ks_pool_cache_entry_is_rebuilt_with_a_warning(poison, pool_cache) -> None:
    ks_states = pool_cache
    good = ks_states.ks_initial_state_pool("train", SMALL_POOL, verbose=False)
    path = _pool_path(ks_states, SMALL_POOL, "train")
    assert path.exists()
    states, terms, runs = poison(good.states, good.uncontrolled_terms, good.run_ids)
    with open(path, "wb") as fh:
        np.savez(fh, states=states, uncontrolled_terms=terms, run_ids=runs)
    ks_states._MEMO.clear()
    with pytest.warns(UserWarning, match="KS pool cache"):
        pool = ks_states.ks_initial_state_pool("train", SMALL_POOL, verbose=False)
    np.testing.assert_array_equal(pool.states, good.states)
    assert pool.states.shape[1] == 64 and np.isfinite(pool.states).all()
    ks_states._MEMO.clear()
    again = ks_states.ks_initial_state_pool("train", SMALL_POOL, verbose=False)  # the rebuilt entry is valid
    np.testing.assert_array_equal(again.states, good.states)


def test_a_ks_pool_cache_others_can_write_is_not_used(pool_cache) -> None:
    ks_states = pool_cache
    good = ks_states.ks_initial_state_pool("test", SMALL_POOL, verbose=False)
    path = _pool_path(ks_states, SMALL_POOL, "test")
    with open(path, "wb") as fh:  # a planted entry, in a folder anyone may write
        np.savez(fh, states=good.states + 1.0, uncontrolled_terms=good.uncontrolled_terms, run_ids=good.run_ids)
    os.chmod(path.parent, 0o777)
    ks_states._MEMO.clear()
    with pytest.warns(UserWarning, match="KS pool cache"):
        pool = ks_states.ks_initial_state_pool("test", SMALL_POOL, verbose=False)
    np.testing.assert_array_equal(pool.states, good.states)


@pytest.mark.parametrize("kind", ["symlink", "fifo"])
def test_a_planted_kernel_cache_entry_is_replaced_never_followed(kind: str, tmp_path, monkeypatch) -> None:
    from pimbrl.physics import kernels

    monkeypatch.setenv("PIMBRL_CACHE_DIR", str(tmp_path / "cache"))
    directory = tmp_path / "cache" / "kernels"
    directory.mkdir(parents=True, mode=0o700)
    victim = tmp_path / "victim.py"
    victim.write_text("precious = 1\n")
    if kind == "symlink":
        (directory / "probe.py").symlink_to(victim)
    else:
        os.mkfifo(directory / "probe.py")
    with within(10), pytest.warns(UserWarning, match="kernel cache"):
        path = kernels._write_source("probe.py", "x = 1\n")
    assert path.read_text() == "x = 1\n" and not path.is_symlink()
    assert victim.read_text() == "precious = 1\n"
