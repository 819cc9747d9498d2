"""The Dyna-style model-based loop of the paper's Algorithm 1: MBRL (data loss) and PiMBRL (data + physics).

Every ``update_every`` real steps, after the real buffer D^r has ``update_after`` transitions, one update
phase runs (:meth:`DynaTrainer.model_phase`, then the agent updates of the shared :class:`Trainer`):

1. **model training** — once D^r holds ``n_sM`` transitions: ``model_steps`` gradient steps of the
   data loss L_D on real transitions (the held-out ones excluded); for PiMBRL, once D^r and D^f together
   hold ``n_sR`` transitions, each step also carries the physics loss L_E on unlabelled state-action
   pairs: real states with actions of the current policy, and imagined pairs once imagination has begun
   (the physics loss needs no label, so it can help the model *reach* the accuracy threshold);
2. **accuracy check** — L_D on the most recent held-out real transitions; the model is *in use* while it
   is below lambda (and the run has not switched to model-free fine-tuning);
3. **imagination** — while in use: ``rollouts`` rollouts of ``l_M`` chained model steps from real start
   states, actions from the current policy with exploration noise, rewards and terminations from the
   physics; they go into the imagined buffer D^f, whose oldest entries they replace;
4. **agent updates** — ``update_every * utd`` TD3/DDPG/SAC updates on batches mixing real and imagined
   transitions (``real_ratio`` real while the model is in use, else all real).

MBRL is this loop with ``physics_weight`` ignored (no physics loss); MFRL is the plain :class:`Trainer`.
Every phase's wall-clock time, the model losses, whether the model is in use, the real and imagined
counts and the update-to-data ratio are logged to ``metrics.csv``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from ..buffers import Batch, ReplayBuffer
from ..envs import PhysicsEnv
from ..models import ModelEnv, ModelTrainer, PhysicsResidual, TransitionData, make_model
from ..models.residual import Scheme
from .config import TrainConfig
from .loop import Trainer
from .rundir import RunDirectory

__all__ = ["DynaTrainer", "PHASES"]

PHASES = ("model_train", "model_check", "imagine", "agent_update", "evaluate")


class DynaTrainer(Trainer):
    """Model-based training (``method`` ``mbrl`` or ``pimbrl``) on a pimbrl environment."""

    def __init__(self, cfg: TrainConfig, run_dir: RunDirectory, progress: bool = True) -> None:
        if cfg.method not in ("mbrl", "pimbrl"):
            raise ValueError(f"DynaTrainer runs mbrl or pimbrl, not {cfg.method!r}")
        super().__init__(cfg, run_dir, progress)
        base = self.env.unwrapped
        self.task = base.task
        self.physics = base.physics
        d = cfg.dyna
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(np.random.SeedSequence(cfg.seed, spawn_key=(4,)).generate_state(1)[0]))
            self.model = make_model(self.physics, n_intermediate=d.n_intermediate)
        residual = (
            PhysicsResidual(self.physics, self.model.n_intermediate, _scheme(d.residual)) if cfg.method == "pimbrl" else None
        )
        self.model_trainer = ModelTrainer(self.model, residual, lr=d.model_lr, weight_physics=d.physics_weight)
        self.imagined = ReplayBuffer(d.imagined_buffer_size, self.obs_dim, self.adapter.dim, extras=self.buffer_extras())
        self.model_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(5,)))
        self.model_env = ModelEnv(self.model, self.task, self.adapter, self.model_rng)
        self.model_in_use = False
        self.finetuning = False
        self.val_mse = float("inf")
        self.model_metrics: dict[str, float] = {}
        self.phase_s = dict.fromkeys(PHASES, 0.0)
        self.imagined_total = 0

    # ------------------------------------------------------------------ real transitions carry physics
    def buffer_extras(self) -> dict[str, tuple[int, ...]]:
        base = self.env.unwrapped
        if not isinstance(base, PhysicsEnv):
            raise ValueError(f"{self.cfg.method} needs a pimbrl environment with a known Physics; {self.cfg.env} is not one")
        n, m = base.physics.state_dim, base.physics.action_dim
        return {"state": (n,), "next_state": (n,), "phys_action": (m,), "k": (1,), "holdout": (1,), "valid": (1,)}

    def _reset_env(self, first: bool) -> np.ndarray:
        obs = super()._reset_env(first)
        self._state = self.physics.canonical(self.env.unwrapped.state)
        return obs

    def transition_extras(self, info: dict[str, Any]) -> dict[str, np.ndarray]:
        base = self.env.unwrapped
        nxt = self.physics.canonical(base.state)
        extras = {
            "state": self._state,
            "next_state": nxt,
            "phys_action": base.last_physical_action,
            "k": np.array([base.elapsed_steps - 1]),
            "holdout": np.array([float(self.model_rng.random() < self.cfg.dyna.holdout_fraction)]),
            "valid": np.array([0.0 if info.get("diverged") else 1.0]),
        }
        self._state = nxt
        return extras

    # ------------------------------------------------------------------ the model phase
    def model_phase(self) -> None:
        d = self.cfg.dyna
        self.check_finetune()
        if self.finetuning:
            self.model_in_use = False
            return
        n_real = len(self.buffer)
        if n_real >= d.start_model_after and d.model_steps > 0:
            t0 = time.perf_counter()
            train_idx, _ = self._split_indices()
            labelled = BufferView(self.buffer, train_idx)
            if not bool(self.model.fitted):  # normalisation statistics from the first training data
                self.model_trainer.ensure_normalization(labelled.all())
            unlabelled = None
            if self.cfg.method == "pimbrl" and n_real + len(self.imagined) >= d.start_physics_after:
                unlabelled = UnlabelledPairs(self, train_idx)
            self.model_metrics = self.model_trainer.fit(d.model_steps, d.model_batch_size, self.model_rng, labelled, unlabelled)
            self.phase_s["model_train"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            _, holdout_idx = self._split_indices()
            recent = holdout_idx[-d.validation_size :]  # _split_indices orders by age, oldest first
            self.val_mse = self.model_trainer.validation_mse(BufferView(self.buffer, recent).all())
            self.model_in_use = self.val_mse < d.threshold
            self.phase_s["model_check"] += time.perf_counter() - t0
        if self.model_in_use and d.rollouts > 0:
            t0 = time.perf_counter()
            self.imagine(d.rollouts)
            self.phase_s["imagine"] += time.perf_counter() - t0

    def check_finetune(self) -> None:
        """Switch (once, for good) to model-free fine-tuning when the configured criterion is met."""
        d = self.cfg.dyna
        if self.finetuning:
            return
        by_return = d.finetune_return is not None and self.last_eval is not None and self.last_eval >= d.finetune_return
        by_steps = d.finetune_after is not None and self.t >= d.finetune_after
        if by_return or by_steps:
            self.finetuning = True
            self.progress.message(f"step {self.t:>8,d}  switching to model-free fine-tuning")

    def imagine(self, n_rollouts: int) -> None:
        """Roll the model from sampled start states and store the imagined transitions in D^f."""
        d = self.cfg.dyna
        n_img = int(round(n_rollouts * d.imagined_start_fraction)) if len(self.imagined) else 0
        starts = [self.buffer.sample_indices(n_rollouts - n_img, self.model_rng)]
        states = [self.buffer.extra("state", starts[0])]
        ks = [self.buffer.extra("k", starts[0])]
        if n_img:
            # continue only imagined rollouts that had not ended (no termination, time left)
            live = (self.imagined.terminated[: len(self.imagined)] < 0.5) & (self.imagined.truncated[: len(self.imagined)] < 0.5)
            live_idx = torch.nonzero(live).reshape(-1)
            if len(live_idx):
                idx = live_idx[torch.from_numpy(self.model_rng.integers(0, len(live_idx), size=n_img))]
                states.append(self.imagined.extra("next_state", idx))
                ks.append(self.imagined.extra("k", idx) + 1)
            else:
                starts.append(self.buffer.sample_indices(n_img, self.model_rng))
                states.append(self.buffer.extra("state", starts[-1]))
                ks.append(self.buffer.extra("k", starts[-1]))
        u = torch.cat(states).double().numpy()
        k = torch.cat(ks).reshape(-1).long().numpy()
        batch = self.model_env.rollout(u, k, lambda obs: self.agent.act(obs), d.rollout_length)
        if len(batch):
            self.imagined.add(
                batch.obs, batch.action, batch.reward, batch.next_obs, batch.terminated, batch.truncated,
                state=batch.state, next_state=batch.next_state, phys_action=batch.phys_action,
                k=batch.k[:, None].astype(np.float32), holdout=np.zeros((len(batch), 1), np.float32),
                valid=np.ones((len(batch), 1), np.float32),
            )  # fmt: skip
            self.imagined_total += len(batch)

    def sample_batch(self, batch_size: int) -> Batch:
        if not self.model_in_use or len(self.imagined) == 0:
            return self.buffer.sample(batch_size, self.rng)
        n_real = int(round(batch_size * self.cfg.dyna.real_ratio))
        parts = [self.buffer.sample(n_real, self.rng)] if n_real else []
        if batch_size - n_real:
            parts.append(self.imagined.sample(batch_size - n_real, self.rng))
        return Batch.concat(parts)

    def agent_updates(self) -> None:
        t0 = time.perf_counter()
        super().agent_updates()
        self.phase_s["agent_update"] += time.perf_counter() - t0

    def evaluate(self) -> Any:
        t0 = time.perf_counter()
        result = super().evaluate()
        self.phase_s["evaluate"] += time.perf_counter() - t0
        return result

    # ------------------------------------------------------------------ helpers
    def _split_indices(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Indices of the model's training and held-out real transitions, oldest first; steps that blew up
        (whose stored next state is the pre-step state) are in neither."""
        n = len(self.buffer)
        age = (torch.arange(n) - self.buffer.pos) % self.buffer.capacity if n == self.buffer.capacity else torch.arange(n)
        order = torch.argsort(age)
        hold = self.buffer.extras["holdout"][order, 0] > 0.5
        valid = self.buffer.extras["valid"][order, 0] > 0.5
        return order[~hold & valid], order[hold & valid]

    # ------------------------------------------------------------------ logging and state
    def metric_names(self) -> list[str]:
        names = super().metric_names() + [
            "model/data_loss",
            "model/val_mse",
            "model/in_use",
            "model/finetuning",
            "imagined_buffer",
            "imagined_total",
        ]
        if self.cfg.method == "pimbrl":
            names.append("model/physics_loss")
        return names + [f"time/{p}_s" for p in PHASES]

    def metric_row(self, sps: float) -> dict[str, Any]:
        row = super().metric_row(sps)
        row.update(
            {
                "model/data_loss": self.model_metrics.get("model/data_loss"),
                "model/physics_loss": self.model_metrics.get("model/physics_loss"),
                "model/val_mse": None if not np.isfinite(self.val_mse) else self.val_mse,
                "model/in_use": int(self.model_in_use),
                "model/finetuning": int(self.finetuning),
                "imagined_buffer": len(self.imagined),
                "imagined_total": self.imagined_total,
                **{f"time/{p}_s": v for p, v in self.phase_s.items()},
            }
        )
        return row

    def extra_state(self) -> dict[str, Any]:
        return {
            "model_trainer": self.model_trainer.state_dict(),
            "imagined": self.imagined.state_dict(),
            "model_rng": self.model_rng.bit_generator.state,
            "model_in_use": self.model_in_use,
            "finetuning": self.finetuning,
            "val_mse": self.val_mse,
            "model_metrics": dict(self.model_metrics),
            "phase_s": dict(self.phase_s),
            "imagined_total": self.imagined_total,
        }

    def load_extra_state(self, state: dict[str, Any]) -> None:
        self.model_trainer.load_state_dict(state["model_trainer"])
        self.imagined.load_state_dict(state["imagined"])
        self.model_rng.bit_generator.state = state["model_rng"]
        self.model_in_use = bool(state["model_in_use"])
        self.finetuning = bool(state["finetuning"])
        self.val_mse = float(state["val_mse"])
        self.model_metrics = dict(state["model_metrics"])
        self.phase_s = dict(state["phase_s"])
        self.imagined_total = int(state["imagined_total"])


class UnlabelledPairs:
    """State-action pairs for the physics loss, which needs no label: real training states with actions of
    the current policy (exploration noise included) and, once imagination has begun, the imagined buffer's
    pairs - half and half. The physics loss thus shapes the model from its first phase on, before the
    model is accurate enough to be used."""

    def __init__(self, trainer: DynaTrainer, train_idx: torch.Tensor) -> None:
        self.t = trainer
        self.idx = train_idx

    def __len__(self) -> int:
        return len(self.idx) + len(self.t.imagined)

    def sample(self, batch: int, rng: np.random.Generator) -> TransitionData:
        t = self.t
        n_img = batch // 2 if len(t.imagined) else 0
        rows = self.idx[torch.from_numpy(rng.integers(0, len(self.idx), size=batch - n_img))]
        obs = t.buffer.obs.index_select(0, rows).numpy()
        phys = t.task.physical_action(t.adapter.to_env(t.agent.act(obs), rng), len(rows))
        states = [t.buffer.extra("state", rows)]
        actions = [torch.as_tensor(phys, dtype=torch.float32)]
        if n_img:
            img = torch.from_numpy(rng.integers(0, len(t.imagined), size=n_img))
            states.append(t.imagined.extra("state", img))
            actions.append(t.imagined.extra("phys_action", img))
        return TransitionData(torch.cat(states), torch.cat(actions))


class BufferView:
    """Physical transitions ``idx`` of a replay buffer, gathered batch by batch (never copied whole)."""

    def __init__(self, buf: ReplayBuffer, idx: torch.Tensor, labels: bool = True) -> None:
        self.buf = buf
        self.idx = idx
        self.labels = labels

    def __len__(self) -> int:
        return len(self.idx)

    def take(self, rows: torch.Tensor) -> TransitionData:
        sel = self.idx.index_select(0, rows)
        nxt = self.buf.extra("next_state", sel) if self.labels else None
        return TransitionData(self.buf.extra("state", sel), self.buf.extra("phys_action", sel), nxt)

    def sample(self, batch: int, rng: np.random.Generator) -> TransitionData:
        return self.take(torch.from_numpy(rng.integers(0, len(self.idx), size=batch)))

    def all(self) -> TransitionData:
        return self.take(torch.arange(len(self.idx)))


def _scheme(name: str) -> Scheme:
    return "solver" if name == "solver" else "etd"
