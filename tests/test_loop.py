"""The loop function: phase order, independent random streams, checkpoints as the components' states."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pimbrl.training import STREAM_KEYS, RandomStreams, Run, create_run, resolve_config, train

SMALL_AGENT = {"agent.hidden": (16, 16), "agent.batch_size": 16}


def _pendulum(method: str, utd: float = 5.0, **model_settings) -> object:
    over = {"method": method, "utd": utd, "total_steps": 500, "warmup_steps": 100, "update_after": 100, "update_every": 50,
            "eval_every": 250, "eval_episodes": 2, "checkpoint_every": 200, **SMALL_AGENT}  # fmt: skip
    model = {"model.start_after": 200, "physics.start_after": 200, "fit.steps": 2, "fit.batch_size": 16,
             "imagine.rollouts": 8, "imagine.rollout_length": 5, "check.threshold": 1e3, "check.validation_size": 32,
             **model_settings}  # fmt: skip
    return resolve_config("pimbrl/Pendulum-v0", {**over, **(model if method != "mfrl" else {})})


def _run(cfg, path) -> tuple[list[tuple[str, int]], Run]:
    events: list[tuple[str, int]] = []
    run = create_run(cfg, str(path), progress=False)
    train(run, on_event=lambda name, r: events.append((name, r.t)))
    return events, run


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
@pytest.mark.parametrize("method", ["mfrl", "pimbrl"])
def test_the_loop_runs_its_phases_in_the_order_of_algorithm_1(method: str, tmp_path) -> None:
    cfg = _pendulum(method)
    events, run = _run(cfg, tmp_path / method)
    acts = [t for name, t in events if name == "act"]
    assert acts == list(range(1, cfg.total_steps + 1))  # one real step at a time
    phases = [(name, t) for name, t in events if name != "act"]
    update_steps = [t for t in range(cfg.update_after, cfg.total_steps + 1) if t % cfg.update_every == 0]
    expected: list[tuple[str, int]] = []
    for t in range(1, cfg.total_steps + 1):
        if t in update_steps:
            expected += [("model_phase", t)] if method == "pimbrl" else []
            expected.append(("agent_updates", t))
        if t % cfg.eval_every == 0:
            expected.append(("evaluate", t))
        # checkpoints only at episode ends (Pendulum: every 200 steps), once checkpoint_every steps passed
        if t % 200 == 0 and t < cfg.total_steps:
            expected.append(("checkpoint", t))
    assert phases == expected
    # counters: the agent got update_every * utd updates per phase, the model its steps per phase
    assert run.agent.n_updates == len(update_steps) * cfg.update_every * cfg.utd
    if method == "pimbrl":
        model_phases = [t for t in update_steps if t >= cfg.method.start_after]
        assert run.model.trainer.steps == len(model_phases) * cfg.method.fit.steps


@pytest.mark.slow  # several seconds: the whole suite runs it, the fast tier does not
def test_a_model_setting_changes_neither_the_holdout_split_nor_early_exploration(tmp_path) -> None:
    """Changing --fit.steps (or the rollouts) draws more or fewer numbers in the model phase; the hold-out
    flags of the real transitions, and everything the agent did in the real environment before the model
    was used, stay identical."""
    _, a = _run(_pendulum("pimbrl", **{"fit.steps": 1}), tmp_path / "a")
    _, b = _run(_pendulum("pimbrl", **{"fit.steps": 4, "imagine.rollouts": 3}), tmp_path / "b")
    assert a.model.trainer.steps != b.model.trainer.steps
    n = len(a.real)
    flags_a, flags_b = a.real.extras["holdout"][:n], b.real.extras["holdout"][:n]
    assert 0 < float(flags_a.sum()) < n  # some held out, not all
    assert bool((flags_a == flags_b).all())
    first_use = a.cfg.method.start_after  # the first model phase: its imagined data reaches the agent after it
    assert bool((a.real.action[:first_use] == b.real.action[:first_use]).all())
    assert bool((a.real.obs[:first_use] == b.real.obs[:first_use]).all())
    assert not bool((a.real.action == b.real.action).all())  # afterwards the model does change what the agent does


@pytest.mark.slow  # several seconds: the whole suite runs it, the fast tier does not
def test_mfrl_and_pimbrl_explore_identically_until_the_model_is_used(tmp_path) -> None:
    """Same seed and update budget: PiMBRL's agent is MFRL's until imagined data first reaches it."""
    _, mf = _run(_pendulum("mfrl"), tmp_path / "mf")
    _, pim = _run(_pendulum("pimbrl"), tmp_path / "pim")
    first_use = pim.cfg.method.start_after
    assert bool((mf.real.action[:first_use] == pim.real.action[:first_use]).all())


def test_streams_are_independent_and_restorable() -> None:
    s = RandomStreams(7)
    draws = {name: getattr(s, name).random(3) for name in STREAM_KEYS}
    assert len({tuple(v) for v in draws.values()}) == len(STREAM_KEYS)  # no two streams alike
    state = s.state_dict()
    again = {name: getattr(s, name).random(2) for name in STREAM_KEYS}
    s.load_state_dict(state)
    for name in STREAM_KEYS:
        np.testing.assert_array_equal(getattr(s, name).random(2), again[name])
    t = RandomStreams(7)
    t.model_batches.random(1000)  # drawing from one stream leaves the others where they were
    np.testing.assert_array_equal(t.holdout.random(3), draws["holdout"])


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
def test_a_checkpoint_is_the_dict_of_the_components_states(tmp_path) -> None:
    _, run = _run(_pendulum("pimbrl"), tmp_path / "run")
    state = run.run_dir.load_checkpoint()
    assert {"t", "streams", "collector", "real", "agent", "model", "logger", "schedule"} <= set(state)
    assert state["t"] == run.cfg.total_steps and state["model"]["trainer"]["steps"] == run.model.trainer.steps


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
def test_a_checkpoint_falls_due_by_wall_clock_and_changes_nothing_the_run_learns(tmp_path) -> None:
    """checkpoint_minutes makes a checkpoint due at the next episode end once that much wall time passed (a
    kill then loses at most about that much of a slow run); writing it changes no number the run produces."""
    by_clock = dataclasses.replace(_pendulum("mfrl"), checkpoint_every=100_000, checkpoint_minutes=1e-9)  # every end
    by_steps = dataclasses.replace(by_clock, checkpoint_minutes=0.0)  # by steps only: none before the end
    clock_events, clock_run = _run(by_clock, tmp_path / "clock")
    steps_events, steps_run = _run(by_steps, tmp_path / "steps")
    assert [t for name, t in clock_events if name == "checkpoint"] == [200, 400]  # episode ends before the last
    assert [t for name, t in steps_events if name == "checkpoint"] == []
    returns = [[row["return_mean"] for row in r.run_dir.evaluations.read()] for r in (clock_run, steps_run)]
    assert len(returns[0]) == 2 and returns[0] == returns[1]
    assert bool((clock_run.real.action == steps_run.real.action).all())
