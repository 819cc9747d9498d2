"""Data-only MBRL on any Gymnasium env with Box spaces (issue 28): the observation as the state, the reward learned."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.models import LearnedReward
from pimbrl.systems.observed import ObservedEnv
from pimbrl.training import RunDirectory

from .test_training import TINY

FLAGS = ["--steps", "600", "--warmup-steps", "200", "--update-after", "200", "--eval-every", "300", "--eval-episodes", "2"]
FLAGS += ["--model.start-after", "200", "--imagine.rollout-length", "5", "--check.threshold", "1.0", "--checkpoint-every", "200"]


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
def test_mbrl_runs_on_gymnasium_s_own_pendulum_with_a_learned_reward(tmp_path) -> None:
    run = tmp_path / "run"
    assert main(["train", "Pendulum-v1", "--method", "mbrl", *FLAGS, "--run-dir", str(run), *TINY]) == 0
    payload = json.loads((run / "config.json").read_text())
    assert payload["config"]["method"]["network"] == "mlp" and payload["system"]["origin"] == "gymnasium"
    lines = (run / "metrics.csv").read_text().splitlines()
    header = lines[0].split(",")
    last = dict(zip(header, lines[-1].split(",")))
    assert float(last["model/reward_mse"]) < 0.5 and int(last["imagined_total"]) > 0  # the model and its reward were used
    # the learned reward in the checkpoint predicts Gymnasium's reward on fresh transitions
    state = RunDirectory(run).load_checkpoint()["model"]["reward_model"]
    reward = LearnedReward(3, 1)
    reward.load_state(state)
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=123)
    u, a, un, r = [], [], [], []
    rng = np.random.default_rng(0)
    for _ in range(200):
        action = rng.uniform(-2, 2, size=1).astype(np.float32)
        nxt, rew, *_ = env.step(action)
        u.append(obs), a.append(action), un.append(nxt), r.append(rew)
        obs = nxt
    predicted = reward.predict(np.array(u), np.array(a), np.array(un))
    spread = float(np.var(r))
    assert float(np.mean((predicted - np.array(r)) ** 2)) < 0.2 * spread  # explains most of the reward's variance


@pytest.mark.slow
def test_a_data_only_run_resumes_as_if_uninterrupted(tmp_path) -> None:
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    assert main(["train", "Pendulum-v1", "--method", "mbrl", *FLAGS, "--run-dir", str(whole), *TINY]) == 0
    short = [*FLAGS]
    short[short.index("--steps") + 1] = "400"
    assert main(["train", "Pendulum-v1", "--method", "mbrl", *short, "--run-dir", str(cut), *TINY]) == 0
    assert main(["resume", str(cut), "--total-steps", "600", "--quiet"]) == 0
    assert (whole / "episodes.csv").read_text() == (cut / "episodes.csv").read_text()
    a, b = RunDirectory(whole).load_checkpoint(), RunDirectory(cut).load_checkpoint()
    ra, rb = a["model"]["reward_model"]["module"], b["model"]["reward_model"]["module"]
    assert all(torch.equal(ra[k], rb[k]) for k in ra)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["Pendulum-v1", "--method", "pimbrl"], "pimbrl needs the system's equation, and Pendulum-v1 declares none"),
        (["CartPole-v1", "--method", "mbrl"], "CartPole-v1: data-only MBRL needs a 1-D Box action space"),
        (["Pendulum-v1", "--method", "known-scheme"], "--method known-scheme needs the system's equation"),
        (["Pendulum-v1", "--method", "mbrl", "--imagine.select-episodes", "3"], "--imagine.select-episodes needs initial states"),
    ],
)
def test_what_a_data_only_run_cannot_do_is_a_one_line_error(argv, message, tmp_path, capsys) -> None:
    assert main(["train", *argv, "--run-dir", str(tmp_path / "r"), "--print-config"]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_the_observed_env_reports_its_observation_as_the_state() -> None:
    env = ObservedEnv(gym.make("Pendulum-v1"))
    obs, info = env.reset(seed=0)
    np.testing.assert_array_equal(info["state"], obs.astype(np.float64))
    obs, _, _, _, info = env.step(np.array([5.0], dtype=np.float32))
    assert info["step_index"] == 1 and info["physical_action"].tolist() == [2.0]  # clipped to the bounds
    np.testing.assert_array_equal(info["state"], obs.astype(np.float64))
