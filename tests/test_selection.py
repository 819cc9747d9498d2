"""Model-based policy selection (``imagine.select_episodes``): judged in the model, trains nothing differently."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.models import ModelEnv
from pimbrl.training import RunDirectory, create_run, resolve_config, train
from pimbrl.training.selection import PolicySelector

from .test_training import _table

# each test trains several short model-based runs (8-13 s each): the slow tier
pytestmark = pytest.mark.slow

PENDULUM = {"total_steps": 600, "warmup_steps": 100, "update_after": 100, "eval_every": 100, "eval_episodes": 3}
SMALL_AGENT = {"agent.hidden": (16, 16), "agent.batch_size": 16}
#: the known scheme as the model: imagined episodes are the simulator's
DYNA = {"method": "known-scheme", "model.start_after": 100, "imagine.rollouts": 4, "imagine.rollout_length": 5,
        "check.threshold": 1e3, "check.validation_size": 32}  # fmt: skip


def _run(tmp_path, name: str, select: int, env: str = "pimbrl/Pendulum-v0"):
    cfg = resolve_config(env, {**PENDULUM, **SMALL_AGENT, **DYNA, "imagine.select_episodes": select})
    run = create_run(cfg, tmp_path / name, progress=False)
    return run, train(run)


@pytest.mark.parametrize("env", ["pimbrl/Pendulum-v0", "pimbrl/CartPole-v0"])  # Box and Discrete(2) actions
def test_selection_keeps_the_best_imagined_policy_and_trains_as_without_it(tmp_path, env: str) -> None:
    plain, _ = _run(tmp_path, "plain", 0, env)
    run, summary = _run(tmp_path, "select", 8, env)
    drop = ("wall_s", "steps_per_s")
    # the judge draws from none of the run's streams and changes no weight: the same run, bit for bit
    assert _table(plain.run_dir.path, "evaluations.csv", drop) == _table(run.run_dir.path, "evaluations.csv", drop)
    for name, p in plain.agent.actor.state_dict().items():
        assert torch.equal(p, run.agent.actor.state_dict()[name]), name
    assert not (plain.run_dir.path / "selection.csv").exists()
    rows = run.run_dir.selection.read()
    evals = run.run_dir.evaluations.read()
    assert [r["step"] for r in rows] == [e["step"] for e in evals] and len(rows) == 6
    assert [r["return_mean"] for r in rows] == [e["return_mean"] for e in evals]
    imagined = [float(r["model_return_mean"]) for r in rows]
    best = int(np.argmax(imagined))  # the first of equal maxima, as the selector keeps the earlier policy
    assert summary.selected_step == int(rows[best]["step"]) == int(rows[-1]["selected_step"])
    assert summary.selected_return_mean == pytest.approx(float(evals[best]["return_mean"]))
    # each row names the best policy up to that step
    for i, r in enumerate(rows):
        assert int(r["selected_step"]) == int(rows[int(np.argmax(imagined[: i + 1]))]["step"])
    written = json.loads((run.run_dir.path / "config.json").read_text())["summary"]
    assert written["selected_step"] == summary.selected_step
    assert plain.summary().selected_step is None
    # the kept policy is loaded into the agent, whatever the agent holds: it scores its recorded test return
    assert run.selector is not None and run.selector.best_policy is not None
    with torch.no_grad():
        for p in run.agent.actor.parameters():
            p.zero_()
    assert run.use_selected_policy() == summary.selected_step
    for name, p in run.agent.actor.state_dict().items():
        assert torch.equal(p, run.selector.best_policy[name]), name
    again = run.evaluator.run(lambda o: run.agent.act(o, deterministic=True))
    assert again.mean == pytest.approx(summary.selected_return_mean)
    with pytest.raises(ValueError, match="trained without model-based policy selection"):
        plain.use_selected_policy()


def test_a_run_that_has_not_evaluated_yet_has_no_selected_policy(tmp_path) -> None:
    cfg = resolve_config("pimbrl/Pendulum-v0", {**PENDULUM, **SMALL_AGENT, **DYNA, "imagine.select_episodes": 4})
    run = create_run(cfg, tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="has not selected a policy yet"):
        run.use_selected_policy()
    run.run_dir.close()


def test_imagined_episodes_of_the_physics_model_are_the_real_episodes(tmp_path) -> None:
    """With the equation in the model, an imagined episode is the simulator's episode (single precision)."""
    cfg = resolve_config("pimbrl/Pendulum-v0", {**PENDULUM, **SMALL_AGENT, **DYNA, "imagine.select_episodes": 5})
    run = create_run(cfg, tmp_path / "run", progress=False)
    assert run.model is not None and run.model.selector is not None
    selector, task, agent = run.model.selector, run.task, run.agent
    imagined = selector.evaluate(agent)
    u = selector.states.copy()
    returns = np.zeros(len(u))
    for k in range(task.max_episode_steps):
        kk = np.full(len(u), k)
        action = agent.act(task.observe(u, kk), deterministic=True)
        out = task.advance(u, task.physical_action(run.adapter.to_env(action), len(u)), kk)
        returns += out.reward
        u = out.state
    assert imagined.blown_up == 0 and len(imagined.returns) == 5
    np.testing.assert_allclose(imagined.returns, returns, rtol=1e-3)
    # the start states are training initial states, fixed by the evaluation seed
    again = PolicySelector(run.model.model_env, 5)
    np.testing.assert_array_equal(again.states, selector.states)


class _Exploding(torch.nn.Module):
    """A model whose every prediction is non-finite."""

    def forward(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return torch.full((len(state), 1, state.shape[-1]), float("nan"))


def test_a_blown_up_imagined_episode_ends_with_the_divergence_penalty(tmp_path) -> None:
    cfg = resolve_config("pimbrl/Pendulum-v0", {**PENDULUM, **SMALL_AGENT, **DYNA, "imagine.select_episodes": 4})
    run = create_run(cfg, tmp_path / "run", progress=False)
    env = ModelEnv(_Exploding(), run.task, run.adapter, physics=run.physics)  # type: ignore[arg-type]
    selector = PolicySelector(env, 4)
    result = selector.evaluate(run.agent)
    assert result.blown_up == 4
    np.testing.assert_array_equal(result.returns, np.full(4, run.task.divergence_penalty))


def test_eval_of_the_selected_policy(tmp_path, capsys) -> None:
    run, summary = _run(tmp_path, "select", 8)
    path = str(run.run_dir.path)
    assert main(["eval", path, "--policy", "selected", "--json"]) == 0
    out = capsys.readouterr().out
    assert f"selected at step {summary.selected_step:,d} of 600" in out
    payload = json.loads(out.strip().splitlines()[-1])
    assert payload["policy_step"] == summary.selected_step and payload["step"] == 600
    # the selected policy, re-evaluated on the run's test states, scores what it scored when it was kept
    assert payload["policy"] == "selected" and payload["return_mean"] == pytest.approx(summary.selected_return_mean)
    plain, _ = _run(tmp_path, "plain", 0)
    assert main(["eval", str(plain.run_dir.path), "--policy", "selected"]) != 0
    assert "trained without model-based policy selection" in capsys.readouterr().err
    assert RunDirectory(plain.run_dir.path).selection.read() == []


def test_selection_is_refused_for_mfrl(capsys) -> None:
    assert main(["train", "pendulum", "--method", "mfrl", "--imagine.select-episodes", "10", "--print-config"]) != 0
    assert "--imagine.select-episodes is a setting of --method mbrl, pimbrl" in capsys.readouterr().err


def test_evaluating_a_run_without_a_checkpoint_says_so(tmp_path, capsys) -> None:
    """``pimbrl eval``, the figures and the benchmarks share one check and one message."""
    from pimbrl.experiments.figures import load_run

    cfg = resolve_config("pimbrl/Pendulum-v0", {**PENDULUM, **SMALL_AGENT, **DYNA})
    create_run(cfg, tmp_path / "new", progress=False).run_dir.close()  # config.json, no checkpoint
    assert main(["eval", str(tmp_path / "new")]) != 0
    assert "has no checkpoint yet: nothing to evaluate (train or resume it first)" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError, match="has no checkpoint yet"):
        load_run(tmp_path / "new")


def test_the_selection_summary_benchmark_reads_what_the_run_logged(tmp_path) -> None:
    import subprocess
    import sys
    from pathlib import Path

    run, summary = _run(tmp_path, "select", 8)
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "selection_summary.py"
    out = subprocess.run(
        [sys.executable, str(script), str(run.run_dir.path), "--threshold=-1e9"], capture_output=True, text=True, check=True
    ).stdout
    assert f"selected {summary.selected_return_mean:7.2f} (step {summary.selected_step:,d})" in out
    assert "first at threshold 100 " in out  # every return is above -1e9: the first evaluation
    plain, _ = _run(tmp_path, "plain", 0)
    failed = subprocess.run([sys.executable, str(script), str(plain.run_dir.path)], capture_output=True, text=True)
    assert failed.returncode != 0 and "was the run trained with --imagine.select-episodes N?" in failed.stderr


def test_the_steps_ratio_benchmark_reads_run_directories_and_records(tmp_path) -> None:
    import subprocess
    import sys
    from pathlib import Path

    from pimbrl.training import RunDirectory

    run, _ = _run(tmp_path, "plain", 0)
    evals = run.run_dir.evaluations.read()
    # a threshold between the 2nd and the best evaluation: the run reaches it at the first evaluation at or above it
    returns = [float(e["return_mean"]) for e in evals]
    threshold = (sorted(returns)[-1] + sorted(returns)[-2]) / 2
    first = next(int(e["step"]) for e, r in zip(evals, returns, strict=True) if r >= threshold)
    record = tmp_path / "compare.json"  # a comparison record of a run whose directory is gone
    filler = {"final_return": -1.0, "wall_s": 1.0, "update_to_data": 1.0}
    record.write_text(
        json.dumps(
            {"threshold": threshold, "runs": [{"method": "mfrl", "seed": 0, "steps_to_threshold": None, "steps": 6000, **filler}]}
        )
    )
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "steps_ratio.py"
    args = [sys.executable, str(script), "--a", str(run.run_dir.path), "--threshold", repr(threshold)]
    out = subprocess.run([*args, "--b", str(run.run_dir.path)], capture_output=True, text=True, check=True).stdout
    assert f"a: reached 1/1; median {first:,}; seed 0: {first:,}" in out and "a/b, medians: 1.000" in out
    out = subprocess.run(
        [*args, "--b-record", str(record), "--b-method", "mfrl"], capture_output=True, text=True, check=True
    ).stdout
    assert "b: reached 0/1; median > 6,000" in out and f"a/b, medians: {first / 6000:.3f} (upper bound" in out
    assert RunDirectory(run.run_dir.path).result(threshold)["steps_to_threshold"] == first
    wrong = subprocess.run(
        [*args[:-1], "-1000000000.0", "--b-record", str(record), "--b-method", "mfrl"], capture_output=True, text=True
    )
    assert wrong.returncode != 0 and "was summarised at threshold" in wrong.stderr
