"""A SIGTERM or SIGINT stops a training run at its next episode end with a checkpoint; resume continues it exactly."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pimbrl.cli import main
from pimbrl.experiments import runner
from pimbrl.experiments.runner import RunSpec, run_all
from pimbrl.training import RunDirectory, RunStopped, create_run, open_run, resolve_config, train
from pimbrl.training import loop as loop_module
from pimbrl.training.stopping import StopRequest, TimeLimitReached

from .settings import ENV_IDS, SMOKE_SETTINGS, TINY_SETTINGS, flags

pytestmark = pytest.mark.skipif(
    threading.current_thread() is not threading.main_thread(), reason="signal handlers are set on the main thread only"
)

#: 180 real steps of Burgers: three episodes of 60
SETTINGS = {"method": "mfrl", **SMOKE_SETTINGS["burgers"], **TINY_SETTINGS, "total_steps": 180}


def _tables(path: Path) -> dict[str, list[dict]]:
    d = RunDirectory(path)
    rows = {"evaluations": d.evaluations.read(), "episodes": d.episodes.read(), "metrics": d.metrics([]).read()}
    timing = ("wall", "time/", "per_s")
    return {name: [{k: v for k, v in r.items() if not any(t in k for t in timing)} for r in rs] for name, rs in rows.items()}


def test_the_first_signal_is_noted_a_ctrl_c_after_it_stops_and_the_handlers_come_back() -> None:
    # Python's own SIGINT handler, as in a terminal (a pytest-xdist worker starts with SIGINT ignored)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        before = signal.getsignal(signal.SIGTERM)
        with StopRequest() as stop:
            assert not stop.requested
            os.kill(os.getpid(), signal.SIGTERM)
            assert stop.signum == signal.SIGTERM  # noted, the process goes on
            with pytest.raises(KeyboardInterrupt):
                os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C after it: at once
        assert signal.getsignal(signal.SIGTERM) is before
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_repeated_sigterm_is_the_same_stop_and_an_inactive_request_sets_nothing(capsys) -> None:
    with StopRequest() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGTERM)  # a job's SIGTERM and the driver's copy of it: still one stop
        assert stop.signum == signal.SIGTERM
    assert "pimbrl: SIGTERM: stopping at the end of this episode, with a checkpoint" in capsys.readouterr().err
    before = signal.getsignal(signal.SIGTERM)
    with StopRequest(active=False) as inactive:  # Python callers of train() keep the usual behaviour
        assert signal.getsignal(signal.SIGTERM) is before and not inactive.requested


def test_a_signal_ignored_by_whoever_started_the_process_stays_ignored() -> None:
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as for a job a shell started in the background
    try:
        with StopRequest() as stop:
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGINT)
            assert not stop.requested
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.slow  # a few seconds: three short runs
def test_a_sigterm_stops_at_the_episode_end_with_a_checkpoint_and_resume_continues_bit_for_bit(tmp_path) -> None:
    cfg = resolve_config(ENV_IDS["burgers"], SETTINGS)  # no checkpoint is due before the end (every 5,000 steps)
    whole = create_run(cfg, tmp_path / "whole", progress=False)
    train(whole)

    def kill_at_70(name: str, run) -> None:
        if name == "act" and run.t == 70:
            os.kill(os.getpid(), signal.SIGTERM)

    cut = create_run(cfg, tmp_path / "cut", progress=False)
    with pytest.raises(RunStopped, match=r"stopped by SIGTERM at step 120, its checkpoint written") as stopped:
        train(cut, on_event=kill_at_70, stop_on_signal=True)
    assert stopped.value.step == 120 and stopped.value.exit_status == 143
    assert RunDirectory(tmp_path / "cut").status == "running"  # not finished: resumable
    resumed = open_run(tmp_path / "cut", progress=False)
    assert resumed.t == 120  # the checkpoint of the stop, not the run's start
    train(resumed, stop_on_signal=True)
    assert _tables(tmp_path / "cut") == _tables(tmp_path / "whole")


def test_the_train_command_says_where_it_stopped_and_exits_as_a_shell_reports_the_signal(
    tmp_path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    class Asked(StopRequest):  # a SIGTERM that came before the first step
        def __enter__(self) -> StopRequest:
            super().__enter__()
            self.signum = signal.SIGTERM
            return self

    monkeypatch.setattr(loop_module, "StopRequest", Asked)
    settings = {k: v for k, v in SETTINGS.items() if k != "method"}
    assert main(["train", "burgers", "--run-dir", str(tmp_path / "run"), "--quiet", *flags(settings)]) == 143
    err = capsys.readouterr().err
    assert "pimbrl train: stopped by SIGTERM at step 60, its checkpoint written" in err
    assert "the last checkpoint (step 60) is intact: `pimbrl resume" in err


def test_the_study_driver_passes_a_sigterm_on_and_a_child_that_gets_two_still_checkpoints(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the child stands in for `pimbrl train`: the same StopRequest; it exits 143 as a run stopped at its checkpoint
    # does, or dies of the KeyboardInterrupt a second signal would raise
    child = (
        "import sys, time\n"
        "from pimbrl.training.stopping import StopRequest\n"
        "with StopRequest() as stop:\n"
        "    print('ready', flush=True)\n"
        "    deadline = time.monotonic() + 30\n"
        "    while not stop.requested and time.monotonic() < deadline:\n"
        "        time.sleep(0.01)\n"
        "    time.sleep(1.5)  # the driver's copy of the SIGTERM arrives meanwhile\n"
        "sys.exit(143 if stop.requested else 1)\n"
    )
    real_popen = subprocess.Popen
    children: list[subprocess.Popen] = []

    def popen(cmd, **kwargs):
        children.append(real_popen([sys.executable, "-c", child], **kwargs))
        return children[-1]

    monkeypatch.setattr(runner.subprocess, "Popen", popen)
    log_path = tmp_path / "run" / runner.CHILD_LOG

    def sigterm_to_the_job_when_the_child_is_ready() -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not (log_path.exists() and "ready" in log_path.read_text()):
            time.sleep(0.05)
        os.kill(children[0].pid, signal.SIGTERM)  # as a scheduler signals every process of a job
        os.kill(os.getpid(), signal.SIGTERM)  # and the driver, which passes it on

    config = resolve_config(ENV_IDS["burgers"], SETTINGS)
    before = signal.getsignal(signal.SIGTERM)
    lines: list[str] = []
    killer = threading.Thread(target=sigterm_to_the_job_when_the_child_is_ready)
    killer.start()
    with pytest.raises(KeyboardInterrupt):
        run_all([RunSpec("mfrl", 0, tmp_path / "run", config)], jobs=1, log=lines.append, status=False)
    killer.join()
    assert children[0].returncode == 143  # two SIGTERMs, one stop: it reached its "checkpoint"
    assert any(line.startswith("stopped mfrl seed 0 (exit code 143): the same command again resumes it") for line in lines)
    assert signal.getsignal(signal.SIGTERM) is before  # the driver's handler is gone with it


def test_the_study_driver_stops_its_runs_with_a_checkpoint_at_its_time_limit(
    tmp_path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    # the child stands in for `pimbrl train` (the same StopRequest): it trains until asked to stop, then exits 143
    child = (
        "import sys, time\n"
        "from pimbrl.training.stopping import StopRequest\n"
        "with StopRequest() as stop:\n"
        "    deadline = time.monotonic() + 30\n"
        "    while not stop.requested and time.monotonic() < deadline:\n"
        "        time.sleep(0.01)\n"
        "sys.exit(143 if stop.requested else 1)\n"
    )
    real_popen = subprocess.Popen
    children: list[subprocess.Popen] = []

    def popen(cmd, **kwargs):
        children.append(real_popen([sys.executable, "-c", child], **kwargs))
        return children[-1]

    monkeypatch.setattr(runner.subprocess, "Popen", popen)
    config = resolve_config(ENV_IDS["burgers"], SETTINGS)
    specs = [RunSpec("mfrl", seed, tmp_path / f"seed{seed}", config) for seed in (0, 1)]
    lines: list[str] = []
    started = time.monotonic()
    with pytest.raises(TimeLimitReached, match=r"time limit \(0.02 minutes\).*the same command again continues"):
        run_all(specs, jobs=1, log=lines.append, status=False, time_limit=0.02)
    assert time.monotonic() - started < 20  # stopped at the limit (1.2 s), not at the child's own 30 s
    assert len(children) == 1 and children[0].returncode == 143  # asked to stop; the waiting run never started
    assert any(line.startswith("time limit (0.02 minutes)") for line in lines)
    assert any(line.startswith("stopped mfrl seed 0 (exit code 143)") for line in lines)
    # and through the command line: exit status 124, one line that says the same command continues
    children.clear()
    spec = tmp_path / "s.yaml"
    spec.write_text('{"systems": ["burgers"], "methods": ["mfrl"], "seeds": [0, 1]}')  # JSON is YAML
    study = ["study", "run", str(spec), "--run-dir", str(tmp_path / "study"), "--time-limit", "0.02"]
    assert main(study) == 124
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "pimbrl study: stopped at its time limit (0.02 minutes): each running run stopped at a checkpoint (an RL run "
        "at its next episode end, a control run at its last saved stage); the same command again continues"
    )
    assert len(children) == 1 and children[0].returncode == 143


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["status", "--time-limit", "5"], "--time-limit applies to study run, not status"),
        (["run", "--time-limit", "0"], "the time limit must be a positive number of minutes, got 0.0"),
        (["run", "--time-limit", "5", "--backend", "ray"], "a time limit applies to local processes, not to Ray"),
    ],
)
def test_a_time_limit_the_driver_cannot_keep_is_refused_in_one_line(args, message, tmp_path, capsys) -> None:
    spec = Path(__file__).parent.parent / "benchmarks" / "pending" / "tune-ks.yaml"
    action, *rest = args
    assert main(["study", action, str(spec), "--run-dir", str(tmp_path / "study"), *rest]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "study").exists()
