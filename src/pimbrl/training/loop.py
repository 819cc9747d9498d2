"""The training loop: real interaction, update phases, evaluation, logging and checkpoints.

:class:`Trainer` is the model-free loop of the paper's Algorithm A1 (TD3). The model-based methods
(:mod:`pimbrl.training.dyna`) subclass it and fill in :meth:`Trainer.model_phase` and
:meth:`Trainer.sample_batch`; everything else - interaction, evaluation, logs, checkpoints, resume - is
shared, so all methods run under the same harness.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from ..agents import make_agent
from ..buffers import Batch, ReplayBuffer
from ..config import from_dict, to_dict
from ..spaces import ActionAdapter
from .config import TrainConfig
from .evaluation import EvalResult, Evaluator
from .progress import TrainingProgress
from .rundir import RunDirectory, package_versions

__all__ = ["Trainer", "RunSummary", "steps_to_threshold"]


@dataclasses.dataclass(frozen=True)
class RunSummary:
    """Outcome of a run, as stored in ``config.json`` when it finishes."""

    steps: int
    updates: int
    final_return_mean: float | None
    best_return_mean: float | None
    steps_to_threshold: int | None
    wall_s: float


def steps_to_threshold(evaluations: list[dict[str, Any]], threshold: float | None) -> int | None:
    """First evaluation step whose mean return reaches ``threshold`` (``None`` if never)."""
    if threshold is None:
        return None
    for row in evaluations:
        if float(row["return_mean"]) >= threshold:
            return int(float(row["step"]))
    return None


class Trainer:
    """One training run in a run directory (created fresh with :meth:`create`, or :meth:`resume`\\ d)."""

    def __init__(self, cfg: TrainConfig, run_dir: RunDirectory, progress: bool = True) -> None:
        self.cfg = cfg
        self.run_dir = run_dir
        torch.set_num_threads(cfg.threads)
        self.env = gym.make(cfg.env, **cfg.env_kwargs)
        space = self.env.observation_space
        if not isinstance(space, gym.spaces.Box):
            raise ValueError(f"{cfg.env}: pimbrl agents need a Box observation space, got {space}")
        self.obs_dim = int(np.prod(space.shape))
        self.adapter = ActionAdapter(self.env.action_space)
        self.agent = make_agent(cfg.agent, self.obs_dim, self.adapter.dim, cfg.agent_config, cfg.seed)
        self.buffer = ReplayBuffer(
            min(cfg.buffer_size, cfg.total_steps), self.obs_dim, self.adapter.dim, extras=self.buffer_extras()
        )
        self.rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(0,)))
        self.evaluator = Evaluator(cfg.env, cfg.env_kwargs, cfg.eval_episodes, cfg.eval_seed)
        self.show_progress = progress
        # counters (all checkpointed)
        self.t = 0
        self.episode = 0
        self.episode_return = 0.0
        self.episode_length = 0
        self.last_checkpoint_t = 0
        self.update_credit = 0.0
        self.wall_offset = 0.0
        self.first_threshold_step: int | None = None
        self.last_eval: float | None = None
        self.metric_sums: dict[str, float] = {}
        self.metric_counts: dict[str, int] = {}
        self._session_start = time.perf_counter()
        self._tb: Any = None
        self.progress = TrainingProgress(cfg.total_steps, 0, "", enabled=False)

    # ------------------------------------------------------------------ construction
    @classmethod
    def create(cls, cfg: TrainConfig, path: str, progress: bool = True, command: str = "") -> Trainer:
        """A new run in ``path`` (which must not hold another run)."""
        run_dir = RunDirectory(path)
        if run_dir.config_path.exists():
            raise FileExistsError(f"{path} already holds a run; use `pimbrl resume {path}` or choose another --run-dir")
        trainer = cls(cfg, run_dir, progress)  # first: a configuration that cannot run leaves no directory behind
        run_dir.path.mkdir(parents=True, exist_ok=True)
        run_dir.write_config({"status": "running", "config": to_dict(cfg), "versions": package_versions(), "command": command})
        return trainer

    @classmethod
    def resume(cls, path: str, progress: bool = True, inspect_only: bool = False) -> Trainer:
        """Reopen the run in ``path`` at its last checkpoint (or from the start if it has none).

        To continue training, the logs are cut back to the checkpoint. ``inspect_only`` loads the state
        without touching any file (for evaluation and figures, also of a run still in progress).
        """
        run_dir = RunDirectory(path)
        payload = run_dir.read_config()
        cfg = from_dict(TrainConfig, payload["config"])
        trainer = cls(cfg, run_dir, progress)
        if run_dir.checkpoint_path.exists():
            trainer.load_state(run_dir.load_checkpoint())
        if not inspect_only:
            run_dir.truncate_logs(trainer.t)
        return trainer

    @property
    def finished(self) -> bool:
        return self.t >= self.cfg.total_steps

    # ------------------------------------------------------------------ hooks for model-based methods
    def buffer_extras(self) -> dict[str, tuple[int, ...]]:
        """Extra per-transition arrays the real buffer stores (none for model-free)."""
        return {}

    def transition_extras(self, info: dict[str, Any]) -> dict[str, np.ndarray]:
        return {}

    def model_phase(self) -> None:
        """Model training and imagined rollouts before the agent's updates (none for model-free)."""

    def sample_batch(self, batch_size: int) -> Batch:
        """The agent's training batch: real transitions only, for model-free."""
        return self.buffer.sample(batch_size, self.rng)

    def extra_state(self) -> dict[str, Any]:
        return {}

    def load_extra_state(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`extra_state` saved."""

    # ------------------------------------------------------------------ the loop
    def run(self) -> RunSummary:
        """Train until ``total_steps`` real steps, then write the final checkpoint and summary."""
        cfg = self.cfg
        if self.finished:  # e.g. killed between the final checkpoint and the status update
            summary = self.summary()
            if self.run_dir.status != "finished":
                self.run_dir.update_status(status="finished", summary=dataclasses.asdict(summary))
            return summary
        label = f"{cfg.method}/{cfg.agent} {cfg.env} seed {cfg.seed}"
        self.progress = TrainingProgress(cfg.total_steps, self.t, label, enabled=self.show_progress)
        self._session_start = time.perf_counter()
        self._open_tensorboard()
        try:
            obs = self._reset_env(first=self.t == 0)
            steps_at_tick, tick = self.t, time.perf_counter()
            while self.t < cfg.total_steps:
                # 1. act in the real environment and store the transition
                action = self.adapter.sample(self.rng) if self.t < cfg.warmup_steps else self.agent.act(obs)[0]
                next_obs, reward, terminated, truncated, info = self.env.step(self.adapter.to_env(action, self.rng))
                self.buffer.add(obs, action, reward, next_obs, terminated, truncated, **self.transition_extras(info))
                self.t += 1
                self.episode_return += float(reward)
                self.episode_length += 1
                obs = next_obs
                # 2. every update_every steps: model phase (model-based only), then agent updates
                if self.t >= cfg.update_after and self.t % cfg.update_every == 0:
                    self.update_phase()
                # 3. evaluate the deterministic policy on the held-out initial states
                if self.t % cfg.eval_every == 0:
                    self.evaluate()
                if self.t % cfg.log_every == 0:
                    now = time.perf_counter()
                    sps = (self.t - steps_at_tick) / max(now - tick, 1e-9)
                    steps_at_tick, tick = self.t, now
                    self.log_metrics(sps)
                    self.progress.update(self.t, sps=sps)
                # 4. episode end: log it, checkpoint if due, reset
                if terminated or truncated:
                    self.end_episode()
                    if self.t - self.last_checkpoint_t >= cfg.checkpoint_every and self.t < cfg.total_steps:
                        self.save_checkpoint()
                    obs = self._reset_env(first=False)
            if self.t % cfg.eval_every != 0 or self.last_eval is None:
                self.evaluate()
            if self.t % cfg.log_every != 0:
                self.log_metrics((self.t - steps_at_tick) / max(time.perf_counter() - tick, 1e-9))
            self.save_checkpoint()
            summary = self.summary()
            self.run_dir.update_status(status="finished", summary=dataclasses.asdict(summary))
            return summary
        finally:
            self.progress.close()
            self.run_dir.close()
            if self._tb is not None:
                self._tb.close()

    def update_phase(self) -> None:
        """The model phase (model-based methods only), then the agent updates."""
        self.model_phase()
        self.agent_updates()

    def agent_updates(self) -> None:
        """``update_every * utd`` agent updates (a fractional update-to-data ratio carries over)."""
        self.update_credit += self.cfg.update_every * self.cfg.utd
        n = int(math.floor(self.update_credit + 1e-9))
        self.update_credit -= n
        for _ in range(n):
            self._accumulate(self.agent.update(self.sample_batch(self.cfg.agent_config.batch_size)))

    def evaluate(self) -> EvalResult:
        result = self.evaluator.run(lambda o: self.agent.act(o, deterministic=True))
        row = {"step": self.t, **result.summary(), "updates": self.agent.n_updates, "wall_s": self.wall_s}
        self.run_dir.evaluations.append(row)
        self.last_eval = result.mean
        if self.cfg.threshold is not None and self.first_threshold_step is None and result.mean >= self.cfg.threshold:
            self.first_threshold_step = self.t
        self._tb_scalars(
            {"eval/return_mean": result.mean, "eval/return_min": row["return_min"], "eval/return_max": row["return_max"]}
        )
        self.progress.update(self.t, eval_return=result.mean)
        self.progress.message(
            f"step {self.t:>8,d}  eval return {result.mean:10.3f} (min {row['return_min']:.3f}, max {row['return_max']:.3f})  "
            f"updates {self.agent.n_updates:,d}  {self.wall_s:7.1f} s"
        )
        return result

    def end_episode(self) -> None:
        self.episode += 1
        self.run_dir.episodes.append(
            {"step": self.t, "episode": self.episode, "return": self.episode_return, "length": self.episode_length}
        )
        self._tb_scalars({"train/episode_return": self.episode_return})
        self.episode_return = 0.0
        self.episode_length = 0

    # ------------------------------------------------------------------ metrics
    def _accumulate(self, metrics: dict[str, torch.Tensor | float]) -> None:
        for k, v in metrics.items():
            self.metric_sums[k] = self.metric_sums.get(k, 0.0) + float(v)
            self.metric_counts[k] = self.metric_counts.get(k, 0) + 1

    def metric_row(self, sps: float) -> dict[str, Any]:
        row: dict[str, Any] = {
            "step": self.t,
            "wall_s": self.wall_s,
            "steps_per_s": sps,
            "episodes": self.episode,
            "agent_updates": self.agent.n_updates,
            "update_to_data": self.agent.n_updates / max(self.t, 1),
            "real_buffer": len(self.buffer),
        }
        for k in sorted(self.metric_sums):
            row[k] = self.metric_sums[k] / max(self.metric_counts[k], 1)
        return row

    def metric_columns(self) -> list[str]:
        return [
            "step",
            "wall_s",
            "steps_per_s",
            "episodes",
            "agent_updates",
            "update_to_data",
            "real_buffer",
            *self.metric_names(),
        ]

    def metric_names(self) -> list[str]:
        names = ["agent/critic_loss", "agent/q_mean", "agent/actor_loss"]
        if self.cfg.agent == "sac":
            names += ["agent/entropy", "agent/alpha"]
        return names

    def log_metrics(self, sps: float) -> None:
        row = self.metric_row(sps)
        self.run_dir.metrics(self.metric_columns()).append(row)
        self._tb_scalars({k: v for k, v in row.items() if k not in ("step",) and isinstance(v, (int, float))})
        self.metric_sums.clear()
        self.metric_counts.clear()

    @property
    def wall_s(self) -> float:
        return self.wall_offset + (time.perf_counter() - self._session_start)

    def summary(self) -> RunSummary:
        rows = self.run_dir.evaluations.read()
        returns = [float(r["return_mean"]) for r in rows]
        return RunSummary(
            steps=self.t,
            updates=self.agent.n_updates,
            final_return_mean=returns[-1] if returns else None,
            best_return_mean=max(returns) if returns else None,
            steps_to_threshold=steps_to_threshold(rows, self.cfg.threshold),
            wall_s=self.wall_s,
        )

    # ------------------------------------------------------------------ TensorBoard
    def _open_tensorboard(self) -> None:
        if not self.cfg.tensorboard:
            return
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise RuntimeError("tensorboard=True needs the tensorboard package: pip install 'pimbrl[tensorboard]'") from exc
        self._tb = SummaryWriter(log_dir=str(self.run_dir.path / "tb"), purge_step=self.t if self.t > 0 else None)

    def _tb_scalars(self, values: dict[str, float]) -> None:
        if self._tb is not None:
            for k, v in values.items():
                self._tb.add_scalar(k, float(v), self.t)

    # ------------------------------------------------------------------ state
    def _reset_env(self, first: bool) -> np.ndarray:
        obs, _ = self.env.reset(seed=self.cfg.seed if first else None)
        return obs

    def state(self) -> dict[str, Any]:
        return {
            "t": self.t,
            "episode": self.episode,
            "last_checkpoint_t": self.t,
            "update_credit": self.update_credit,
            "wall_s": self.wall_s,
            "first_threshold_step": self.first_threshold_step,
            "last_eval": self.last_eval,
            "metric_sums": dict(self.metric_sums),
            "metric_counts": dict(self.metric_counts),
            "rng": self.rng.bit_generator.state,
            "env_rng": self.env.unwrapped.np_random.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "agent": self.agent.state_dict(),
            "buffer": self.buffer.state_dict(),
            "extra": self.extra_state(),
        }

    def save_checkpoint(self) -> None:
        """Write the full state at an episode boundary (before the next reset), atomically."""
        self.last_checkpoint_t = self.t
        self.run_dir.save_checkpoint(self.state())

    def load_state(self, state: dict[str, Any]) -> None:
        self.t = int(state["t"])
        self.episode = int(state["episode"])
        self.last_checkpoint_t = int(state["last_checkpoint_t"])
        self.update_credit = float(state["update_credit"])
        self.wall_offset = float(state["wall_s"])
        self.first_threshold_step = state["first_threshold_step"]
        self.last_eval = state["last_eval"]
        self.metric_sums = dict(state["metric_sums"])
        self.metric_counts = dict(state["metric_counts"])
        self.rng.bit_generator.state = state["rng"]
        env_rng = np.random.Generator(np.random.PCG64())
        env_rng.bit_generator.state = state["env_rng"]
        self.env.unwrapped.np_random = env_rng
        torch.set_rng_state(state["torch_rng"])
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.load_extra_state(state["extra"])
        self._session_start = time.perf_counter()
