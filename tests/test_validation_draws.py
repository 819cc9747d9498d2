"""Training never reads the test pool (issue 28): the decisions a run makes read validation draws.

Every system has validation initial states disjoint from its test states (KS: a validation pool from runs of
its own seed stream; the others: draws from a seed stream no evaluation seed reaches). The switch to
model-free fine-tuning (``finetune.at_return``) reads the mean return on those, so two runs that differ
only in their test set (number of test episodes and evaluation seed) train identically, step for step, while
the switch fires in both at the same step: on one system of each kind (``CASES``), the draws being checked
on every system.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.training import RunDirectory

from .test_training import TINY

EXAMPLES = {
    "duffing": str(Path(__file__).resolve().parents[1] / "examples" / "duffing.py"),
    "allen-cahn": str(Path(__file__).resolve().parents[1] / "examples" / "allen_cahn.py"),
}
KS_POOL = json.dumps({"pool_config": {"n_train": 24, "n_test": 8, "n_validation": 4, "batch": 16, "seed": 123}})

#: Pendulum's run of the checkpoint test below: a model-based run whose validation return crosses its threshold
PENDULUM = ["--method", "mbrl", "--steps", "800", "--warmup-steps", "100", "--update-after", "100", "--eval-every", "100"]
#: per system, one of each path a system's draws come by (a built-in ODE, a built-in PDE, KS's pool, a system
#: of a user's own): a model-based run whose switch fires part-way (threshold between the validation returns of
#: its early and later evaluations on this code), and two test sets (episodes, seed); the draws of every system
#: are checked below, and the switch reads them through the same loop whatever the system
CASES = {
    # the reproduction: on 968d692 these two runs trained differently (the switch read the test return)
    "burgers": (
        ["--method", "pimbrl", "--steps", "720", "--warmup-steps", "60", "--update-after", "60", "--eval-every", "60"],
        "-10.6",
        (("1", "11"), ("50", "12")),
    ),
    "cartpole": (
        ["--method", "mbrl", "--steps", "600", "--warmup-steps", "100", "--update-after", "100", "--eval-every", "100"],
        "9.0",
        (("2", "5"), ("6", "6")),
    ),
    "ks": (
        [
            "--method", "pimbrl", "--steps", "200", "--warmup-steps", "40", "--update-after", "40", "--update-every", "20",
            "--eval-every", "40", "--model.start-after", "40", "--finetune.episodes", "2", "--env-kwargs", KS_POOL,
        ],
        "-850",
        (("2", "5"), ("8", "6")),
    ),
    # systems of a user's own (issue 28): the same holds for every declared system
    "duffing": (
        ["--import", EXAMPLES["duffing"], "--method", "mbrl", "--steps", "600", "--warmup-steps", "100", "--update-after", "100",
         "--eval-every", "100", "--model.start-after", "100"],
        "-40",
        (("2", "5"), ("6", "6")),
    ),
}  # fmt: skip


def _column(path: Path, name: str) -> list[str]:
    with open(path, newline="") as fh:
        return [row[name] for row in csv.DictReader(fh)]


def _agent_tensors(run: Path) -> list[torch.Tensor]:
    state = RunDirectory(run).load_checkpoint()["agent"]
    out: list[torch.Tensor] = []

    def walk(node) -> None:
        if isinstance(node, torch.Tensor):
            out.append(node)
        elif isinstance(node, dict):
            for key in sorted(node, key=str):
                walk(node[key])
        elif isinstance(node, (list, tuple)):
            for item in node:
                walk(item)

    walk(state)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("env", list(CASES))
def test_a_run_trains_the_same_whatever_its_test_set(env: str, tmp_path) -> None:
    flags, threshold, test_sets = CASES[env]
    runs = []
    for i, (episodes, seed) in enumerate(test_sets):
        run = tmp_path / f"run{i}"
        argv = ["train", env, *flags, "--eval-episodes", episodes, "--eval-seed", seed, "--finetune.at-return", threshold]
        assert main([*argv, "--log-every", flags[flags.index("--eval-every") + 1], "--run-dir", str(run), *TINY]) == 0
        runs.append(run)
    a, b = runs
    # the test sets differ (else this test would prove nothing) ...
    assert _column(a / "evaluations.csv", "episodes") != _column(b / "evaluations.csv", "episodes")
    # ... the switch fired, at the same step in both, read from the same validation returns ...
    switched = [_column(r / "metrics.csv", "model/finetuning") for r in runs]
    assert switched[0] == switched[1] and "1" in switched[0] and switched[0][0] == "0"
    assert _column(a / "metrics.csv", "model/validation_return") == _column(b / "metrics.csv", "model/validation_return")
    # ... and training is identical: every episode, every loss, the final weights
    if env != "ks":  # (a KS episode is 400 steps, longer than this run)
        assert (a / "episodes.csv").read_text() == (b / "episodes.csv").read_text()
    for column in ("agent/critic_loss", "agent/actor_loss", "model/data_loss"):
        assert _column(a / "metrics.csv", column) == _column(b / "metrics.csv", column)
    assert all(torch.equal(x, y) for x, y in zip(_agent_tensors(a), _agent_tensors(b), strict=True))


@pytest.mark.parametrize(
    "env",
    [
        "pimbrl/Burgers-v0",
        "pimbrl/Pendulum-v0",
        "pimbrl/CartPole-v0",
        "pimbrl/KuramotoSivashinsky-v0",
        "example/Duffing-v0",
        "example/AllenCahn-v0",
    ],
)
def test_validation_draws_are_fixed_and_disjoint_from_the_test_draws(env: str) -> None:
    from pimbrl.systems import get_system, import_systems

    from .conftest import SMALL_POOL

    if get_system(env) is None:
        import_systems(list(EXAMPLES.values()))

    kwargs = {"pool_config": {**SMALL_POOL.__dict__, "n_validation": 4}} if "Kuramoto" in env else {}
    task = gym.make(env, **kwargs).unwrapped.task
    n = 4
    validation = task.protocol_initial_states("validation", n, 0)
    assert validation.shape == (n, task.state_dim) and np.isfinite(validation).all()
    np.testing.assert_array_equal(validation, task.validation_initial_states(n))  # fixed
    for seed in (0, 2021, 12):  # whatever the evaluation seed, no test state is a validation state
        test = task.protocol_initial_states("test", n, seed)
        assert not (validation[:, None, :] == test[None, :, :]).all(-1).any()
    if "Kuramoto" in env:  # and no KS validation state is a training state
        train = task.pool
        assert not (validation[:, None, :] == train[None, :, :]).all(-1).any()


@pytest.mark.slow
def test_the_validation_return_is_checkpointed(tmp_path) -> None:
    """A run resumed right after the evaluation whose validation return fires the switch switches as if uninterrupted.

    Pendulum, threshold -1430: on this code the validation return first reaches it at the evaluation of step
    600, which ends an episode (a checkpoint); the model phase at 650 reads it from the checkpoint.
    """
    flags = ["pendulum", *PENDULUM, "--finetune.at-return", "-1430", "--log-every", "50"]
    flags += ["--checkpoint-every", "200", "--eval-episodes", "2", *TINY]
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert main(["train", *flags, "--run-dir", str(whole)]) == 0
    short = [*flags]
    short[short.index("--steps") + 1] = "600"
    assert main(["train", *short, "--run-dir", str(cut)]) == 0
    assert main(["resume", str(cut), "--total-steps", "800", "--quiet"]) == 0
    steps, switched = _column(whole / "metrics.csv", "step"), _column(whole / "metrics.csv", "model/finetuning")
    assert steps[switched.index("1")] == "650"  # the phase after the checkpoint switched
    assert _column(cut / "metrics.csv", "model/finetuning") == switched
    assert (whole / "episodes.csv").read_text() == (cut / "episodes.csv").read_text()
    assert all(torch.equal(x, y) for x, y in zip(_agent_tensors(whole), _agent_tensors(cut), strict=True))
