"""The command line for a newcomer: one-line errors instead of tracebacks, warnings before a run that
cannot learn, suggestions for typos, a fast ``--help`` and `pimbrl compare`'s live status and reruns."""

from __future__ import annotations

import errno
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest

from pimbrl.cli import main
from pimbrl.config import to_dict
from pimbrl.training.config import resolve_config

SRC = Path(__file__).resolve().parents[1] / "src"
#: a pendulum run of a few seconds
QUICK = ["--steps", "40", "--warmup-steps", "20", "--update-after", "20", "--eval-every", "40", "--eval-episodes", "1",
         "--agent.hidden", "16,16", "--agent.batch-size", "16", "--quiet"]  # fmt: skip


def _error_line(capsys) -> str:
    """The stderr of a command that failed with a one-line message (no traceback)."""
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    return err.splitlines()[-1]


def _fake_run(path: Path, env: str, method: str = "mfrl", status: str = "finished", **overrides) -> None:
    """A run directory with only its ``config.json`` (enough for the checks made before loading a run)."""
    path.mkdir(parents=True)
    cfg = resolve_config(env, {"method": method, **overrides})
    (path / "config.json").write_text(json.dumps({"status": status, "config": to_dict(cfg)}))


# ---------------------------------------------------------------------------------- figures
@pytest.mark.parametrize(
    ("kind", "env", "method", "expected"),
    [
        ("ks-contours", "pimbrl/Burgers-v0", "mfrl", "needs a Kuramoto-Sivashinsky run"),
        ("burgers", "pimbrl/KuramotoSivashinsky-v0", "mfrl", "needs a Burgers run"),
        ("rollouts", "pimbrl/KuramotoSivashinsky-v0", "mfrl", "needs a run with a model"),
    ],
)
def test_a_figure_that_does_not_fit_the_run_is_a_message(kind, env, method, expected, tmp_path, capsys) -> None:
    run = tmp_path / "run"
    _fake_run(run, env, method)
    out = tmp_path / "fig.png"
    assert main(["figure", kind, str(run), "--out", str(out)]) == 2
    line = _error_line(capsys)
    assert line.startswith(f"pimbrl figure: error: `pimbrl figure {kind}` {expected}") and str(run) in line
    assert not out.exists()


def test_rollouts_refuse_a_model_that_was_never_trained(tmp_path, capsys) -> None:
    run = tmp_path / "run"
    args = ["train", "pendulum", "--method", "pimbrl", "--run-dir", str(run), *QUICK, "--model.start-after", "1000"]
    assert main(args) == 0
    capsys.readouterr()
    assert main(["figure", "rollouts", str(run), "--out", str(tmp_path / "r.png")]) == 2
    line = _error_line(capsys)
    assert "model was never trained" in line and "model.start_after = 1000" in line
    assert not (tmp_path / "r.png").exists()


# ---------------------------------------------------------------------------------- files and disks
def test_a_run_dir_under_a_regular_file_is_a_message_and_nothing_is_created(tmp_path, capsys) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert main(["train", "pendulum", "--run-dir", str(blocker / "run"), *QUICK]) == 2
    line = _error_line(capsys)
    assert str(blocker) in line and "not a directory" in line and "--run-dir" in line
    assert blocker.read_text() == "not a directory" and sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_a_full_disk_names_the_path_and_what_survives(tmp_path, capsys, monkeypatch) -> None:
    from pimbrl.training import loop

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "run" / "metrics.csv"))

    monkeypatch.setattr(loop.Run, "save_checkpoint", full)
    assert main(["train", "pendulum", "--run-dir", str(tmp_path / "run"), *QUICK]) == 2
    line = _error_line(capsys)
    assert "No space left on device" in line and str(tmp_path / "run" / "metrics.csv") in line
    assert "no checkpoint" in line and "intact" not in line


def test_an_os_error_without_a_file_is_not_swallowed(monkeypatch) -> None:
    from pimbrl import cli

    def broken(args):
        raise OSError("a programming error")

    monkeypatch.setattr(cli, "_cmd_eval", broken)
    monkeypatch.setattr(cli, "_shared_parser", cli.build_parser)  # a parser that calls the patched handler
    with pytest.raises(OSError, match="a programming error"):
        main(["eval", "somewhere"])


def test_tensorboard_without_the_package_is_a_message_and_no_directory(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # `import torch.utils.tensorboard` fails
    run = tmp_path / "run"
    assert main(["train", "pendulum", "--run-dir", str(run), *QUICK, "--tensorboard", "true"]) == 2
    line = _error_line(capsys)
    assert "tensorboard" in line and "pip install" in line
    assert not run.exists()


# ---------------------------------------------------------------------------------- diverging runs
def test_a_diverging_run_says_whether_a_checkpoint_exists(tmp_path, capsys, monkeypatch) -> None:
    from pimbrl.agents.td3 import TD3

    def diverge(self, batch):
        self._check_finite(__import__("torch").tensor(float("nan")), "the critic loss")

    monkeypatch.setattr(TD3, "update", diverge)
    run = tmp_path / "run"
    assert main(["train", "pendulum", "--run-dir", str(run), *QUICK, "--update-every", "10"]) == 2
    line = _error_line(capsys)
    assert line.startswith("pimbrl train: error: the critic loss became nan")
    assert "intact" not in line and "no checkpoint" in line and f"pimbrl resume {run}" in line


# ---------------------------------------------------------------------------------- sweep files
@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ("[]", "a sweep file is an object"),
        ("null", "a sweep file is an object"),
        ("42", "a sweep file is an object"),
        ('{"envs": [1], "methods": ["mfrl"], "seeds": [0]}', "'envs'"),
        ('{"envs": ["pendulum"], "seeds": [0]}', "'methods'"),
        ('{"envs": "pendulum", "methods": ["mfrl"], "seeds": [0]}', "'envs'"),
        ('{"envs": ["pendulum"], "methods": ["mfrl"], "seeds": "3"}', "'seeds'"),
        ('{"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "name": 5}', "'name'"),
        ('{"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "grid": []}', "'grid'"),
        ('{"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "grid": {"agent.gamma": 0.9}}', "'grid'"),
        ('{"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "overrides": [1]}', "'overrides'"),
        ('{"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "train_args": "--steps 9"}', "'train_args'"),
        ('{"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "train_args": [1]}', "'train_args'"),
        ('{"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "threshold": "high"}', "threshold"),
        ('{"envs": ["pendulum"], "methods": ["pimbrll"], "seeds": [0]}', "did you mean 'pimbrl'"),
        ('{"envs": ["pendullum"], "methods": ["mfrl"], "seeds": [0]}', "did you mean 'pendulum'"),
        ('{"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "overrides": {"utdd": 2.0}}', "did you mean 'utd'"),
        ("{not json", "not valid JSON"),
    ],
)
def test_each_malformed_sweep_file_is_a_message(content: str, expected: str, tmp_path, capsys) -> None:
    path = tmp_path / "sweep.json"
    path.write_text(content)
    assert main(["sweep", str(path), "--run-dir", str(tmp_path / "out"), "--no-ray"]) == 2
    line = _error_line(capsys)
    assert line.startswith(f"pimbrl sweep: error: {path}") and expected in line
    assert not (tmp_path / "out").exists()


def test_an_unreadable_toml_sweep_file_is_a_message(tmp_path, capsys) -> None:
    path = tmp_path / "sweep.toml"
    path.write_text("envs = [pendulum")
    assert main(["sweep", str(path), "--run-dir", str(tmp_path / "out"), "--no-ray"]) == 2
    assert _error_line(capsys).startswith(f"pimbrl sweep: error: {path}: not valid TOML")


@pytest.mark.parametrize("flag", [[], ["--no-replicas"]])
def test_compare_and_sweep_pass_no_replicas_to_the_study_engine(flag: list[str], tmp_path, monkeypatch) -> None:
    """As `study run --no-replicas`: every seed of a seed-free controller trains (the engine is stubbed here)."""
    from pimbrl.experiments import compare as compare_module
    from pimbrl.experiments import sweep as sweep_module

    seen: list[bool] = []

    def engine(*args, **kwargs):
        seen.append(kwargs["replicas"])
        return {"failed": []}

    monkeypatch.setattr(compare_module, "run_study", engine)
    monkeypatch.setattr(sweep_module, "run_study", engine)
    main(["compare", "pendulum", "--methods", "feedback", "--seeds", "3", "--run-dir", str(tmp_path / "c"), *flag])
    path = tmp_path / "sweep.json"
    path.write_text('{"envs": ["pendulum"], "methods": ["feedback"], "seeds": [0, 1, 2]}')
    main(["sweep", str(path), "--run-dir", str(tmp_path / "s"), "--no-ray", *flag])
    assert seen == [not flag, not flag]


# ---------------------------------------------------------------------------------- --env-kwargs
@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("{reward: 1", "--env-kwargs must be a JSON object"),
        ("[1, 2]", "--env-kwargs must be a JSON object"),
        ('{"rewrd": "physical"}', "pimbrl/Pendulum-v0 takes no keyword argument 'rewrd'"),
    ],
)
def test_bad_env_kwargs_are_a_message(value: str, expected: str, tmp_path, capsys) -> None:
    run = tmp_path / "run"
    assert main(["train", "pendulum", "--run-dir", str(run), *QUICK, "--env-kwargs", value]) == 2
    line = _error_line(capsys)
    assert expected in line
    if "rewrd" in value:
        assert "it takes:" in line
    assert not run.exists()


# ---------------------------------------------------------------------------------- a newcomer's first run
def test_a_budget_that_ends_before_warm_up_and_model_is_warned_about(capsys) -> None:
    assert main(["train", "ks", "--method", "pimbrl", "--steps", "1500", "--print-config"]) == 0
    err = capsys.readouterr().err
    assert "warning: --steps 1500 ends before the first agent update (update_after = 4000)" in err
    assert "--update-after" in err
    assert "warning: --steps 1500 ends before the model is first fitted (model.start_after = 6000)" in err
    assert "--model.start-after" in err


def test_preset_returns_kept_on_a_changed_system_are_warned_about(capsys) -> None:
    # the KS preset's threshold and its switch to model-free fine-tuning are -55, on the registered system's
    # return scale; a run on another system that keeps them is warned, once per setting, with the flag to set
    base = ["train", "ks", "--steps", "20000", "--print-config"]
    changed = ["--env-kwargs", '{"convection": 1.3}']
    assert main([*base, *changed, "--method", "pimbrl"]) == 0
    err = capsys.readouterr().err
    assert "warning: threshold = -55 (the recipe's) counts a run as solved" in err
    assert "give --threshold for this system" in err
    assert "warning: finetune.at_return = -55 (the recipe's) switches to model-free fine-tuning" in err
    assert "--env-kwargs change convection" in err and "--finetune.at-return none never to switch" in err
    assert main([*base, *changed, "--method", "mfrl"]) == 0  # no model, no switch: the threshold alone
    err = capsys.readouterr().err
    assert "threshold = -55" in err and "finetune_return" not in err
    for quiet in (
        [*base, *changed, "--method", "pimbrl", "--threshold", "-30", "--finetune.at-return", "none"],
        [*base, *changed, "--method", "mbrl", "--threshold", "-30", "--finetune.at-return", "-30"],
        [*base, "--env-kwargs", '{"convection": 1.0}', "--method", "pimbrl"],  # the registered value
        [*base, "--method", "pimbrl"],  # the registered system
    ):
        assert main(quiet) == 0
        assert "warning" not in capsys.readouterr().err, quiet


class _Stopped(BaseException):
    """Raised by a stand-in for the comparison, so that a test stops once the warnings are printed."""


def test_compare_warns_each_method_of_preset_returns_on_a_changed_system(tmp_path, capsys, monkeypatch) -> None:
    import pimbrl.experiments.compare as compare_module

    def stop(*args, **kwargs):
        raise _Stopped

    monkeypatch.setattr(compare_module, "compare", stop)
    argv = ["compare", "ks", "--methods", "mfrl,pimbrl", "--seeds", "1", "--run-dir", str(tmp_path / "c")]
    with pytest.raises(_Stopped):
        main([*argv, "--", "--env-kwargs", '{"convection": 1.3}'])
    err = capsys.readouterr().err
    assert "pimbrl compare: warning: mfrl: threshold = -55" in err
    assert "pimbrl compare: warning: pimbrl: finetune.at_return = -55" in err
    assert "mfrl: finetune.at_return" not in err
    with pytest.raises(_Stopped):
        main([*argv, "--threshold", "-30", "--", "--env-kwargs", '{"convection": 1.3}', "--finetune.at-return", "none"])
    assert "warning" not in capsys.readouterr().err


def test_physics_start_before_the_first_update_phase_is_warned_about(capsys) -> None:
    # model phases run from update_after on: a physics_start before it trains nothing until then
    base = ["train", "ks", "--method", "pimbrl", "--steps", "20000", "--print-config"]
    assert main([*base, "--physics.alone-from", "0"]) == 0  # the preset: update_after 4000, labels at 6000
    err = capsys.readouterr().err
    assert "physics.alone_from = 0 is before update_after = 4000" in err
    assert "the physics-only training runs from 4000 to 6000" in err and "--update-after" in err
    assert main([*base, "--physics.alone-from", "0", "--model.start-after", "4000"]) == 0
    assert "no phase trains on the physics alone" in capsys.readouterr().err
    assert main([*base, "--physics.alone-from", "4000"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_a_budget_past_warm_up_gets_no_warning(capsys) -> None:
    assert main(["train", "ks", "--method", "pimbrl", "--steps", "20000", "--print-config"]) == 0
    assert "warning" not in capsys.readouterr().err


# ---------------------------------------------------------------------------------- typos
@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["train", "pendulum", "--utdd", "3"], "did you mean --utd?"),
        (["train", "pendulum", "--agent.gama", "0.9"], "did you mean --agent.gamma?"),
        (["figure", "ks-contour", "x"], "did you mean 'ks-contours'?"),
    ],
)
def test_an_unknown_flag_suggests_the_closest(argv, expected, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert expected in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["train", "pendullum", "--print-config"], "did you mean 'pendulum'?"),
        (["train", "pendulum", "--method", "pimbrll", "--print-config"], "did you mean 'pimbrl'?"),
        (["train", "pendulum", "--agent", "td33", "--print-config"], "did you mean 'td3'?"),
        (["compare", "pendulum", "--methods", "mfrl,pimbrll", "--run-dir", "x", "--no-run"], "did you mean 'pimbrl'?"),
    ],
)
def test_an_unknown_name_suggests_the_closest(argv, expected, capsys) -> None:
    assert main(argv) == 2
    assert expected in _error_line(capsys)


def test_main_reuses_one_parser_and_no_call_sees_another_s_arguments(monkeypatch, capsys) -> None:
    import pimbrl.cli as cli

    seen: list[list[str]] = []

    def load_and_mutate(args) -> None:  # a handler that changes its list argument in place
        seen.append(list(args.imports))
        args.imports.append("changed-by-a-handler")

    monkeypatch.setattr(cli, "_load_systems", load_and_mutate)
    first = cli._shared_parser()
    assert main(["train", "pendulum", "--print-config"]) == 0
    assert main(["train", "pendulum", "--import", "a_module", "--print-config"]) == 0
    assert main(["train", "pendulum", "--print-config"]) == 0
    assert seen == [[], ["a_module"], []]
    assert cli._shared_parser() is first and cli.build_parser() is not first
    capsys.readouterr()


# ---------------------------------------------------------------------------------- start-up time
def test_help_and_argument_errors_do_not_import_torch() -> None:
    code = (
        "import sys\n"
        "from pimbrl.cli import build_parser, main\n"
        "build_parser()\n"
        "for argv in (['--help'], ['train', '--help'], ['train', 'pendulum', '--utdd', '1']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "heavy = sorted(m for m in ('torch', 'numba', 'matplotlib') if m in sys.modules)\n"
        "print('heavy:', heavy)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={"PYTHONPATH": str(SRC)}, check=True)
    assert "heavy: []" in out.stdout


def test_importing_pimbrl_still_registers_the_environments() -> None:
    code = "import gymnasium as gym, pimbrl\nprint(sorted(i for i in gym.registry if i.startswith('pimbrl/')))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={"PYTHONPATH": str(SRC)}, check=True)
    import gymnasium as gym

    from pimbrl import ENV_IDS
    from pimbrl.systems import get_system

    assert out.stdout.strip() == str(sorted(ENV_IDS))
    for env_id in ENV_IDS:  # the entry points name the classes each system's module declares
        spec = gym.spec(env_id)
        system = get_system(env_id)
        assert system is not None and system.id == env_id and spec.max_episode_steps == system.episode_steps
        assert spec.entry_point == f"{system.env.__module__}:{system.env.__name__}"
        assert spec.vector_entry_point == f"{system.vector_env.__module__}:{system.vector_env.__name__}"


# ---------------------------------------------------------------------------------- progress bar
@pytest.mark.parametrize("width", [60, 80, 120])
def test_the_progress_bar_fits_the_terminal(width: int) -> None:
    from rich.console import Console

    from pimbrl.training.progress import TrainingProgress

    bar = TrainingProgress(200_000, 0, "pimbrl/td3 pimbrl/KuramotoSivashinsky-v0 seed 0", enabled=False)
    console = Console(file=io.StringIO(), width=width, force_terminal=True, color_system=None)
    progress = bar.build(console)
    task = progress.add_task(bar.label, total=200_000, completed=123_456, eval="-63.21", sps="1,234")
    assert task is not None
    console.print(progress.get_renderable())
    lines = [line for line in console.file.getvalue().splitlines() if line.strip()]  # type: ignore[attr-defined]
    assert len(lines) == 1 and len(lines[0]) <= width
    assert "123,456/200,000" in lines[0] and "-63.21" in lines[0]
    if width >= 80:
        assert "1,234" in lines[0] and "KS" in lines[0]


# ---------------------------------------------------------------------------------- compare
def test_compare_status_line_reads_the_run_directory(tmp_path) -> None:
    from pimbrl.experiments.compare import child_status, plan_runs

    spec = plan_runs("pimbrl/Pendulum-v0", ["mfrl"], [0], tmp_path, {"total_steps": 2000})[0]
    assert child_status(spec) == "mfrl seed 0: starting"
    spec.path.mkdir(parents=True)
    (spec.path / "evaluations.csv").write_text("step,return_mean\n500,-1234.5\n1000,-800.25\n")
    (spec.path / "metrics.csv").write_text("step,wall_s,steps_per_s\n1000,9.0,111.2\n")
    (spec.path / "episodes.csv").write_text("step,episode,return,length\n1000,5,-900,200\n1200,6,-700,200\n")
    assert child_status(spec) == "mfrl seed 0: 1,200/2,000 steps  test return -800.25  111 steps/s"
    tuning = plan_runs("pimbrl/Pendulum-v0", ["mfrl"], [0], tmp_path, {"total_steps": 2000, "eval_protocol": "validation"})[0]
    assert child_status(tuning) == "mfrl seed 0: 1,200/2,000 steps  validation return -800.25  111 steps/s"
    assert child_status(spec, returns=False) == "mfrl seed 0: 1,200/2,000 steps  111 steps/s"  # a confirmatory run's


TINY_COMPARE = ["--warmup-steps", "100", "--update-after", "100", "--eval-every", "100", "--eval-episodes", "2",
                "--agent.hidden", "16,16", "--agent.batch-size", "16"]  # fmt: skip


@pytest.mark.slow
def test_compare_refuses_a_run_with_another_configuration_and_reruns_it_on_request(tmp_path, capsys) -> None:
    from pimbrl.experiments.compare import plan_runs
    from pimbrl.training.cli_args import parse_train_args

    root = tmp_path / "cmp"
    old = plan_runs("pimbrl/Pendulum-v0", ["mfrl"], [0], root, {**parse_train_args(TINY_COMPARE), "total_steps": 300})[0]
    old.path.mkdir(parents=True)  # a finished run of 300 steps
    (old.path / "config.json").write_text(json.dumps({"status": "finished", "config": to_dict(old.config)}))
    args = ["compare", "pendulum", "--methods", "mfrl", "--seeds", "1", "--run-dir", str(root), "--steps", "200"]
    assert main([*args, "--", *TINY_COMPARE]) == 2
    line = _error_line(capsys)
    assert str(old.path) in line and "total_steps (300 there, 200 requested)" in line and "--rerun" in line
    assert json.loads((old.path / "config.json").read_text())["config"]["total_steps"] == 300  # left alone
    assert main([*args, "--rerun", "--", *TINY_COMPARE]) == 0
    recorded = json.loads((old.path / "config.json").read_text())
    assert recorded["status"] == "finished" and recorded["config"]["total_steps"] == 200
    moved = [p for p in old.path.parent.iterdir() if p.name.startswith("seed0.replaced-")]
    assert len(moved) == 1 and json.loads((moved[0] / "config.json").read_text())["config"]["total_steps"] == 300


def test_agent_names_are_the_agents() -> None:
    from pimbrl.agents import AGENT_NAMES, AGENTS

    assert tuple(AGENTS) == AGENT_NAMES


@pytest.mark.parametrize("protocol", ["test", "validation"])
def test_train_s_summary_names_the_draws_its_evaluations_played(protocol: str, tmp_path, capsys) -> None:
    run = tmp_path / "run"
    assert main(["train", "pendulum", "--run-dir", str(run), *QUICK, "--eval-protocol", protocol]) == 0
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    assert f"final {protocol} return -" in summary and summary.startswith(str(run))
