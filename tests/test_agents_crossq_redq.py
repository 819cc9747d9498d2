"""CrossQ and REDQ: updates, checkpoints, batch renormalisation, REDQ's target subsets, settings, small runs."""

from __future__ import annotations

import dataclasses
import math
import typing

import numpy as np
import pytest
import torch

from pimbrl.agents import AGENT_TYPES, CrossQConfig, REDQConfig, make_agent
from pimbrl.agents.networks import BatchRenorm
from pimbrl.agents.redq import draw_subset
from pimbrl.buffers import Batch
from pimbrl.cli import main
from pimbrl.config import ConfigError, validate
from pimbrl.training import resolve_config

from .test_training import _table
from .test_validation import test_every_float_field_rejects_non_finite_values as _rejects_non_finite
from .test_validation import test_every_numeric_field_has_an_upper_bound as _has_upper_bound

OBS, ACT = 4, 2
#: small networks of each agent (CrossQ's actor every 3rd update, as by default)
SMALL = {
    "crossq": CrossQConfig(hidden=(16,), critic_hidden=(32, 32), batch_size=32),
    "redq": REDQConfig(hidden=(16, 16), batch_size=32, n_critics=5, target_subset=2),
}


def _batch(seed: int, size: int = 32) -> Batch:
    g = torch.Generator().manual_seed(seed)
    return Batch(
        obs=torch.randn(size, OBS, generator=g),
        action=torch.rand(size, ACT, generator=g) * 2 - 1,
        reward=torch.randn(size, generator=g),
        next_obs=torch.randn(size, OBS, generator=g),
        terminated=(torch.rand(size, generator=g) < 0.1).float(),
        truncated=torch.zeros(size),
    )


def _params(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


@pytest.mark.parametrize("name", ["crossq", "redq"])
def test_updates_give_finite_metrics_and_move_actor_critics_and_temperature(name: str) -> None:
    agent = make_agent(SMALL[name], OBS, ACT, seed=0)
    actor, critic, log_alpha = _params(agent.actor), _params(agent.critic), float(agent.log_alpha.detach())
    seen: set[str] = set()
    for i in range(6):
        metrics = agent.update(_batch(i))
        assert all(v.dim() == 0 and not v.requires_grad and math.isfinite(float(v)) for v in metrics.values()), metrics
        seen |= set(metrics)
    assert seen == {"agent/critic_loss", "agent/q_mean", "agent/actor_loss", "agent/entropy", "agent/alpha"}
    assert agent.n_updates == 6
    assert all(not torch.equal(a, b) for a, b in zip(actor, _params(agent.actor)))
    assert all(not torch.equal(a, b) for a, b in zip(critic, _params(agent.critic)))
    assert float(agent.log_alpha.detach()) != log_alpha
    obs = np.random.default_rng(0).standard_normal((5, OBS))
    for deterministic in (True, False):
        a = agent.act(obs, deterministic=deterministic)
        assert a.shape == (5, ACT) and a.dtype == np.float32 and np.all(np.abs(a) <= 1.0)


def test_crossq_updates_the_actor_every_policy_delay_critic_updates() -> None:
    agent = make_agent(dataclasses.replace(SMALL["crossq"], policy_delay=3), OBS, ACT, seed=0)
    with_actor = ["agent/actor_loss" in agent.update(_batch(i)) for i in range(7)]
    assert with_actor == [False, False, True, False, False, True, False]


@pytest.mark.parametrize("name", ["crossq", "redq"])
def test_checkpoint_roundtrip_gives_identical_actions_and_updates(name: str) -> None:
    a = make_agent(SMALL[name], OBS, ACT, seed=3)
    for i in range(5):
        a.update(_batch(i))
    state = a.state_dict()
    b = make_agent(SMALL[name], OBS, ACT, seed=99)
    b.load_state_dict(state)
    obs = np.random.default_rng(1).standard_normal((3, OBS))
    np.testing.assert_array_equal(a.act(obs, deterministic=True), b.act(obs, deterministic=True))
    np.testing.assert_array_equal(a.act(obs), b.act(obs))  # the exploration stream is restored too
    for i in (5, 6):  # CrossQ: 6 is an actor update
        ma, mb = a.update(_batch(i)), b.update(_batch(i))
        assert {k: float(v) for k, v in ma.items()} == {k: float(v) for k, v in mb.items()}
    for k, v in a.critic.state_dict().items():
        assert torch.equal(v, b.critic.state_dict()[k]), k
    np.testing.assert_array_equal(a.act(obs), b.act(obs))
    policy = make_agent(SMALL[name], OBS, ACT, seed=7)
    policy.load_policy_state(a.policy_state())
    np.testing.assert_array_equal(a.act(obs, deterministic=True), policy.act(obs, deterministic=True))


# ----------------------------------------------------------------------------------------------- CrossQ
def test_crossq_has_no_target_networks_and_its_critic_statistics_train_in_one_joint_pass() -> None:
    agent = make_agent(SMALL["crossq"], OBS, ACT, seed=0)
    assert not any("targ" in k for k in agent._modules()) and not hasattr(agent, "critic_targ")
    critic_state = agent.state_dict()["modules"]["critic"]
    buffers = [k for k in critic_state if k.endswith(("running_mean", "running_var", "steps"))]
    assert len(buffers) == 3 * 3  # input and two hidden layers
    batch = _batch(0)
    agent.update(batch)
    assert not agent.critic.training  # left in eval mode: only the critic step normalises with its batch
    first = agent.critic.norms[0]
    # the input statistics are those of the concatenation of (s, a) and (s', a'): the obs columns show it
    both = torch.cat([batch.obs, batch.next_obs])
    torch.testing.assert_close(first.running_mean[:, 0, :OBS], 0.01 * both.mean(0).expand(2, -1))
    torch.testing.assert_close(first.running_var[:, 0, :OBS], 0.99 + 0.01 * both.var(0, unbiased=False).expand(2, -1))
    for i in range(1, 6):  # the actor steps (updates 3 and 6) evaluate the critics without moving the statistics
        agent.update(_batch(i))
    assert all(int(norm.steps) == 6 for norm in agent.critic.norms)
    assert all(not torch.equal(n.running_mean, torch.zeros_like(n.running_mean)) for n in agent.critic.norms)
    # in eval mode a Q-value does not depend on the rest of the batch, and evaluating moves nothing
    before = {k: v.clone() for k, v in agent.critic.state_dict().items()}
    with torch.no_grad():
        q_all = agent.critic(batch.obs, batch.action)
        q_one = agent.critic(batch.obs[:1], batch.action[:1])
    torch.testing.assert_close(q_all[:, :1], q_one)
    assert all(torch.equal(v, agent.critic.state_dict()[k]) for k, v in before.items())


def test_batch_renorm_normalises_with_the_batch_then_corrects_to_the_running_statistics() -> None:
    x = torch.randn(2, 64, 5) * 3 + 1
    warm = BatchRenorm(2, 5, warmup=0)
    plain = BatchRenorm(2, 5, warmup=10**6)
    for layer in (warm, plain):
        layer.running_mean.fill_(0.5)
        layer.running_var.fill_(4.0)
    eval_out = warm.eval()(x)
    # after the warm-up, renormalisation's value is the running statistics' normalisation (r, d unclipped here)
    torch.testing.assert_close(warm.train()(x), eval_out)
    # before it (or with plain batch normalisation), every feature of the batch is standardised
    y = plain.train()(x)
    torch.testing.assert_close(y.mean(1), torch.zeros(2, 5), atol=1e-5, rtol=0)
    torch.testing.assert_close(y.var(1, unbiased=False), torch.ones(2, 5), atol=1e-3, rtol=0)
    assert int(plain.steps) == 1 and int(warm.steps) == 1
    torch.testing.assert_close(plain.running_mean, 0.99 * 0.5 + 0.01 * x.mean(1, keepdim=True))
    # the renormalised output still carries the batch statistics' gradient (it is not the eval-mode graph)
    xg = x.clone().requires_grad_(True)
    warm.train()(xg).pow(2).sum().backward()
    assert xg.grad is not None and torch.isfinite(xg.grad).all()


def test_crossq_refuses_critic_layer_norm() -> None:
    with pytest.raises(ConfigError, match="critic_layer_norm does not apply to crossq"):
        make_agent(SMALL["crossq"], OBS, ACT, seed=0, critic_layer_norm=True)


# ------------------------------------------------------------------------------------------------- REDQ
def test_draw_subset_draws_m_distinct_critics_reproducibly() -> None:
    g = torch.Generator().manual_seed(0)
    draws = [draw_subset(10, 2, g) for _ in range(200)]
    assert all(d.shape == (2,) and d.dtype == torch.int64 and 0 <= d[0] < d[1] < 10 for d in draws)
    assert len({tuple(d.tolist()) for d in draws}) > 30  # many pairs of the 45
    again = torch.Generator().manual_seed(0)
    assert all(torch.equal(d, draw_subset(10, 2, again)) for d in draws)
    assert draw_subset(4, 4, g).tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="3 of 2"):
        draw_subset(2, 3, g)


@pytest.mark.parametrize("m", [1, 2, 5])
def test_redq_target_is_the_minimum_over_m_target_critics_and_the_actor_ascends_the_mean(m: int) -> None:
    agent = make_agent(dataclasses.replace(SMALL["redq"], target_subset=m, gamma=0.9), OBS, ACT, seed=0)
    agent.log_alpha.data.fill_(-30.0)  # no entropy terms
    with torch.no_grad():  # member i of the targets and the critics outputs the constant c_i
        c = torch.tensor([3.0, -1.0, 4.0, 1.0, 5.0])
        for net in (agent.critic, agent.critic_targ):
            net.weights[-1].zero_()
            net.biases[-1].copy_(c.view(5, 1, 1))
    drawn: list[torch.Tensor] = []
    subset = agent.critic_targ.subset

    def spy(obs: torch.Tensor, action: torch.Tensor, members: torch.Tensor) -> torch.Tensor:
        drawn.append(members)
        return subset(obs, action, members)

    agent.critic_targ.subset = spy  # type: ignore[method-assign]
    batch = _batch(0)
    metrics = agent.update(batch)
    assert len(drawn) == 1 and len(set(drawn[0].tolist())) == m
    target = batch.reward + 0.9 * (1 - batch.terminated) * c[drawn[0]].min()
    expected = (c.view(5, 1) - target).pow(2).mean(dim=1).sum()
    assert float(metrics["agent/critic_loss"]) == pytest.approx(float(expected), rel=1e-5)
    # the actor's loss is minus the mean of the critics (after their step: within Adam's first step)
    assert float(metrics["agent/actor_loss"]) == pytest.approx(-float(c.mean()), abs=0.05)
    subsets = {tuple(d.tolist()) for d in drawn}
    for i in range(1, 20):
        agent.update(_batch(i))
    subsets |= {tuple(d.tolist()) for d in drawn}
    assert len(drawn) == 20 and (len(subsets) > 1 if m < 5 else subsets == {(0, 1, 2, 3, 4)})


# ---------------------------------------------------------------------------------------------- settings
def test_subset_larger_than_the_ensemble_is_one_line_naming_both(tmp_path, capsys) -> None:
    with pytest.raises(ConfigError, match=r"agent.target_subset 3 is more than agent.n_critics 2"):
        REDQConfig(n_critics=2, target_subset=3)
    argv = ["train", "pendulum", "--agent", "redq", "--agent.n-critics", "2", "--agent.target-subset", "3"]
    assert main([*argv, "--run-dir", str(tmp_path / "r"), "--print-config"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "agent.target_subset 3" in err and "agent.n_critics 2" in err
    assert not (tmp_path / "r").exists()
    REDQConfig(n_critics=2, target_subset=2)  # equal is fine


@pytest.mark.parametrize(
    ("over", "message"),
    [
        ({"critic_norm": "layer"}, "critic_norm must be one of 'renorm', 'batch'"),
        ({"adam_beta1": 1.0}, "adam_beta1 must be in [0.0, 1.0)"),
        ({"norm_momentum": 1.0}, "norm_momentum must be in"),
        ({"critic_hidden": ()}, "critic_hidden must be 1 to"),
        ({"policy_delay": 0}, "policy_delay must be > 0"),
    ],
)
def test_crossq_settings_are_checked(over, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")):
        validate(CrossQConfig(**over))


@pytest.mark.parametrize("cls", [CrossQConfig, REDQConfig])
def test_every_numeric_setting_is_finite_and_bounded_with_the_bound_in_its_help(cls: type) -> None:
    """The generic checks of test_validation, on the new types."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if typing.get_origin(hints[f.name]) is tuple:
            continue
        base = next(a for a in (*typing.get_args(hints[f.name]), hints[f.name]) if a is not type(None))
        if base in (int, float):
            _has_upper_bound(cls, f.name, base)
        if base is float:
            for bad in (math.inf, -math.inf, math.nan):
                _rejects_non_finite(cls, f.name, bad)
        if f.metadata.get("check") is not None:
            assert "must be" in f.metadata["help"], f.name


def test_the_agents_have_their_papers_defaults_and_their_own_flags(tmp_path, capsys) -> None:
    cfg = resolve_config("pimbrl/Pendulum-v0", {"agent": "crossq"}).agent
    assert isinstance(cfg, CrossQConfig) and cfg.sac_family
    assert (cfg.critic_hidden, cfg.hidden, cfg.batch_size, cfg.policy_delay) == ((2048, 2048), (256, 256), 256, 3)
    assert (cfg.actor_lr, cfg.adam_beta1, cfg.norm_momentum, cfg.init_alpha) == (1e-3, 0.5, 0.99, 1.0)
    redq = resolve_config("pimbrl/Pendulum-v0", {"agent": "redq", "agent.policy_delay": 20}).agent
    assert isinstance(redq, REDQConfig) and (redq.n_critics, redq.target_subset, redq.policy_delay) == (10, 2, 20)
    with pytest.raises(TypeError):  # no target networks, no polyak
        CrossQConfig(polyak=0.99)  # type: ignore[call-arg]
    argv = ["train", "pendulum", "--agent", "crossq", "--agent.polyak", "0.9", "--print-config"]
    assert main([*argv, "--run-dir", str(tmp_path / "r")]) == 2
    assert "not crossq" in capsys.readouterr().err
    assert main(["train", "--help-all"]) == 0
    full = capsys.readouterr().out
    assert "--agent.critic-hidden" in full and "--agent.target-subset" in full and "--agent.adam-beta1" in full
    assert {n for n, t in AGENT_TYPES.items() if t.sac_family} == {"sac", "crossq", "redq"}


# ------------------------------------------------------------------------------------------------- runs
TINY = ["--steps", "300", "--warmup-steps", "100", "--update-after", "100", "--eval-every", "150", "--eval-episodes", "2",
        "--agent.hidden", "32,32", "--agent.batch-size", "32", "--quiet"]  # fmt: skip
#: each agent's own small settings (REDQ: more updates than steps, a delayed actor)
OWN = {
    "crossq": ["--agent.critic-hidden", "64,64"],
    "redq": ["--agent.n-critics", "4", "--utd", "2", "--agent.policy-delay", "2"],
}


@pytest.mark.slow
@pytest.mark.parametrize("agent", ["crossq", "redq"])
def test_a_small_pendulum_run_finishes_and_logs_entropy_and_temperature(agent: str, tmp_path) -> None:
    run = tmp_path / agent
    assert main(["train", "pendulum", "--agent", agent, *TINY, *OWN[agent], "--run-dir", str(run)]) == 0
    evals = _table(run, "evaluations.csv")
    assert [int(r["step"]) for r in evals] == [150, 300] and all(math.isfinite(float(r["return_mean"])) for r in evals)
    metrics = _table(run, "metrics.csv")
    assert metrics and all(math.isfinite(float(metrics[-1][k])) for k in ("agent/critic_loss", "agent/entropy", "agent/alpha"))


@pytest.mark.slow
@pytest.mark.parametrize("agent", ["crossq", "redq"])
def test_a_small_model_based_run_trains_either_agent(agent: str, tmp_path) -> None:
    dyna = ["--method", "mbrl", "--model.start-after", "100", "--fit.steps", "5", "--check.threshold", "1e3",
            "--imagine.rollout-length", "20", "--fit.batch-size", "32", "--imagine.rollouts", "16", "--check.validation-size", "64"]  # fmt: skip
    run = tmp_path / agent
    assert main(["train", "pendulum", "--agent", agent, *TINY, *OWN[agent], *dyna, "--run-dir", str(run)]) == 0
    assert [int(r["step"]) for r in _table(run, "evaluations.csv")] == [150, 300]
