"""`pimbrl resume RUN --total-steps N`: a finished run continued to a larger budget."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.training import RunDirectory

from .test_dyna import DYNA_SMOKE, SMALL_MODEL, _for_method
from .test_training import TINY


def _returns(path) -> list[tuple[str, str]]:
    return [(r["step"], r["return_mean"]) for r in RunDirectory(path).evaluations.read()]


@pytest.mark.slow  # several seconds: the whole suite runs it, the fast tier does not
def test_an_extended_run_continues_to_the_larger_budget(tmp_path, capsys) -> None:
    args = [*_for_method(DYNA_SMOKE["pendulum"], "mbrl"), *TINY, *SMALL_MODEL, "--method", "mbrl"]
    args = [a if a != "300" else "150" for a in args]  # --steps 150 (the eval interval stays 150)
    short, long = tmp_path / "short", tmp_path / "long"
    assert main(["train", "pendulum", "--run-dir", str(short), *args]) == 0
    assert json.loads((short / "config.json").read_text())["status"] == "finished"
    assert main(["train", "pendulum", "--run-dir", str(long), *args, "--steps", "450"]) == 0
    assert main(["resume", str(short), "--total-steps", "450", "--quiet"]) == 0
    payload = json.loads((short / "config.json").read_text())
    assert payload["status"] == "finished" and payload["config"]["total_steps"] == 450
    assert payload["summary"]["steps"] == 450
    # up to the old end the two are the same run; after it the extended one starts a new episode
    assert _returns(short)[:1] == _returns(long)[:1]
    assert [r["step"] for r in RunDirectory(short).evaluations.read()] == ["150", "300", "450"]


@pytest.mark.slow
def test_extending_to_fewer_steps_is_a_one_line_error(tmp_path, capsys) -> None:
    run = tmp_path / "run"
    args = [*_for_method(DYNA_SMOKE["pendulum"], "mbrl"), *TINY, *SMALL_MODEL, "--method", "mbrl"]
    assert main(["train", "pendulum", "--run-dir", str(run), *args]) == 0
    capsys.readouterr()
    before = (run / "config.json").read_text()
    assert main(["resume", str(run), "--total-steps", "200"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--total-steps 200 must be larger than the run's total_steps 300" in err[0]
    assert (run / "config.json").read_text() == before


def test_wall_clock_to_threshold_is_the_training_time_of_the_first_evaluation_at_it() -> None:
    from pimbrl.training.rundir import wall_s_to_threshold

    rows = [
        {"step": "100", "return_mean": "-300.0", "wall_s": "5.0"},
        {"step": "200", "return_mean": "-150.0", "wall_s": "9.5"},
        {"step": "300", "return_mean": "-140.0", "wall_s": "14.0"},
    ]
    assert wall_s_to_threshold(rows, -200.0) == 9.5
    assert wall_s_to_threshold(rows, -100.0) is None
    assert wall_s_to_threshold(rows, None) is None


@pytest.mark.slow
def test_a_finished_run_reports_wall_clock_to_its_threshold(tmp_path) -> None:
    run = tmp_path / "run"
    args = [*_for_method(DYNA_SMOKE["pendulum"], "mbrl"), *TINY, *SMALL_MODEL, "--method", "mbrl", "--threshold=-1e9"]
    assert main(["train", "pendulum", "--run-dir", str(run), *args]) == 0
    result = RunDirectory(run).result()
    assert result is not None
    first = RunDirectory(run).evaluations.read()[0]
    assert result["steps_to_threshold"] == int(first["step"])
    assert result["wall_s_to_threshold"] == float(first["wall_s"]) > 0


def _filled(capacity: int, n: int):
    from pimbrl.buffers import ReplayBuffer

    buf = ReplayBuffer(capacity, 2, 1)
    for i in range(n):
        buf.add(np.full(2, i), np.full(1, i), float(i), np.full(2, i + 1), False, False)
    return buf


def test_a_buffer_that_never_wrapped_grows_into_a_larger_one_in_order() -> None:
    small = _filled(5, 5)  # full, never overwritten: pos wrapped to 0
    big = _filled(8, 0)
    big.load_state_dict(small.state_dict())
    assert (big.size, big.pos, big.capacity) == (5, 5, 8)
    big.add(np.full(2, 5), np.full(1, 5), 5.0, np.full(2, 6), False, False)
    reference = _filled(8, 6)
    for name in ("obs", "action", "reward", "next_obs"):
        assert torch.equal(getattr(big, name)[:6], getattr(reference, name)[:6])
    assert (big.size, big.pos) == (reference.size, reference.pos)


def test_a_buffer_that_overwrote_entries_does_not_grow() -> None:
    wrapped = _filled(5, 7)
    with pytest.raises(ValueError, match="capacity 5 differs from 8"):
        _filled(8, 0).load_state_dict(wrapped.state_dict())


def test_kernel_note_names_a_run_made_with_another_simulator_kernel() -> None:
    from pimbrl.physics.kernels import GENERATOR_VERSION
    from pimbrl.training.rundir import kernel_note, package_versions

    assert package_versions()["kernel"] == GENERATOR_VERSION
    assert kernel_note(package_versions()) is None
    assert "before version 5 (not recorded)" in (kernel_note({"pimbrl": "0.1"}) or "")
    assert f"made with simulator kernel 3, this pimbrl has kernel {GENERATOR_VERSION}" in (kernel_note({"kernel": "3"}) or "")
