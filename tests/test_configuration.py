"""One configuration tree: typed methods and agents, recipes as files, the model phase written once, old runs read."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import pytest

from pimbrl.agents import DDPGConfig, SACConfig, TD3Config
from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.experiments.model_eval_config import ModelEvalConfig
from pimbrl.systems.presets import PresetError, load_presets
from pimbrl.training import (
    MBRL,
    METHODS,
    Hybrid,
    IdentifiedScheme,
    KnownScheme,
    PhysicsLoss,
    PiHybrid,
    PiMBRL,
    create_run,
    resolve_config,
    train,
)
from pimbrl.training.cli_args import config_from_argv, parse_train_args
from pimbrl.training.config import (
    config_from_dict,
    config_to_dict,
    field_paths,
    inapplicable_reason,
    load_config_file,
    recipe_of,
)
from pimbrl.training.methods import METHOD_TYPES, SECTIONS, methods_with
from pimbrl.training.rundir import cpu_identity, cpu_model

ROOT = Path(__file__).resolve().parent.parent
LEGACY = Path(__file__).resolve().parent / "data" / "legacy"
KS = "pimbrl/KuramotoSivashinsky-v0"


# ---------------------------------------------------------------------------------- typed methods and agents
def test_a_setting_a_method_or_agent_does_not_have_cannot_be_written() -> None:
    with pytest.raises(TypeError):
        MBRL(physics=PhysicsLoss())  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        KnownScheme(fit=None)  # type: ignore[call-arg]  # nothing is trained
    with pytest.raises(TypeError):
        SACConfig(policy_delay=2)  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        DDPGConfig(target_noise=0.1)  # type: ignore[call-arg]
    assert TD3Config().policy_delay == 2 and not hasattr(DDPGConfig(), "policy_delay")
    # the methods are named for what runs: the known scheme is not PiMBRL
    assert METHODS == (
        "mfrl", "mbrl", "pimbrl", "known-scheme", "identified-scheme", "hybrid", "pihybrid", "feedback", "mpc", "dpc"
    )  # fmt: skip
    kinds = {name: cls().model_kind for name, cls in METHOD_TYPES.items()}
    assert kinds == {"mfrl": None, "mbrl": "auto", "pimbrl": "auto", "known-scheme": "physics",
                     "identified-scheme": "physics", "hybrid": "hybrid", "pihybrid": "hybrid",
                     "feedback": None, "mpc": None, "dpc": None}  # fmt: skip
    assert not hasattr(MBRL(), "physics") and hasattr(PiMBRL(), "physics") and hasattr(PiHybrid(), "learn")
    assert not hasattr(Hybrid(), "physics") and hasattr(IdentifiedScheme(), "learn")


def test_which_method_has_a_setting_follows_from_the_types_alone() -> None:
    for path in field_paths():
        head, _, name = path.partition(".")
        if head not in ("model", *SECTIONS):
            continue
        for method, cls in METHOD_TYPES.items():
            fields = {f.name: f for f in dataclasses.fields(cls)}
            has = (name in fields and not fields[name].metadata.get("section")) if head == "model" else head in fields
            assert (method in methods_with(path)) == has, (path, method)
            reason = inapplicable_reason("pimbrl/Burgers-v0", method, "td3", path)
            assert (reason is None) == has or "PDE" in (reason or ""), (path, method, reason)


def test_structured_values_are_read_once_on_the_command_line() -> None:
    over = parse_train_args(
        ["--method", "pimbrl", "--model.prior", "nu=0.007", "--learn.coefficients", "nu,damping:0:1,correction",
         "--physics.sources", "policy,symmetry"]
    )  # fmt: skip
    assert over["model.prior"] == {"nu": 0.007}
    assert over["learn.coefficients"] == {"nu": None, "damping": [0.0, 1.0]} and over["learn.correction"] is True
    assert over["physics.sources"] == ("policy", "symmetry")
    cfg = config_from_argv(["burgers", "--method", "pimbrl", "--model.prior", "nu=0.007", "--learn.coefficients", "nu"])
    assert cfg.method.prior == {"nu": 0.007} and cfg.method.learn.ranges() == {"nu": None}
    with pytest.raises(ConfigError, match=r'^model\.prior takes a mapping, e\.g\. \{"nu": 0\.01\}'):
        resolve_config("pimbrl/Burgers-v0", {"method": "pimbrl", "model.prior": "nu=0.007"})


def test_an_old_setting_path_names_its_new_one_in_one_line(capsys) -> None:
    with pytest.raises(ConfigError, match=r"^dyna\.physics_weight is now physics\.weight \(--physics\.weight\)$"):
        resolve_config("pimbrl/Burgers-v0", {"method": "pimbrl", "dyna.physics_weight": 2.0})
    with pytest.raises(ConfigError, match=r"^lr_decay_after is now experimental\.lr_decay_after"):
        resolve_config("pimbrl/Burgers-v0", {"lr_decay_after": 100})
    with pytest.raises(ConfigError, match=r"dyna\.model is now the method itself: .*--method known-scheme"):
        resolve_config("pimbrl/Burgers-v0", {"dyna.model": "physics"})


def test_knobs_measured_as_no_help_are_experimental() -> None:
    for old in ("lr_decay_after", "agent.critic_layer_norm", "dyna.reset_start_symmetry"):
        with pytest.raises(ConfigError, match="is now experimental"):
            resolve_config("pimbrl/Burgers-v0", {old: 1 if "decay" in old else True})
    cfg = resolve_config("pimbrl/Burgers-v0", {"experimental.critic_layer_norm": True})
    assert cfg.experimental.critic_layer_norm and not hasattr(cfg.agent, "critic_layer_norm")


# ---------------------------------------------------------------------------------- the command line
def _options(text: str) -> set[str]:
    return {tok.split("=")[0].rstrip(",") for line in text.splitlines() if line.startswith("  -")
            for tok in line.split() if tok.startswith("-")}  # fmt: skip


def test_train_help_shows_at_most_25_options_and_help_all_shows_every_setting(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    shown = _options(capsys.readouterr().out)
    assert len(shown) <= 25, sorted(shown)
    assert {"--method", "--agent", "--preset", "--steps", "--seed", "--device", "--help-all"} <= shown
    assert "--physics.weight" not in shown and "--agent.gamma" not in shown
    assert main(["train", "--help-all"]) == 0
    full = capsys.readouterr().out
    every = _options(full)
    assert {"--physics.weight", "--imagine.rollout-length", "--agent.gamma", "--model.prior", "--learn.coefficients",
            "--experimental.lr-decay-after", "--fit.steps", "--check.threshold", "--finetune.at-return"} <= every  # fmt: skip
    assert "[methods pimbrl, pihybrid]" in full and "[agent sac, crossq, redq]" in full
    assert "preset/default" not in full and "where the recipe sets none" in full


def test_a_misspelled_flag_is_one_line_with_the_closest_flag(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["train", "burgers", "--utdd", "3"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--utdd" in err[0] and "(did you mean" in err[0] and "--utd" in err[0]
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("pimbrl ")


def test_the_device_is_a_setting_and_cuda_without_a_gpu_is_refused() -> None:
    import torch

    assert resolve_config("pimbrl/Burgers-v0").device == "cpu"
    assert resolve_config("pimbrl/Burgers-v0", {"device": "auto"}).device == "auto"
    with pytest.raises(ConfigError, match="device must be one of"):
        resolve_config("pimbrl/Burgers-v0", {"device": "tpu"})
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match=r"^--device cuda: torch sees no CUDA GPU here"):
            resolve_config("pimbrl/Burgers-v0", {"device": "cuda"})


def test_the_cli_s_warnings_live_below_the_cli() -> None:
    import pimbrl.cli as cli
    from pimbrl.training import advice

    assert not hasattr(cli, "budget_warnings") and not hasattr(cli, "_flag_of") and "config_warnings" not in cli.__all__
    for script in (ROOT / "benchmarks").glob("*.py"):  # scripts read the warnings from the library, not the CLI
        assert "from pimbrl.cli import" not in script.read_text() or "config_warnings" not in script.read_text(), script
    cfg = resolve_config(KS, {"method": "pimbrl", "total_steps": 1500})
    assert any("model.start_after = 6000" in line for line in advice.budget_warnings(cfg))


# ---------------------------------------------------------------------------------- recipes as files
def test_every_built_in_system_has_a_preset_file_beside_its_definition() -> None:
    for module in ("burgers", "cartpole", "pendulum", "ks"):
        path = ROOT / "src" / "pimbrl" / "systems" / f"{module}.yaml"
        default, recipes = load_presets(path)
        assert default == "default" and {"default", "paper"} <= set(recipes), module
        assert all(r.about for r in recipes.values())


def test_the_paper_recipe_has_the_paper_s_values_and_best_names_its_study() -> None:
    pendulum = "pimbrl/Pendulum-v0"
    assert resolve_config(pendulum, {"method": "pimbrl"}).method.start_after == 600
    paper = resolve_config(pendulum, {"method": "pimbrl"}, preset="paper")
    assert paper.method.start_after == 6_000 and paper.method.physics.start_after == 12_000 and paper.utd == 1.0
    assert resolve_config(KS, {"method": "pimbrl"}, preset="paper").method.network == "convlstm"
    selection = recipe_of(KS, "selection")
    assert selection.method == "known-scheme" and "EXPLORATORY" in selection.chosen_by and "test states" in selection.chosen_by
    cfg = resolve_config(KS, {"seed": 3}, preset="selection")
    assert cfg.method.name == "known-scheme" and cfg.method.imagine.rollout_length == 25 and cfg.seed == 3
    best = recipe_of(KS, "best")  # chosen on validation since tune-ks; the exploratory one kept as `selection`
    assert best.method == "mpc" and "tune-ks" in best.chosen_by and "validation" in best.chosen_by
    assert "EXPLORATORY" not in best.chosen_by
    pimbrl = resolve_config(KS, {"method": "pimbrl"}, preset="best")
    assert pimbrl.method.physics.weight == 0.1 and pimbrl.method.start_after == 1000 and pimbrl.total_steps == 60_000
    cartpole = recipe_of("pimbrl/CartPole-v0", "best")  # chosen on validation since tune-cartpole
    assert "tune-cartpole" in cartpole.chosen_by and cartpole.method == "feedback"
    with pytest.raises(ConfigError, match=r"^--preset fastest: pimbrl/CartPole-v0 has the recipes default, paper, best$"):
        resolve_config("pimbrl/CartPole-v0", preset="fastest")


def test_burgers_best_recipe_holds_its_tuning_study_s_choices_as_the_confirmatory_spec_does() -> None:
    from pimbrl.experiments.spec import load_spec
    from pimbrl.training.config import get_setting

    best = recipe_of("pimbrl/Burgers-v0", "best")
    assert "tune-burgers" in best.chosen_by and "validation" in best.chosen_by and best.method == "mpc"
    assert (ROOT / "benchmarks" / "results" / "tune-burgers.json").is_file()
    spec = load_spec(ROOT / "benchmarks" / "confirmatory" / "confirmatory-burgers.yaml")
    assert spec.kind == "confirmatory" and spec.outcome == "holdout" and min(spec.seeds) >= 100  # no tuning seed
    for arm in spec.arms:  # the spec's settings are the recipe's (each arm's own overrides)
        cfg = resolve_config("pimbrl/Burgers-v0", {"method": arm.method}, preset="best")
        for path, value in arm.overrides.items():
            assert get_setting(cfg, path) == (tuple(value) if isinstance(value, list) else value), (arm.name, path)


def test_running_a_recipe_says_which_and_who_chose_it(capsys) -> None:
    assert main(["train", "ks", "--preset", "selection", "--print-config"]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["method"]["name"] == "known-scheme"
    assert "recipe selection of pimbrl/KuramotoSivashinsky-v0" in out.err and "EXPLORATORY" in out.err


def test_a_user_s_system_gets_its_preset_from_a_file_and_a_bad_one_is_one_line(tmp_path) -> None:
    cfg = config_from_argv(["duffing", "--method", "pimbrl"]) if _imported("duffing") else None
    assert cfg is not None and cfg.total_steps == 10_000 and cfg.method.imagine.rollout_length == 20
    bad = tmp_path / "bad.yaml"
    bad.write_text("recipes:\n  default:\n    settings: [1, 2]\n")
    with pytest.raises(PresetError, match=r"^x: recipe 'default': settings must map setting paths"):
        load_presets(bad, where="x")
    bad.write_text("recipes: {default: {about: a}}\ndefault: paper\n")
    with pytest.raises(PresetError, match="the default recipe 'paper' is not among the recipes"):
        load_presets(bad, where="x")
    bad.write_text("recipes: {default: {setings: {}}}\n")
    with pytest.raises(PresetError, match="unknown key"):
        load_presets(bad, where="x")


def _imported(alias: str) -> bool:
    from pimbrl.systems import import_systems, resolve_env_id

    import_systems([str(ROOT / "examples" / "duffing.py")])
    return resolve_env_id(alias) == "example/Duffing-v0"


# ---------------------------------------------------------------------------------- the model phase once
def test_model_eval_uses_the_training_s_physics_loss_and_its_defaults() -> None:
    assert ModelEvalConfig().physics == PhysicsLoss() == PiMBRL().physics
    assert PhysicsLoss().sources == () and PhysicsLoss().units == "step"  # every source the system offers
    # one sampler of unlabelled pairs, used by the loop and by the model study
    for path in ("training/dyna.py", "experiments/model_eval.py", "experiments/model_study.py"):
        text = (ROOT / "src" / "pimbrl" / path).read_text()
        assert "class UnlabelledPairs" not in text and "class PhysicsPairs" not in text, path
    assert "PhysicsPairs(" in (ROOT / "src/pimbrl/training/dyna.py").read_text()
    assert "PhysicsPairs(" in (ROOT / "src/pimbrl/experiments/model_eval.py").read_text()


@pytest.mark.slow
def test_the_model_phase_reads_fit_check_imagine(tmp_path, monkeypatch) -> None:
    from pimbrl.training.dyna import DynaModel

    order: list[str] = []
    for name in ("fit_model", "check_model", "imagine"):
        original = getattr(DynaModel, name)

        def wrapped(self, *args, _name=name, _original=original, **kwargs):
            order.append(_name)
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(DynaModel, name, wrapped)
    cfg = resolve_config(
        "pimbrl/Pendulum-v0",
        {"method": "pimbrl", "total_steps": 200, "warmup_steps": 100, "update_after": 100, "eval_every": 200,
         "eval_episodes": 2, "agent.hidden": (16, 16), "agent.batch_size": 16, "model.start_after": 100,
         "physics.start_after": 100, "fit.steps": 1, "fit.batch_size": 16, "imagine.rollouts": 4,
         "check.threshold": 1e3, "check.validation_size": 16},
    )  # fmt: skip
    train(create_run(cfg, tmp_path / "run", progress=False))
    assert order and order[:3] == ["fit_model", "check_model", "imagine"]


def test_model_eval_prints_its_splits_plainly(tmp_path, capsys) -> None:
    args = ["model-eval", "cartpole", "--run-dir", str(tmp_path / "me"), "--transitions", "200", "--test-transitions", "20"]
    assert main([*args, "--steps", "20", "--batch-size", "32", "--refresh-every", "10"]) == 0
    out = capsys.readouterr().out
    assert "  in-sample      MSE" in out and "  out-sample     MSE" in out and "in -sample" not in out
    summary = json.loads((tmp_path / "me" / "summary.json").read_text())
    assert summary["config"]["physics"] == json.loads(json.dumps(dataclasses.asdict(PhysicsLoss())))
    from pimbrl.experiments.model_eval import spec_sha256

    # the summary names its spec's hash: the one of what it records, and another for another setting
    assert summary["spec_sha256"] == spec_sha256(summary["env"], summary["config"])
    assert spec_sha256(summary["env"], {**summary["config"], "steps": 21}) != summary["spec_sha256"]
    with pytest.raises(SystemExit):  # the schedule of a training run's physics loss is not a model-eval flag
        main([*args, "--physics.start-after", "5"])
    from pimbrl.experiments.model_eval import check_physics_settings

    with pytest.raises(ValueError, match=r"--physics\.start-after sets when a training run's physics loss starts"):
        check_physics_settings(ModelEvalConfig(physics=PhysicsLoss(start_after=5)))


# ---------------------------------------------------------------------------------- plots and figures
def test_a_plot_of_two_systems_warns_and_names_each_curve(tmp_path, capsys, monkeypatch) -> None:
    from .test_training import SMOKE, TINY

    runs = {"pendulum": tmp_path / "p", "cartpole": tmp_path / "c", "pendulum2": tmp_path / "p2"}
    for name, path in runs.items():
        env = name.rstrip("2")
        assert main(["train", env, *SMOKE[env], *TINY, "--run-dir", str(path)]) == 0
    capsys.readouterr()
    assert main(["plot", str(runs["pendulum"]), str(runs["cartpole"]), "--out", str(tmp_path / "mixed.png")]) == 0
    err = capsys.readouterr().err
    assert "on 2 systems" in err and "different scales" in err
    from pimbrl import plotting

    seen: dict = {}
    original = plotting.plot_learning_curves

    def spy(curves, path, **kwargs):
        seen["labels"] = [c[0] for c in curves]
        seen["band"] = kwargs.get("band")
        return original(curves, path, **kwargs)

    monkeypatch.setattr(plotting, "plot_learning_curves", spy)
    assert main(["plot", str(runs["pendulum"]), str(runs["pendulum2"]), "--out", str(tmp_path / "same.png")]) == 0
    assert len(set(seen["labels"])) == 2 and all("mfrl/td3 seed 0" in label for label in seen["labels"])
    assert "lowest to the highest return of the test episodes" in seen["band"]


def test_the_histogram_figure_has_its_own_file_beside_model_eval_s() -> None:
    from pimbrl.cli import FIGURE_FILES

    assert FIGURE_FILES["model-errors"] == "model_error_histograms.png"
    assert len(set(FIGURE_FILES.values())) == len(FIGURE_FILES) and "model_errors.png" not in FIGURE_FILES.values()


# ---------------------------------------------------------------------------------- recorded runs re-created
def test_old_configurations_map_to_the_commands_that_make_them_now() -> None:
    old = {
        name: json.loads((LEGACY / f"{name}.json").read_text())["config"]
        for name in ("burgers_pimbrl", "burgers_mfrl", "ks_known_scheme")
    }
    burgers = "pimbrl/Burgers-v0"
    assert config_from_dict(old["burgers_pimbrl"]) == resolve_config(burgers, {"method": "pimbrl", "total_steps": 2000})
    assert config_from_dict(old["burgers_mfrl"]) == resolve_config(burgers, {"method": "mfrl", "total_steps": 2000})
    ks = config_from_dict(old["ks_known_scheme"])  # --method mbrl --dyna.model physics: the known scheme, named so
    assert ks.method.name == "known-scheme" and ks == resolve_config(KS, {"seed": 0, "threads": 1}, preset="selection")
    for cfg in map(config_from_dict, old.values()):  # written in the new form, read back the same
        assert config_from_dict(json.loads(json.dumps(config_to_dict(cfg)))) == cfg


#: the README main job's two runs as the release before the typed methods recorded them, and the KS known-scheme
#: run of ``legacy/ks_known_scheme.json`` to a first evaluation at step 1,200 of 20 episodes, recorded at 72f8f90
#: (the legacy KS record's own first evaluation, at step 2,500 with 15,500 updates and 200 episodes, took 212 s
#: of CPU alone on the Intel machine; it passed there at 3be2a71, and its configuration is still checked above).
#: The short KS record is this code's own output at 72f8f90, a regression check, not the legacy release's; it
#: names its CPU by model and by ``cpu_identity`` (family, model, stepping, flags), as ``Intel(R) Xeon(R)
#: Processor`` names many.
RECORDED_RUNS = {"burgers_pimbrl": LEGACY, "burgers_mfrl": LEGACY, "ks_known_scheme_short": LEGACY.parent / "recorded"}


@pytest.mark.slow  # the KS run trains 1,200 steps with 2,500 updates
@pytest.mark.parametrize("name", sorted(RECORDED_RUNS))
def test_recorded_runs_reproduce_their_first_evaluations_bit_for_bit(name: str, tmp_path) -> None:
    record = json.loads((RECORDED_RUNS[name] / f"{name}.json").read_text())
    if cpu_model() != record["cpu"]:
        pytest.skip(f"recorded on {record['cpu']!r}; runs are bit for bit on one CPU model only (this is {cpu_model()!r})")
    if record.get("cpu_id", cpu_identity()) != cpu_identity():  # a virtual machine's model name can be generic
        pytest.skip(f"recorded on {record['cpu_id']!r}; runs are bit for bit on one CPU only (this is {cpu_identity()!r})")
    expected = record["evaluations"]

    class StopAtFirstEvaluationsError(Exception):
        pass

    seen: list[int] = []

    def on_event(event: str, run) -> None:
        if event == "evaluate":
            seen.append(run.t)
            if len(seen) == len(expected):
                raise StopAtFirstEvaluationsError

    run = create_run(config_from_dict(record["config"]), tmp_path / "run", progress=False)
    with pytest.raises(StopAtFirstEvaluationsError):
        train(run, on_event=on_event)
    run.run_dir.close()
    with open(tmp_path / "run" / "evaluations.csv") as fh:
        rows = [{k: v for k, v in r.items() if k in expected[0]} for r in csv.DictReader(fh)]
    assert rows == expected


def test_an_old_run_directory_still_resumes_evaluates_and_plots(tmp_path, capsys) -> None:
    """A run directory whose config.json has the old flat form is read into the new types by every command."""
    old = json.loads((LEGACY / "burgers_mfrl.json").read_text())["config"]
    old.update(total_steps=130, eval_every=120, eval_episodes=2, warmup_steps=60, update_after=60, checkpoint_every=60)
    old["agent_config"].update(hidden=[16, 16], batch_size=16)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"status": "running", "config": old, "command": "an old release"}))
    assert main(["resume", str(run), "--quiet"]) == 0  # no checkpoint yet: the run starts from its beginning
    assert main(["eval", str(run), "--episodes", "2"]) == 0
    assert main(["plot", str(run), "--out", str(tmp_path / "c.png")]) == 0
    assert (tmp_path / "c.png").exists()


#: the modules that test the command line (flags, messages, CLI runs): the only ones that read `pimbrl train` flags
CLI_TEST_MODULES = {"test_cli.py", "test_cli_ux.py", "test_config.py", "test_configuration.py", "test_training.py"}


def test_unit_tests_build_runs_through_the_python_api() -> None:
    """Outside the command-line tests, a run's configuration comes from resolve_config, never from flags."""
    here = Path(__file__).resolve().parent
    readers = {
        path.name
        for path in here.glob("test_*.py")
        if "config_from_argv" in path.read_text() or "parse_train_args" in path.read_text()
    }
    assert readers <= CLI_TEST_MODULES, sorted(readers - CLI_TEST_MODULES)
    assert "flags(" in (here / "test_training.py").read_text()  # the CLI tests derive their flags from tests/settings.py


# ---------------------------------------------------------------------------------- review: edges of the new tree
@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"dyna": [1, 2]}, "dyna must be an object"),
        ({"agent_config": [1]}, "agent_config must be an object"),
        ({"dyna": {"learn_coefficients": ["damping"]}}, "dyna.learn_coefficients must be a string"),
        ({"dyna": {"physics_prior": 5}}, "dyna.physics_prior must be a string"),
        ({"dyna": {"no_such_field": 1}}, "unknown old configuration field 'dyna.no_such_field'"),
        ({"method": "mbrl", "dyna": {"model": "physics", "physics_start": 150, "start_model_after": 300}},
         "used the scheme from dyna.physics_start 150"),
        ({"method": "mbrl", "dyna": {"model": "physics", "model_steps": 0}}, "never checked nor used"),
    ],
)  # fmt: skip
def test_an_old_configuration_that_cannot_be_read_is_one_line(change: dict, message: str) -> None:
    old = {"env": "pimbrl/Pendulum-v0", "method": "mbrl", **change}
    with pytest.raises(ConfigError, match=message) as exc:
        config_from_dict(old)
    assert "\n" not in str(exc.value)


def test_recipes_merge_the_user_s_keyword_arguments_and_keep_their_own_keys() -> None:
    cfg = resolve_config(KS, {"env_kwargs": {"convection": 1.0}}, preset="selection")
    assert cfg.env_kwargs == {"pool_config": {"n_validation": 200}, "convection": 1.0}
    from pimbrl.systems.presets import Recipe
    from pimbrl.training.config import recipe_settings, return_scale_warnings, run_names

    assert (
        run_names(KS, {}, "selection") == ("known-scheme", "td3") and run_names(KS, {"method": "mbrl"}, "selection")[0] == "mbrl"
    )
    assert return_scale_warnings(resolve_config(KS, {}, preset="selection"), "selection") == []  # the recipe's own pool_config
    with pytest.raises(ConfigError, match="method is chosen by the recipe's own 'method:' key"):
        recipe_settings(Recipe("r", settings={"method": "pimbrl"}), model_based=False)


def test_flags_of_the_previous_release_and_structured_flag_values(tmp_path, capsys) -> None:
    with pytest.raises(SystemExit):
        main(["train", "pendulum", "--agent.critic-layer-norm", "true"])
    assert "--agent.critic-layer-norm is now experimental.critic_layer_norm" in capsys.readouterr().err
    with pytest.raises(ConfigError, match=r"^--dyna\.rollouts is now imagine\.rollouts"):
        parse_train_args(["--dyna.rollouts", "3"])
    with pytest.raises(ConfigError, match=r"agent_config\.gamma is now agent\.gamma"):
        resolve_config("pimbrl/Burgers-v0", {"agent_config.gamma": 0.9})
    assert parse_train_args(["--physics.sources", "auto"])["physics.sources"] == ()
    assert parse_train_args(["--physics.sources", "policy, box"])["physics.sources"] == ("policy", "box")
    with pytest.raises(ConfigError, match=r"names 'correction' and --learn\.correction is false"):
        parse_train_args(["--learn.coefficients", "correction", "--learn.correction", "false"])
    config = tmp_path / "run.yaml"
    config.write_text("env: pimbrl/Burgers-v0\nmethod: {name: pimbrl, fit: {lr: 1e-3, steps: 7}}\n")
    cfg = load_config_file(config)
    assert cfg.method.fit.lr == 0.001 and cfg.method.fit.steps == 7


def test_compare_and_sweep_start_from_a_named_recipe(tmp_path) -> None:
    from pimbrl.experiments.compare import plan_runs
    from pimbrl.experiments.sweep import load_sweep, plan_trials

    specs = plan_runs(KS, ["known-scheme", "mfrl"], [0], tmp_path, {"total_steps": 100}, preset="selection")
    by = {s.label: s.config for s in specs}
    assert by["known-scheme"].method.imagine.rollout_length == 25 and by["mfrl"].agent.gamma == 0.99
    sweep = tmp_path / "sweep.json"
    sweep.write_text(json.dumps({"envs": ["ks"], "methods": ["known-scheme"], "seeds": [0], "preset": "selection"}))
    (trial,) = plan_trials(load_sweep(sweep), tmp_path / "out")
    assert trial.config == resolve_config(KS, {"method": "known-scheme", "seed": 0}, preset="selection")


# ---------------------------------------------------------------------------------- sweep trials (issue 30, in part)
def test_a_sweep_plans_each_distinct_run_once_and_inside_its_root(tmp_path) -> None:
    from pimbrl.experiments.sweep import load_sweep, plan_trials

    def plan(**spec):
        path = tmp_path / "sweep.json"
        path.write_text(json.dumps({"envs": ["pendulum"], "methods": ["mfrl"], "seeds": [0], **spec}))
        return plan_trials(load_sweep(path), tmp_path / "root")

    duplicates = (
        {"seeds": [0, 0]},
        {"grid": {"utd": [1, 1.0]}},
        {"envs": ["pendulum", "pimbrl/Pendulum-v0"]},
        {"grid": {"env_kwargs": [{"g": 9.0, "m": 1.0}, {"m": 1, "g": 9}]}},  # the same mapping, written twice
    )
    for duplicate in duplicates:
        with pytest.raises(ConfigError, match=r"is the same run as|seed 0 is given twice"):
            plan(**duplicate)
    (escape,) = plan(grid={"env_kwargs": [{"observation": "x/../../../y"}]})  # a value that reads as a path
    assert (tmp_path / "root").resolve() in Path(escape.path).resolve().parents and ".." not in Path(escape.path).parts
    trials = plan(grid={"env_kwargs": [{"l": 1.0}, {"l": 1.1}]}, methods=["mfrl"])  # "{'l': 1.0}": quotes, braces
    root = (tmp_path / "root").resolve()
    dirs = {Path(t.path).resolve() for t in trials}
    assert len(dirs) == 2 and all(root in d.parents for d in dirs)
    assert all("/" not in Path(t.path).parent.name and ".." not in Path(t.path).parent.name for t in trials)


@pytest.mark.slow
def test_a_huge_comparison_is_refused_at_once_and_planning_is_per_method(tmp_path, capsys) -> None:
    from pimbrl.experiments.compare import MAX_SEEDS, plan_runs

    assert main(["compare", "pendulum", "--seeds", "1000000", "--run-dir", str(tmp_path / "c"), "--no-run"]) == 2
    assert "more than a comparison runs (10,000 seeds at most)" in capsys.readouterr().err
    specs = plan_runs("pimbrl/Pendulum-v0", ["mfrl", "mbrl"], list(range(MAX_SEEDS)), tmp_path / "p")
    assert len(specs) == 2 * MAX_SEEDS and specs[-1].config.seed == MAX_SEEDS - 1
    assert specs[-1].config == resolve_config("pimbrl/Pendulum-v0", {"method": "mbrl", "seed": MAX_SEEDS - 1})
    with pytest.raises(ValueError, match="seed 3 is given twice"):
        plan_runs("pimbrl/Pendulum-v0", ["mfrl"], [3, 1, 3], tmp_path / "p")


def test_a_coefficient_out_of_bounds_stops_planning_not_a_run(tmp_path) -> None:
    from pimbrl.experiments.sweep import load_sweep, plan_trials

    with pytest.raises(ConfigError, match=r"^env_kwargs: burgers: nu must be a finite number in \[0, 1\], got 1e\+300$"):
        resolve_config("pimbrl/Burgers-v0", {"env_kwargs": {"nu": 1e300}})
    with pytest.raises(ConfigError, match="unstable"):  # in bounds, but the explicit solver step amplifies a mode
        resolve_config(KS, {"env_kwargs": {"hyper_diffusion": 100.0}})
    path = tmp_path / "sweep.json"
    path.write_text(
        json.dumps({"envs": ["burgers"], "methods": ["mfrl"], "seeds": [0], "overrides": {"env_kwargs": {"nu": 1e300}}})
    )
    with pytest.raises(ConfigError, match="nu must be a finite number"):
        plan_trials(load_sweep(path), tmp_path / "root")
    assert not (tmp_path / "root").exists()


def test_two_comparisons_in_one_directory_do_not_run_at_once(tmp_path) -> None:
    import fcntl
    import os

    from pimbrl.experiments.compare import COMPARE_LOCK, compare

    root = tmp_path / "cmp"
    root.mkdir()
    held = os.open(root / COMPARE_LOCK, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as a running comparison holds it
        with pytest.raises(ConfigError, match="is in use by another pimbrl driver"):
            compare("pimbrl/Pendulum-v0", ["mfrl"], [0], root, {"total_steps": 200}, log=lambda m: None, status=False)
        assert not (root / "mfrl").exists()  # nothing was started
        summary = compare("pimbrl/Pendulum-v0", ["mfrl"], [0], root, {"total_steps": 200}, run=False, log=lambda m: None)
        assert summary["runs"] == []  # a --no-run summary takes no lock
    finally:
        os.close(held)


def test_a_recipe_gives_each_method_and_agent_its_own_settings_on_top() -> None:
    from pimbrl.systems.presets import PresetError, load_presets
    from pimbrl.training.config import recipe_settings

    data = {"recipes": {"default": {"settings": {"total_steps": 300, "agent.actor_lr": 1e-3},
                                    "model_based": {"utd": 5.0},
                                    "methods": {"pimbrl": {"physics.weight": 0.1}, "mfrl": {"agent.actor_lr": 3e-4}},
                                    "agents": {"crossq": {"agent.actor_lr": 3e-3}}}}}  # fmt: skip
    recipe = load_presets(data)[1]["default"]
    assert recipe_settings(recipe, True, "pimbrl", "td3") == {"total_steps": 300, "agent.actor_lr": 1e-3, "utd": 5.0,
                                                              "physics.weight": 0.1}  # fmt: skip
    assert recipe_settings(recipe, False, "mfrl", "td3")["agent.actor_lr"] == 3e-4
    assert recipe_settings(recipe, False, "mfrl", "crossq")["agent.actor_lr"] == 3e-3  # the agent's last
    assert "physics.weight" not in recipe_settings(recipe, True, "mbrl", "td3")
    typo = load_presets({"recipes": {"default": {"methods": {"pimbr": {"physics.weight": 0.1}}}}})[1]["default"]
    with pytest.raises(ConfigError, match=r"recipe 'default': methods names 'pimbr' .*did you mean 'pimbrl'"):
        recipe_settings(typo, True, "pimbrl", "td3")
    with pytest.raises(PresetError, match="methods must map method names to settings"):
        load_presets({"recipes": {"default": {"methods": {"pimbrl": 0.1}}}})
    for section, message in (({"methods": {"mfrl": {"fit.steps": 7}}}, r"a mfrl run has no setting 'fit\.steps'"),
                             ({"agents": {"td3": {"agent.n_critics": 7}}}, r"a td3 run has no setting 'agent\.n_critics'"),
                             ({"methods": {"dpc": {"model.horizon": "abc"}}}, r"methods: dpc: .*model\.horizon"),
                             ({"methods": {"pimbrl": {"threshold": -1.0}}}, "threshold belongs in the recipe's settings")):  # fmt: skip
        bad = load_presets({"recipes": {"default": section}})[1]["default"]
        with pytest.raises(ConfigError, match=message):  # checked whichever method runs
            recipe_settings(bad, False, "mfrl", "td3")


def test_a_recipe_extends_another_section_by_section_and_a_bad_chain_is_one_line() -> None:
    from pimbrl.systems.presets import PresetError, load_presets

    data = {"recipes": {"default": {"about": "base", "method": "pimbrl", "settings": {"total_steps": 300, "eval_every": 50},
                                    "model_based": {"utd": 5.0, "fit.steps": 10},
                                    "methods": {"pimbrl": {"physics.weight": 0.1, "model.start_after": 50}},
                                    "agents": {"redq": {"utd": 5.0}}},
                        "paper": {"about": "paper", "extends": "default", "model_based": {"utd": 1.0},
                                  "methods": {"pimbrl": {"physics.weight": 0.01}}},
                        "best": {"extends": "paper", "method": "mpc", "chosen_by": "a study",
                                 "settings": {"total_steps": 600}}}}  # fmt: skip
    _, recipes = load_presets(data)
    paper, best = recipes["paper"], recipes["best"]
    assert paper.about == "paper" and paper.method == "pimbrl" and paper.extends == "default"
    assert paper.for_method(True, "pimbrl", "redq") == {"total_steps": 300, "eval_every": 50, "utd": 5.0, "fit.steps": 10,
                                                        "physics.weight": 0.01, "model.start_after": 50}  # fmt: skip
    assert paper.for_method(True, "pimbrl", "td3")["utd"] == 1.0  # the agent's section is last, as without extends
    assert best.method == "mpc" and best.about == "" and best.chosen_by == "a study"  # about/chosen_by are its own
    assert best.for_method(True, "pimbrl")["total_steps"] == 600 and best.for_method(True, "pimbrl")["physics.weight"] == 0.01
    assert recipes["default"].for_method(True, "pimbrl")["physics.weight"] == 0.1  # the parent is untouched
    for recipes_, message in (({"a": {"extends": "nope"}}, r"recipe 'a' extends 'nope', which is not among the recipes \(a\)"),
                              ({"a": {"extends": "bets"}, "best": {}}, r"not among the recipes \(a, best\) \(did you mean 'best'\?\)$"),
                              ({"a": {"extends": "a"}}, r"in a cycle \(a -> a\)"),
                              ({"a": {"extends": "b"}, "b": {"extends": "c"}, "c": {"extends": "b"}}, r"in a cycle \(b -> c -> b\)"),
                              ({"a": {"extends": ["b"]}, "b": {}}, "recipe 'a': extends must be a string")):  # fmt: skip
        with pytest.raises(PresetError, match=message):
            load_presets({"default": "a", "recipes": recipes_}, where="x")


def test_the_built_in_paper_and_best_recipes_extend_default_and_differ_only_where_they_say() -> None:
    burgers = load_presets(ROOT / "src" / "pimbrl" / "systems" / "burgers.yaml")[1]
    assert burgers["paper"].extends == "default" and burgers["best"].extends == "default"
    default, paper = burgers["default"].for_method(True, "pimbrl"), burgers["paper"].for_method(True, "pimbrl")
    assert {k for k in default if default[k] != paper[k]} == {"utd"} and paper["utd"] == 1.0 and default["utd"] == 5.0
    ks = load_presets(ROOT / "src" / "pimbrl" / "systems" / "ks.yaml")[1]
    assert ks["best"].extends == "default"
    assert ks["selection"].extends == ""  # KS's selection changes most settings: it is written out whole
    ks_paper = resolve_config(KS, {"method": "pimbrl"}, preset="paper")
    assert ks_paper.total_steps == 200_000 and ks_paper.method.imagine.reward_quadrature == "path"
    assert ks_paper.method.fit.steps == 10 and ks_paper.method.finetune.at_return == -55.0  # from default


def test_a_recipes_method_and_agent_sections_reach_the_run_and_a_controller_gets_no_agents(monkeypatch) -> None:
    from pimbrl.systems.presets import load_presets
    from pimbrl.training import config as config_module

    data = {"recipes": {"default": {"settings": {"total_steps": 300},
                                    "methods": {"pimbrl": {"physics.weight": 0.3}, "mpc": {"model.horizon": 7}},
                                    "agents": {"td3": {"eval_episodes": 3}, "crossq": {"agent.actor_lr": 0.002}}}}}  # fmt: skip
    recipe = load_presets(data)[1]["default"]
    monkeypatch.setattr(config_module, "recipe_of", lambda env, preset=None: recipe)
    pimbrl = resolve_config("pimbrl/Pendulum-v0", {"method": "pimbrl"})
    assert pimbrl.method.physics.weight == 0.3 and pimbrl.eval_episodes == 3 and pimbrl.total_steps == 300
    assert resolve_config("pimbrl/Pendulum-v0", {"method": "mfrl", "agent": "crossq"}).agent.actor_lr == 0.002
    mpc = resolve_config("pimbrl/Pendulum-v0", {"method": "mpc"})
    assert mpc.method.horizon == 7 and mpc.eval_episodes != 3  # td3's section is not a controller's
