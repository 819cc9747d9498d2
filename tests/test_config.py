"""Typed configurations end to end: overrides checked against field types, flags that do not apply to the
method, agent or environment rejected, sweeps and comparisons built from TrainConfig objects, children
started from a config file, and the layering cli -> experiments -> training."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.experiments.compare import REQUEST_FILE, compare, plan_runs
from pimbrl.experiments.sweep import load_sweep, plan_trials
from pimbrl.training import MFRL
from pimbrl.training.cli_args import config_from_argv, parse_train_args
from pimbrl.training.config import (
    config_from_dict,
    config_to_dict,
    get_setting,
    inapplicable_reason,
    is_pde_env,
    resolve_config,
)

SRC = Path(__file__).resolve().parent.parent / "src" / "pimbrl"
PENDULUM = "pimbrl/Pendulum-v0"
TINY_RUN = {"total_steps": 200, "warmup_steps": 100, "update_after": 100, "eval_every": 100, "eval_episodes": 2,
            "agent.hidden": [16, 16], "agent.batch_size": 16}  # fmt: skip


# ---------------------------------------------------------------------------------- inapplicable flags
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["pendulum", "--method", "mfrl", "--imagine.rollout-length", "7"],
         "--imagine.rollout-length is a setting of --method mbrl, pimbrl, known-scheme, identified-scheme, hybrid, pihybrid, not mfrl"),
        (["pendulum", "--method", "pimbrl", "--model.n-intermediate", "9"],
         "--model.n-intermediate applies to the PDE systems (Burgers, Kuramoto-Sivashinsky, a declared PDE), not pimbrl/Pendulum-v0"),
        (["cartpole", "--method", "pimbrl", "--model.scheme", "solver"], "--model.scheme applies to the PDE systems"),
        (["pendulum", "--agent.init-alpha", "0.3"], "--agent.init-alpha is a setting of the agent sac and crossq and redq, not td3"),
        (["pendulum", "--agent", "ddpg", "--agent.autotune-alpha", "false"], "--agent.autotune-alpha is a setting of the agent sac and crossq and redq, not ddpg"),
        (["burgers", "--method", "mbrl", "--physics.weight", "2"], "--physics.weight is a setting of --method pimbrl, pihybrid, not mbrl"),
        (["pendulum", "--agent", "ddpg", "--agent.policy-delay", "3"], "--agent.policy-delay is a setting of the agent td3 and crossq and redq, not ddpg"),
        (["pendulum", "--agent", "sac", "--agent.target-noise", "0.1"], "--agent.target-noise is a setting of the agent td3, not sac"),
        (["pendulum", "--agent", "sac", "--agent.exploration-noise", "0.2"], "--agent.exploration-noise is a setting of the agent td3 and ddpg, not sac"),
    ],
)  # fmt: skip
def test_a_flag_that_does_not_apply_is_an_error_that_says_why(argv, message, tmp_path, capsys) -> None:
    assert main(["train", *argv, "--run-dir", str(tmp_path / "r"), "--print-config"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["ks", "--experimental.reset-start-symmetry", "true"], "acts on reset starts, and --imagine.reset-start-fraction is 0"),
        (
            ["pendulum", "--imagine.reset-start-fraction", "0.5", "--experimental.reset-start-symmetry", "true"],
            "needs a PDE on a periodic grid (shifts, reflection); pimbrl/Pendulum-v0 has none",
        ),
    ],
)
def test_symmetric_reset_starts_need_reset_starts_and_a_pde(tmp_path, capsys, argv: list[str], message: str) -> None:
    assert main(["train", *argv, "--method", "mbrl", "--run-dir", str(tmp_path / "r"), "--print-config"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_rollout_start_shares_over_one_are_an_error_that_says_why(tmp_path, capsys) -> None:
    argv = ["pendulum", "--method", "mbrl", "--imagine.imagined-start-fraction", "0.6", "--imagine.reset-start-fraction", "0.5"]
    assert main(["train", *argv, "--run-dir", str(tmp_path / "r"), "--print-config"]) == 2
    assert (
        "--imagine.imagined-start-fraction 0.6 and --imagine.reset-start-fraction 0.5 add up to more than 1"
        in capsys.readouterr().err
    )
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["burgers", "--method", "pimbrl", "--model.n-intermediate", "9", "--model.scheme", "solver"],
        ["pendulum", "--agent", "sac", "--agent.init-alpha", "0.3", "--agent.target-entropy", "none"],
        ["pendulum", "--agent", "ddpg", "--agent.exploration-noise", "0.3"],
        ["pendulum", "--method", "mbrl", "--imagine.rollout-length", "7", "--agent.policy-delay", "3"],
    ],
)
def test_flags_that_apply_are_accepted(argv, capsys) -> None:
    assert main(["train", *argv, "--print-config"]) == 0
    assert json.loads(capsys.readouterr().out)["method"]["name"] in ("mfrl", "mbrl", "pimbrl")


def test_presets_are_not_checked_only_explicit_overrides() -> None:
    # a recipe's model settings go to the methods that have them; mfrl's recipe does not make its config invalid
    assert resolve_config("pimbrl/KuramotoSivashinsky-v0", {"method": "mfrl"}).method == MFRL()
    assert resolve_config("pimbrl/KuramotoSivashinsky-v0", {"method": "mbrl"}).method.imagine.rollout_length == 3
    assert resolve_config(PENDULUM, {"method": "pimbrl"}).method.physics.start_after == 1_000
    assert not hasattr(resolve_config(PENDULUM, {"method": "mbrl"}).method, "physics")  # mbrl has no physics loss
    assert is_pde_env("pimbrl/Burgers-v0") and is_pde_env("pimbrl/KuramotoSivashinsky-v0")
    assert not is_pde_env(PENDULUM) and not is_pde_env("pimbrl/CartPole-v0") and not is_pde_env("Pendulum-v1")
    assert inapplicable_reason(PENDULUM, "pimbrl", "td3", "utd") is None


# ---------------------------------------------------------------------------------- typed overrides
def test_overrides_are_type_checked_not_converted() -> None:
    with pytest.raises(ConfigError, match=r"seed must be an integer, got 1\.7"):
        resolve_config(PENDULUM, {"seed": 1.7})
    with pytest.raises(ConfigError, match=r"imagine\.rollout_length must be an integer, got 7\.0 \(write 7\)"):
        resolve_config(PENDULUM, {"method": "pimbrl", "imagine.rollout_length": 7.0})
    with pytest.raises(ConfigError, match="tensorboard must be true or false, got 1"):
        resolve_config(PENDULUM, {"tensorboard": 1})
    with pytest.raises(
        ConfigError, match=r"unknown setting 'imagine\.rollout_lenght' \(did you mean 'imagine\.rollout_length'\?\)"
    ):
        resolve_config(PENDULUM, {"imagine.rollout_lenght": 3})
    with pytest.raises(ConfigError, match=r"^dyna\.rollout_length is now imagine\.rollout_length \(--imagine\.rollout-length\)$"):
        resolve_config(PENDULUM, {"dyna.rollout_length": 3})  # an old path names its new one
    cfg = resolve_config(PENDULUM, {"utd": 2, "agent.hidden": [8, 8], "agent.gamma": 0.9})
    assert cfg.utd == 2.0 and isinstance(cfg.utd, float) and cfg.agent.hidden == (8, 8)
    assert cfg.agent.gamma == 0.9


def test_train_flags_parse_into_typed_overrides_below_the_cli() -> None:
    assert parse_train_args(["--steps", "200", "--agent.gamma", "0.9", "--imagine.rollout-length", "4"]) == {
        "total_steps": 200,
        "agent.gamma": 0.9,
        "imagine.rollout_length": 4,
    }
    with pytest.raises(ConfigError, match="bad train arguments"):
        parse_train_args(["--no-such-flag", "1"])
    cfg = config_from_argv(["ks", "--method", "pimbrl", "--finetune.at-return", "none"])
    assert cfg.env == "pimbrl/KuramotoSivashinsky-v0" and cfg.method.finetune.at_return is None


# ---------------------------------------------------------------------------------- train --config
def test_train_runs_a_config_file_and_rejects_other_flags_with_it(tmp_path, capsys) -> None:
    assert main(["train", "burgers", "--method", "pimbrl", "--utd", "3", "--print-config"]) == 0
    printed = capsys.readouterr().out
    path = tmp_path / "cfg.json"
    path.write_text(printed)
    assert main(["train", "--config", str(path), "--print-config"]) == 0
    assert json.loads(capsys.readouterr().out) == json.loads(printed)
    assert config_from_dict(json.loads(printed)) == resolve_config("pimbrl/Burgers-v0", {"method": "pimbrl", "utd": 3.0})
    assert main(["train", "--config", str(path), "--utd", "4", "--fit.steps", "2", "--print-config"]) == 2
    err = capsys.readouterr().err
    assert "cannot be combined with --utd, --fit.steps" in err
    assert main(["train", "burgers", "--config", str(path), "--print-config"]) == 2
    assert "cannot be combined with the environment 'burgers'" in capsys.readouterr().err
    bad = json.loads(printed)
    bad["method"]["imagine"]["rollout_length"] = 2.5
    path.write_text(json.dumps(bad))
    assert main(["train", "--config", str(path), "--print-config"]) == 2
    assert f"{path}: imagine.rollout_length must be an integer, got 2.5" in capsys.readouterr().err
    assert main(["train", "--print-config"]) == 2
    assert "needs an environment" in capsys.readouterr().err


# ---------------------------------------------------------------------------------- sweeps
def _sweep(tmp_path, **fields) -> Path:
    spec = {"name": "t", "envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], **fields}
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps(spec))
    return path


def test_sweep_values_are_typed_and_keys_known(tmp_path) -> None:
    with pytest.raises(ConfigError, match=r"grid: imagine\.rollout_length must be an integer, got 1\.7"):
        load_sweep(_sweep(tmp_path, methods=["pimbrl"], grid={"imagine.rollout_length": [3, 1.7]}))
    with pytest.raises(ConfigError, match=r"unknown setting 'agent\.gama' \(did you mean 'agent\.gamma'\?\)"):
        load_sweep(_sweep(tmp_path, grid={"agent.gama": [0.9]}))
    with pytest.raises(ConfigError, match=r"'seeds' must be a list of integers >= 0, got 1\.7"):
        load_sweep(_sweep(tmp_path, seeds=[0, 1.7]))
    with pytest.raises(ConfigError, match="tensorboard must be true or false"):
        load_sweep(_sweep(tmp_path, overrides={"tensorboard": "yes"}))
    with pytest.raises(ConfigError, match="'method' cannot be a grid key"):
        load_sweep(_sweep(tmp_path, grid={"method": ["mfrl"]}))
    with pytest.raises(ConfigError, match="total_steps is set both in 'train_args' and in 'overrides'"):
        load_sweep(_sweep(tmp_path, train_args=["--steps", "200"], overrides={"total_steps": 300}))


def test_sweep_train_args_become_typed_overrides_and_trials_carry_configs(tmp_path) -> None:
    spec = load_sweep(_sweep(tmp_path, train_args=["--steps", "200", "--agent.hidden", "16,16"], grid={"utd": [1, 2]}))
    assert spec.overrides == {"total_steps": 200, "agent.hidden": (16, 16)}
    trials = plan_trials(spec, tmp_path / "out")
    assert [t.config.utd for t in trials] == [1.0, 2.0] and [t.setting for t in trials] == ["utd=1", "utd=2"]
    assert all(t.config.total_steps == 200 and t.config.agent.hidden == (16, 16) for t in trials)


def test_sweep_overrides_go_to_the_trials_they_fit_grid_keys_to_all(tmp_path) -> None:
    spec = load_sweep(_sweep(tmp_path, methods=["mfrl", "pimbrl"], overrides={"fit.steps": 5}))
    by_method = {t.method: t.config for t in plan_trials(spec, tmp_path / "out")}
    assert by_method["pimbrl"].method.fit.steps == 5 and by_method["mfrl"].method == MFRL()
    with pytest.raises(ConfigError, match="is a setting of --method mbrl, pimbrl, identified-scheme, hybrid, pihybrid, not mfrl"):
        plan_trials(load_sweep(_sweep(tmp_path, overrides={"fit.steps": 5})), tmp_path / "out")
    with pytest.raises(ConfigError, match=r"pimbrl/Pendulum-v0 mfrl imagine\.rollout_length=3: --imagine\.rollout-length"):
        plan_trials(
            load_sweep(_sweep(tmp_path, methods=["pimbrl", "mfrl"], grid={"imagine.rollout_length": [3]})), tmp_path / "o"
        )


def test_shipped_sweep_files_still_load(tmp_path) -> None:
    root = Path(__file__).resolve().parent.parent
    files = sorted([*(root / "configs").glob("*.json"), *(root / "benchmarks" / "sweeps").glob("*.json")])
    assert files
    for path in files:
        for trial in plan_trials(load_sweep(path), tmp_path):
            assert trial.config.method.name == trial.method and trial.config.seed == trial.seed
            for key, value in trial.params:
                assert get_setting(trial.config, key) == value


@pytest.mark.parametrize(
    ("name", "key", "values", "flags"),
    [
        ("ks_scheme_hour", "imagine.rollout_length", (25, 50), "--imagine.rollout-length {v}"),
        (
            "ks_scheme_hour_reset",
            "imagine.reset_start_fraction",
            (0.5,),
            "--imagine.rollout-length 25 --imagine.reset-start-fraction {v}",
        ),
    ],
)
def test_ks_hour_sweeps_run_the_documented_commands(tmp_path, name: str, key: str, values: tuple, flags: str) -> None:
    """The KS hour sweep files plan exactly the `pimbrl train` runs docs/results.md gives."""
    path = Path(__file__).resolve().parent.parent / "benchmarks" / "sweeps" / f"{name}.json"
    trials = plan_trials(load_sweep(path), tmp_path)
    assert sorted((t.seed, dict(t.params)[key]) for t in trials) == [(s, v) for s in range(4) for v in values]
    for trial in trials:
        argv = "ks --method known-scheme --total-steps 60000 --utd 10 --warmup-steps 1000"
        argv += " --update-after 1000 --model.start-after 1000 --eval-every 2500 --finetune.at-return none"
        argv += " " + flags.format(v=dict(trial.params)[key]) + f" --agent.gamma 0.99 --threads 1 --seed {trial.seed}"
        assert trial.config == config_from_argv(argv.split())


# ---------------------------------------------------------------------------------- compare
def test_compare_applies_overrides_to_the_runs_they_fit(tmp_path) -> None:
    specs = plan_runs(PENDULUM, ["mfrl", "pimbrl", "mfrl-matched"], [0], tmp_path, {"fit.steps": 5})
    cfg = {s.label: s.config for s in specs}
    assert cfg["pimbrl"].method.fit.steps == 5 and cfg["mfrl"].method == MFRL()
    assert cfg["mfrl-matched"].utd == resolve_config(PENDULUM, {"method": "pimbrl"}).utd and cfg["mfrl"].utd == 1.0
    assert plan_runs(PENDULUM, ["mfrl-matched"], [0], tmp_path, {"utd": 2.0})[0].config.utd == 2.0  # the user's wins
    assert plan_runs(PENDULUM, ["mfrl"], [3], tmp_path, ["--steps", "300"])[0].config.total_steps == 300  # flags still read
    with pytest.raises(
        ConfigError, match=r"--fit\.steps is a setting of --method mbrl, pimbrl, identified-scheme, hybrid, pihybrid, not mfrl"
    ):
        plan_runs(PENDULUM, ["mfrl", "mfrl-matched"], [0], tmp_path, {"fit.steps": 5})
    with pytest.raises(ConfigError, match="compare sets seed itself"):
        plan_runs(PENDULUM, ["mfrl"], [0], tmp_path, {"seed": 3})


def test_compare_cli_rejects_an_extra_flag_that_fits_no_method(tmp_path, capsys) -> None:
    args = ["compare", "pendulum", "--methods", "mfrl", "--seeds", "1", "--run-dir", str(tmp_path / "c")]
    assert main([*args, "--", "--fit.steps", "5"]) == 2
    assert "--fit.steps is a setting of --method mbrl, pimbrl" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


@pytest.mark.slow  # several seconds: the whole suite runs it, the fast tier does not
def test_compare_launches_children_with_a_config_file(tmp_path) -> None:
    root = tmp_path / "cmp"
    lines: list[str] = []
    result = compare(PENDULUM, ["mfrl"], [0], root, {**TINY_RUN, "threads": 1}, log=lines.append)
    assert not result["failed"] and len(result["runs"]) == 1
    run = root / "mfrl" / "seed0"
    request = json.loads((run / REQUEST_FILE).read_text())
    recorded = json.loads((run / "config.json").read_text())
    assert recorded["status"] == "finished"
    planned = plan_runs(PENDULUM, ["mfrl"], [0], root, TINY_RUN)[0].config
    assert request == recorded["config"] == json.loads(json.dumps(config_to_dict(planned)))
    assert config_from_dict(request) == planned
    assert "--config" in recorded["command"] and any(f"--config {run / REQUEST_FILE}" in line for line in lines)


# ---------------------------------------------------------------------------------- layering
def _modules(package: str) -> list[str]:
    return sorted(f"pimbrl.{package}" + ("" if p.stem == "__init__" else f".{p.stem}") for p in (SRC / package).glob("*.py"))


@pytest.mark.slow
def test_experiments_and_training_never_import_the_cli() -> None:
    modules = _modules("training") + _modules("experiments")
    # at import time: each module imported afresh (every pimbrl module dropped before the next)
    code = (
        "import sys, importlib\n"
        f"for name in {modules!r}:\n"
        "    for m in [m for m in sys.modules if m == 'pimbrl' or m.startswith('pimbrl.')]:\n"
        "        del sys.modules[m]\n"
        "    importlib.import_module(name)\n"
        "    assert 'pimbrl.cli' not in sys.modules, name\n"
        "print('ok', len(sys.argv))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stderr[-2000:]
    # and nowhere in their code, functions included (lazy imports run only when called)
    for package in ("training", "experiments"):
        for path in (SRC / package).glob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom):
                    names = [node.module or ""] + [f"{node.module or ''}.{a.name}" for a in node.names]
                    assert not any(n.split(".")[-1] == "cli" or n.endswith("pimbrl.cli") for n in names), (path, node.lineno)
                elif isinstance(node, ast.Import):
                    assert not any(a.name == "pimbrl.cli" for a in node.names), (path, node.lineno)
