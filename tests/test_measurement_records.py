"""A benchmark script's record names its measurement spec: the script, its arguments and their SHA-256."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture
def common(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> ModuleType:
    """benchmarks/_common.py, loaded as a module of its own, writing its records under ``tmp_path``."""
    spec = importlib.util.spec_from_file_location("bench_common_under_test", BENCHMARKS / "_common.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    monkeypatch.setattr(module, "RESULTS", tmp_path / "results")
    return module


def _write_as(common: ModuleType, monkeypatch: pytest.MonkeyPatch, script: Path, argv: list[str]) -> dict:
    """The record ``common.record`` writes when ``script`` runs as ``__main__`` with ``argv``."""
    main = ModuleType("__main__")
    main.__file__ = str(script)
    monkeypatch.setitem(sys.modules, "__main__", main)
    monkeypatch.setattr(sys, "argv", [str(script), *argv])
    return json.loads(common.record("probe", {"figure": 1.5}).read_text())


def test_a_record_names_its_script_arguments_and_their_hash(common, monkeypatch, tmp_path) -> None:
    script = tmp_path / "bench_probe.py"
    script.write_text("print('measures something')\n")
    rec = _write_as(common, monkeypatch, script, ["--size", "64"])
    assert rec["figure"] == 1.5 and rec["machine"]["cpu"]
    assert rec["spec"] == {"script": script.resolve().as_posix(), "argv": ["--size", "64"]}
    expected = hashlib.sha256(script.read_bytes() + b"\0" + json.dumps(["--size", "64"]).encode()).hexdigest()
    assert rec["spec_sha256"] == expected

    other_args = _write_as(common, monkeypatch, script, ["--size", "128"])["spec_sha256"]
    script.write_text("print('measures something else')\n")
    other_text = _write_as(common, monkeypatch, script, ["--size", "64"])["spec_sha256"]
    assert len({expected, other_args, other_text}) == 3


def test_a_script_of_the_repository_is_named_relative_to_it(common) -> None:
    shown, digest = common.measurement_spec(BENCHMARKS / "floor_fractions.py", [])
    assert shown == {"script": "benchmarks/floor_fractions.py", "argv": []}
    assert len(digest) == 64


def test_what_shared_the_cores_is_not_part_of_the_spec(common, monkeypatch, tmp_path) -> None:
    script = tmp_path / "bench_probe.py"
    script.write_text("print('measures something')\n")
    plain = _write_as(common, monkeypatch, script, ["--size", "64"])
    loaded = _write_as(common, monkeypatch, script, ["--load", "two training processes", "--size", "64"])
    inline = _write_as(common, monkeypatch, script, ["--size", "64", "--load=idle"])
    short = _write_as(common, monkeypatch, script, ["--loa", "idle", "--size", "64"])
    assert loaded["spec"]["argv"] == inline["spec"]["argv"] == short["spec"]["argv"] == ["--size", "64"]
    assert plain["spec_sha256"] == loaded["spec_sha256"] == inline["spec_sha256"] == short["spec_sha256"]
    assert common.without_load(["--log", "x", "--l", "y"]) == ["--log", "x", "--l", "y"]  # not --load


def test_a_command_timing_names_its_command_and_hash(monkeypatch, tmp_path) -> None:
    spec = importlib.util.spec_from_file_location("time_command_under_test", BENCHMARKS / "time_command.py")
    assert spec is not None and spec.loader is not None
    timer = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(timer)
    monkeypatch.setattr(timer, "RESULTS", tmp_path)
    monkeypatch.setattr(timer, "RECORD", tmp_path / "command_timings.json")
    assert timer.main(["probe", "--cwd", str(BENCHMARKS.parent), "--load", "idle", "--", "true"]) == 0
    assert timer.main(["probe", "--cwd", str(BENCHMARKS.parent), "--load", "idle", "--", "exit 3"]) == 3
    first, second = json.loads((tmp_path / "command_timings.json").read_text())
    assert first["spec"] == {"script": "benchmarks/time_command.py", "command": "true"}
    text = (BENCHMARKS / "time_command.py").read_bytes()
    assert first["spec_sha256"] == hashlib.sha256(text + b"\0" + b"true").hexdigest()
    assert second["exit_status"] == 3 and second["spec_sha256"] != first["spec_sha256"]
    # the command's last non-empty line of output (stderr too) is kept: for pytest, its counts
    assert first["last_line"] == "" and second["last_line"] == ""
    assert (
        timer.main(["probe", "--cwd", str(BENCHMARKS.parent), "--load", "idle", "--", "echo a; echo '2 passed' >&2; echo"]) == 0
    )
    assert json.loads((tmp_path / "command_timings.json").read_text())[-1]["last_line"] == "2 passed"


def test_a_run_profile_names_the_runs_own_commit_and_cpu(monkeypatch, tmp_path) -> None:
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # the script imports _common from beside it
    spec = importlib.util.spec_from_file_location("profile_runs_under_test", BENCHMARKS / "profile_runs.py")
    assert spec is not None and spec.loader is not None
    profiler = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(profiler)
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.csv").write_text(
        "step,wall_s,agent_updates,time/env_step_s,time/agent_update_s,time/evaluate_s\n"
        "1000,50.0,4000,1.0,30.0,4.0\n2000,100.0,9000,2.0,80.0,8.0\n"
    )
    provenance = {"commit": "88d0b76", "cpu": "AMD EPYC"}
    config = {"config": {"method": "mfrl", "env": "ks"}, "provenance": provenance}
    (run / "config.json").write_text(json.dumps(config))
    got = profiler.profile(run)
    assert got["provenance"] == provenance and got["steps"] == 2000 and got["agent_updates"] == 9000
    assert got["phase_s"] == {"env_step": 2.0, "agent_update": 80.0, "evaluate": 8.0, "other": 10.0}
    assert got["phase_share"]["agent_update"] == pytest.approx(0.8)
    assert got["s_per_1000_steps"] == pytest.approx(50.0) and got["ms_per_agent_update"] == pytest.approx(80000 / 9000)
