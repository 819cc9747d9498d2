"""Agents: learning on a toy task, determinism, TD targets, buffer and action mapping."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium import spaces

from pimbrl.agents import AGENT_TYPES, TD3Config, make_agent
from pimbrl.agents.networks import CriticEnsemble
from pimbrl.buffers import Batch, ReplayBuffer
from pimbrl.spaces import ActionAdapter
from pimbrl.training import create_run, resolve_config, train

from .test_training import _table
from .toy_env import register

register()
SMALL = {"agent.hidden": (64, 64), "agent.batch_size": 64, "agent.actor_lr": 3e-3, "agent.critic_lr": 3e-3}


def _train_toy(tmp_path, agent: str, env: str = "toy/Reach-v0", steps: int = 3000, seed: int = 0, **over):
    cfg = resolve_config(
        env,
        {
            "agent": agent,
            "seed": seed,
            "total_steps": steps,
            "warmup_steps": 300,
            "update_after": 300,
            "eval_every": 500,
            "eval_episodes": 10,
            "checkpoint_every": 1000,
            **SMALL,
            **over,
        },
    )
    run = create_run(cfg, str(tmp_path / f"{agent}-{seed}"), progress=False)
    return train(run), run


@pytest.mark.slow
@pytest.mark.parametrize("agent", ["td3", "ddpg", "sac", "td3-layer-norm"])
def test_agent_learns_the_toy_task(tmp_path, agent: str) -> None:
    name, _, norm = agent.partition("-")
    over = {"experimental.critic_layer_norm": True} if norm else {}
    summary, trainer = _train_toy(tmp_path, name, steps=2000, **over)
    rng = np.random.default_rng(0)
    random_return = trainer.evaluator.run(lambda o: rng.uniform(-1, 1, (len(o), 2))).mean
    # a random policy returns about -5 on this task; a learned one reaches the origin quickly
    assert random_return < -3.0
    assert summary.best_return_mean is not None and summary.best_return_mean > -1.0, trainer.run_dir.evaluations.read()


def test_critic_layer_norm_makes_q_invariant_to_the_scale_of_a_hidden_layer() -> None:
    torch.manual_seed(0)
    obs, act = torch.randn(32, 5), torch.rand(32, 2) * 2 - 1
    for layer_norm in (True, False):
        critic = CriticEnsemble(5, 2, (16, 16), n=2, layer_norm=layer_norm)
        q = critic(obs, act)
        assert torch.allclose(critic.first(obs, act), q[0], atol=1e-6)
        with torch.no_grad():  # scale the first layer's pre-activations by 7: layer norm removes the scale
            critic.weights[0].mul_(7.0)
            critic.biases[0].mul_(7.0)
        moved = (critic(obs, act) - q).abs().max().item()
        assert (moved < 1e-4) if layer_norm else (moved > 1e-2), (layer_norm, moved)


@pytest.mark.slow  # several seconds: the whole suite runs it, the fast tier does not
def test_td3_drives_discrete_cartpole_style_actions(tmp_path) -> None:
    summary, _ = _train_toy(tmp_path, "td3", env="toy/ReachDiscrete-v0", steps=2000)
    assert summary.best_return_mean is not None and summary.best_return_mean > -2.0


@pytest.mark.slow
def test_same_seed_gives_identical_metrics(tmp_path) -> None:
    _, a = _train_toy(tmp_path / "a", "td3", steps=1200)
    _, b = _train_toy(tmp_path / "b", "td3", steps=1200)
    _, c = _train_toy(tmp_path / "c", "td3", steps=1200, seed=1)

    def table(t, name, drop=("wall_s", "steps_per_s")):
        return [{k: v for k, v in r.items() if k not in drop} for r in getattr(t.run_dir, name).read()]

    assert table(a, "evaluations") == table(b, "evaluations")
    assert table(a, "episodes") == table(b, "episodes")
    assert _table(a.run_dir.path, "metrics.csv") == _table(b.run_dir.path, "metrics.csv")
    assert table(a, "evaluations") != table(c, "evaluations")


@pytest.mark.parametrize("name", ["td3", "ddpg", "sac"])
def test_td_target_bootstraps_through_truncation(name: str) -> None:
    torch.manual_seed(0)
    extra = {"target_smoothing": False} if name == "td3" else {}
    agent = make_agent(AGENT_TYPES[name](hidden=(8,), gamma=0.9, **extra), 3, 1, seed=0)

    n_critics = 1 if name == "ddpg" else 2
    agent.critic_targ.forward = lambda obs, act: torch.full((n_critics, obs.shape[0]), 10.0)
    if name == "sac":  # remove the entropy bonus from the target
        agent.log_alpha.data.fill_(-30.0)
    batch = Batch(
        obs=torch.zeros(3, 3),
        action=torch.zeros(3, 1),
        reward=torch.tensor([1.0, 1.0, 1.0]),
        next_obs=torch.zeros(3, 3),
        terminated=torch.tensor([0.0, 1.0, 0.0]),
        truncated=torch.tensor([0.0, 0.0, 1.0]),
    )
    with torch.no_grad():
        q = agent.critic(batch.obs, batch.action)
    expected_target = torch.tensor([1.0 + 0.9 * 10, 1.0, 1.0 + 0.9 * 10])  # truncation still bootstraps
    expected = (q - expected_target).pow(2).mean(dim=1).sum()
    metrics = agent.update(batch)
    assert float(metrics["agent/critic_loss"]) == pytest.approx(float(expected), rel=1e-4)


def test_agent_state_roundtrip_reproduces_updates() -> None:
    rng = np.random.default_rng(0)
    buf = ReplayBuffer(500, 4, 2)
    buf.add(
        rng.standard_normal((300, 4)),
        rng.uniform(-1, 1, (300, 2)),
        rng.standard_normal(300),
        rng.standard_normal((300, 4)),
        np.zeros(300),
        np.zeros(300),
    )
    for name in ("td3", "sac"):
        a = make_agent(AGENT_TYPES[name](hidden=(16,)), 4, 2, seed=3)
        for _ in range(5):
            a.update(buf.sample(32, np.random.default_rng(1)))
        state = a.state_dict()
        b = make_agent(AGENT_TYPES[name](hidden=(16,)), 4, 2, seed=99)
        b.load_state_dict(state)
        batch = buf.sample(32, np.random.default_rng(2))
        ma, mb = a.update(batch), b.update(batch)
        assert {k: float(v) for k, v in ma.items()} == {k: float(v) for k, v in mb.items()}
        obs = rng.standard_normal((3, 4))
        np.testing.assert_array_equal(a.act(obs), b.act(obs))


def test_replay_buffer_stores_termination_and_truncation_apart() -> None:
    buf = ReplayBuffer(4, 2, 1)
    for i in range(6):  # wraps around
        buf.add(np.full(2, i), [0.5], float(i), np.full(2, i + 1), terminated=i == 4, truncated=i == 5)
    assert len(buf) == 4 and buf.total_added == 6
    b = buf.gather(torch.arange(4))
    stored = {int(o[0]): (float(te), float(tr)) for o, te, tr in zip(b.obs, b.terminated, b.truncated)}
    assert stored[4] == (1.0, 0.0) and stored[5] == (0.0, 1.0) and stored[3] == (0.0, 0.0)
    assert isinstance(b, Batch) and b.obs.dtype == torch.float32
    with pytest.raises(ValueError, match="non-finite"):
        buf.add(np.array([np.nan, 0.0]), [0.0], 0.0, np.zeros(2), False, False)
    with pytest.raises(ValueError, match="empty"):
        ReplayBuffer(3, 2, 1).sample(2, np.random.default_rng(0))


def test_action_adapter_mappings() -> None:
    box = ActionAdapter(spaces.Box(np.array([-0.025, -0.025], np.float32), np.array([0.075, 0.075], np.float32)))
    np.testing.assert_allclose(box.to_env(np.array([-1.0, 1.0])), [-0.025, 0.075], rtol=1e-6)
    np.testing.assert_allclose(box.to_env(np.array([0.0, 0.0])), [0.025, 0.025], rtol=1e-6)
    disc = ActionAdapter(spaces.Discrete(2))
    assert disc.dim == 1 and disc.to_env(np.array([0.3])) == 1 and disc.to_env(np.array([-0.3])) == 0
    np.testing.assert_array_equal(disc.to_env(np.array([[0.1], [-0.1]])), [1, 0])
    # while training, a is the probability (a + 1) / 2 of pushing right
    draws = disc.to_env(np.full((20_000, 1), 0.5), np.random.default_rng(0))
    assert abs(draws.mean() - 0.75) < 0.01
    assert disc.to_env(np.full((100, 1), 1.0), np.random.default_rng(0)).min() == 1
    multi = ActionAdapter(spaces.Discrete(3, start=1))
    assert multi.dim == 3 and multi.to_env(np.array([0.1, 0.9, -1.0])) == 2
    with pytest.raises(ValueError, match="bounded"):
        ActionAdapter(spaces.Box(-np.inf, np.inf, (1,)))


def test_replay_buffer_keeps_the_newest_rows_of_an_oversized_batch() -> None:
    buf = ReplayBuffer(5, 1, 1, extras={"k": (1,)})
    buf.add(np.zeros(2), np.zeros(2), np.zeros(2), np.zeros(2), np.zeros(2), np.zeros(2), k=np.zeros(2))
    buf.add(np.arange(8.0), np.zeros(8), np.arange(8.0), np.zeros(8), np.zeros(8), np.zeros(8), k=np.arange(8.0))
    assert len(buf) == 5 and buf.total_added == 10
    assert sorted(buf.reward.tolist()) == [3.0, 4.0, 5.0, 6.0, 7.0]
    assert sorted(buf.extras["k"][:, 0].tolist()) == [3.0, 4.0, 5.0, 6.0, 7.0]


def test_preactivation_penalty_pulls_the_actor_off_tanh_saturation() -> None:
    """A TD3 actor driven into saturation: with the penalty its pre-tanh outputs shrink, without it they do not."""
    obs = torch.randn(256, 3)
    batch = Batch(obs, torch.zeros(256, 1), torch.zeros(256), obs, torch.zeros(256), torch.zeros(256))
    sizes = {}
    for penalty in (0.0, 10.0):
        agent = make_agent(TD3Config(hidden=(16,), policy_delay=1, actor_lr=0.05, preactivation_penalty=penalty), 3, 1, seed=0)
        with torch.no_grad():
            agent.actor.net[-2].bias.fill_(5.0)  # tanh(5) = 0.9999: saturated
        before = float(agent.actor.preactivation(obs).abs().mean())
        for _ in range(50):
            agent.update(batch)
        sizes[penalty] = float(agent.actor.preactivation(obs).abs().mean()) / before
    assert sizes[10.0] < 0.5 < sizes[0.0], sizes
