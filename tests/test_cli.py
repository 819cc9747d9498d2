"""The command line: `pimbrl simulate` smoke tests and error messages."""

from __future__ import annotations

import pytest

from pimbrl.cli import main


@pytest.mark.parametrize(
    ("env", "policy"), [pytest.param("burgers", "random", marks=pytest.mark.slow), ("cartpole", "zero"), ("pendulum", "constant")]
)
def test_simulate_writes_a_figure_and_prints_the_return(env: str, policy: str, tmp_path, capsys) -> None:
    out = tmp_path / "fig.png"
    args = ["simulate", env, "--policy", policy, "--seed", "3", "--out", str(out)]
    if policy == "constant":
        args += ["--value", "1.5"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "return=" in printed
    assert out.exists() and out.stat().st_size > 10_000
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_simulate_constant_burgers_matches_the_documented_return(capsys, tmp_path) -> None:
    # the constant action (0.075, 0.075) returns about -20, on the authors' code and on ours
    # (docs/environments.md, section "Viscous Burgers")
    assert main(["simulate", "burgers", "--policy", "constant", "--value", "0.075", "--out", str(tmp_path / "b.png")]) == 0
    ret = float(capsys.readouterr().out.split("return=")[1].split()[0])
    assert -21.5 < ret < -19.5


@pytest.mark.slow
def test_feedback_floors_are_far_above_no_control(capsys, tmp_path) -> None:
    """Each system's feedback floor (PDEs: a_i = -gain x the observation under actuator i; Cart-Pole: an LQR;
    the pendulum: energy pumping and an LQR): no learning, no model, and far above zero control."""

    def ret(*args: str) -> float:
        assert main(["simulate", *args, "--out", str(tmp_path / "f.png")]) == 0
        return float(capsys.readouterr().out.split("return=")[1].split()[0])

    assert ret("burgers", "--policy", "feedback", "--gain", "1") > ret("burgers", "--policy", "zero") + 20  # -8.7 vs -39.8
    assert ret("ks", "--policy", "feedback", "--gain", "3") > ret("ks", "--policy", "zero") + 50  # -140 vs -241
    assert ret("burgers", "--policy", "feedback", "--gain", "0") == ret("burgers", "--policy", "zero")
    assert ret("cartpole", "--policy", "feedback", "--gain", "0.1") == 200.0  # the pole stays up for the whole episode
    assert ret("cartpole", "--policy", "zero") < 50
    assert ret("pendulum", "--policy", "feedback", "--gain", "0.5") > ret("pendulum", "--policy", "zero") + 300


def test_bad_input_gives_a_clear_error(capsys, tmp_path) -> None:
    assert main(["simulate", "navier-stokes", "--out", str(tmp_path / "x.png")]) == 2
    assert "unknown environment 'navier-stokes'" in capsys.readouterr().err
    assert main(["simulate", "burgers", "--policy", "constant", "--out", str(tmp_path / "x.png")]) == 2
    assert "needs --value" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["simulate", "burgers", "--steps", "0"])


@pytest.mark.slow
def test_a_closed_standard_output_ends_the_command_quietly() -> None:
    # `pimbrl train ... --print-config | head -1`: the reader goes away before the command writes
    import subprocess
    import sys

    proc = subprocess.Popen(
        [sys.executable, "-m", "pimbrl.cli", "train", "pendulum", "--print-config"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # no reader: the command's first write fails with EPIPE
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141
    assert err == ""  # no traceback, no "Exception ignored" at exit, no error line (no run was stopped)


def test_a_broken_pipe_that_is_not_standard_output_is_not_hidden(monkeypatch) -> None:
    # a child process's pipe breaking is a real error: only a closed standard output ends quietly
    import pimbrl.cli as cli

    def broken(args) -> int:
        raise BrokenPipeError("a child's pipe")

    monkeypatch.setattr(cli, "_cmd_simulate", broken)
    monkeypatch.setattr(cli, "_shared_parser", cli.build_parser)  # a parser that calls the patched handler
    with pytest.raises(BrokenPipeError, match="a child's pipe"):
        main(["simulate", "pendulum"])
