"""Time per 1,000 TD3 updates (batch 128, 2x256 networks, one thread): pimbrl vs Stable-Baselines3.

Both agents update from replay buffers filled with the same random transitions; each is timed over
repeats of 1,000 updates in the same process, interleaved, and the fastest repeat is kept for each.
Problem sizes: Pendulum (obs 3, action 1) and KS (obs 64, action 4).

Usage: ``pip install stable-baselines3`` then ``python benchmarks/bench_td3_updates.py``
(writes benchmarks/results/td3_updates.json).
"""

from __future__ import annotations

import argparse
import time

import _common
import gymnasium as gym
import numpy as np
import torch

from pimbrl.agents import TD3Config, make_agent
from pimbrl.buffers import ReplayBuffer

UPDATES = 1_000
REPEATS = 5


def _sb3_model(obs_dim: int, act_dim: int):
    from stable_baselines3 import TD3 as SB3TD3
    from stable_baselines3.common.logger import configure

    class Dummy(gym.Env):
        observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (act_dim,), np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros(obs_dim, np.float32), {}

        def step(self, action):
            return np.zeros(obs_dim, np.float32), 0.0, False, False, {}

    model = SB3TD3(
        "MlpPolicy", Dummy(), policy_kwargs={"net_arch": [256, 256]}, batch_size=128, learning_starts=0,
        learning_rate=1e-3, gamma=0.99, tau=0.005, policy_delay=2, seed=0, device="cpu", verbose=0,
    )  # fmt: skip
    model.set_logger(configure(None, []))
    return model


def bench(obs_dim: int, act_dim: int, n: int = 20_000) -> dict:
    rng = np.random.default_rng(0)
    obs = rng.standard_normal((n, obs_dim)).astype(np.float32)
    act = rng.uniform(-1, 1, (n, act_dim)).astype(np.float32)
    rew = rng.standard_normal(n).astype(np.float32)
    nxt = np.roll(obs, -1, axis=0)
    sb3 = _sb3_model(obs_dim, act_dim)
    sb3.replay_buffer.add  # noqa: B018 - make sure the buffer exists
    for i in range(0, n, 1000):  # SB3's buffer: one env, rows of shape (1, dim)
        for j in range(i, min(i + 1000, n)):
            sb3.replay_buffer.add(obs[j : j + 1], nxt[j : j + 1], act[j : j + 1], rew[j : j + 1], np.array([False]), [{}])
    ours = make_agent(TD3Config(batch_size=128, hidden=(256, 256)), obs_dim, act_dim, seed=0)
    buf = ReplayBuffer(n, obs_dim, act_dim)
    buf.add(obs, act, rew, nxt, np.zeros(n), np.zeros(n))
    sb3.train(gradient_steps=50, batch_size=128)
    for _ in range(50):
        ours.update(buf.sample(128, rng))
    t_sb3, t_ours = [], []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        sb3.train(gradient_steps=UPDATES, batch_size=128)
        t_sb3.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for _ in range(UPDATES):
            ours.update(buf.sample(128, rng))
        t_ours.append(time.perf_counter() - t0)
    row = {"obs_dim": obs_dim, "act_dim": act_dim, "pimbrl_s_per_1000": min(t_ours), "sb3_s_per_1000": min(t_sb3)}
    row["ratio_pimbrl_over_sb3"] = row["pimbrl_s_per_1000"] / row["sb3_s_per_1000"]
    print(
        f"obs {obs_dim:3d}, act {act_dim}: pimbrl {row['pimbrl_s_per_1000']:.2f} s / 1000 updates, "
        f"SB3 {row['sb3_s_per_1000']:.2f} s / 1000 updates, ratio {row['ratio_pimbrl_over_sb3']:.2f}",
        flush=True,
    )
    return row


def main() -> None:
    import stable_baselines3

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _common.add_load_argument(parser)
    args = parser.parse_args()

    rows = [bench(3, 1), bench(64, 4)]
    payload = {"sb3_version": stable_baselines3.__version__, "torch_threads": torch.get_num_threads(), "rows": rows}
    print(f"recorded {_common.record('td3_updates', payload, load=args.load)}")


if __name__ == "__main__":
    main()
