"""A run's ``threads`` sizes every library's thread pool, not torch's alone: in its process and in a study's children."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from threadpoolctl import threadpool_info, threadpool_limits

from pimbrl.experiments import runner
from pimbrl.experiments.runner import THREAD_VARIABLES, RunSpec, pinned_environment, run_all, thread_variables
from pimbrl.training import create_run
from pimbrl.training.config import resolve_config

# the child that stands in for `pimbrl train`: it exits 0 only where its environment pins every pool to 2 threads
CHECK = "import os, sys; names = sys.argv[1:]; sys.exit(0 if all(os.environ.get(n) == '2' for n in names) else 3)"


def test_pinned_environment_sets_every_pool_and_keeps_the_rest() -> None:
    env = pinned_environment(3, {"PATH": "/bin", "OPENBLAS_NUM_THREADS": "8"})
    assert env["PATH"] == "/bin"
    assert {name: env[name] for name in THREAD_VARIABLES} == dict.fromkeys(THREAD_VARIABLES, "3")
    assert set(THREAD_VARIABLES) >= {"OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"}
    assert thread_variables(1) == dict.fromkeys(THREAD_VARIABLES, "1")


def test_a_study_child_starts_with_its_runs_threads(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    started: list[dict[str, str]] = []
    real_popen = subprocess.Popen

    def popen(cmd, **kwargs):  # the command a run would start, replaced by the check with the same environment
        started.append(kwargs["env"])
        return real_popen([sys.executable, "-c", CHECK, *THREAD_VARIABLES], **kwargs)

    monkeypatch.setattr(runner.subprocess, "Popen", popen)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "16")  # the parent's setting does not leak into the child
    config = resolve_config("pendulum", {"method": "mfrl", "threads": 2})
    failed = run_all([RunSpec("mfrl", 0, tmp_path / "run", config)], jobs=1, log=lambda line: None, status=False)
    assert len(started) == 1 and started[0]["OPENBLAS_NUM_THREADS"] == "2"
    assert failed == []  # the child saw every variable at 2 (it exits 3 otherwise)


def test_a_run_sizes_the_blas_pools_its_process_has_loaded(tmp_path) -> None:
    blas = [i for i in threadpool_info() if i["user_api"] == "blas"]
    assert blas, "numpy loads a BLAS library (OpenBLAS in its wheels)"
    config = resolve_config("pimbrl/Pendulum-v0", {"method": "mfrl", "threads": 1})
    with threadpool_limits(limits=2):  # as numpy's OpenBLAS starts on a 2-core machine (restored afterwards)
        assert {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"} == {2}
        run = create_run(config, tmp_path / "run", progress=False)
        run.run_dir.close()
        assert {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"} == {1}
        assert torch.get_num_threads() == 1
