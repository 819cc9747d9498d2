"""Model-error comparison: a data-only and a physics-informed model trained on the same buffer.

1. Collect ``transitions`` real transitions with a uniformly random policy from the task's own initial
   states (the *in-sample* distribution); hold out ``test_transitions`` of them.
2. Collect ``test_transitions`` transitions from *another* distribution (out-of-sample, per environment:
   declared by each system: :attr:`pimbrl.systems.System.out_of_sample`).
3. Train two models from the same initialisation for the same number of gradient steps: ``data`` with
   ``L_D`` only; ``physics`` with ``L_D + w_E L_E``, where ``L_E`` is applied to unlabelled pairs drawn as a
   PiMBRL run draws them (:func:`study_pairs`: the same sampler, sources and imagination, with the random
   policy that collected the data).
4. Write ``model_errors.csv`` (``model, split, mse``: one row per test transition), ``summary.json`` and
   ``model_errors.png`` (histograms of log10 MSE, in- and out-of-sample).

``summary.json`` names its spec, the environment and the whole configuration, and their SHA-256
(``spec_sha256``, of the canonical JSON: :func:`spec_sha256`), beside the machine (commit, CPU model), so a
page that quotes it can say which settings made a figure.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from ..config import validate
from ..envs import PhysicsEnv, Task
from ..fileio import atomic_write_bytes
from ..models import ModelEnv, ModelTrainer, PhysicsResidual, TransitionData, TransitionModel, make_model
from ..models.residual import as_scheme
from ..models.state_sources import PhysicsPairs, choose_sources
from ..physics import Physics
from ..spaces import ActionAdapter
from ..systems import get_system
from ..training.methods import PhysicsLoss
from ..training.rundir import provenance
from ..training.threads import pin_threads
from .model_eval_config import PHYSICS_FLAGS, ModelEvalConfig, defaults

__all__ = [
    "ModelEvalConfig",
    "check_physics_settings",
    "collect_transitions",
    "network_of",
    "out_of_sample",
    "run_model_eval",
    "study_pairs",
]


def out_of_sample(env_id: str) -> Callable[[Task, np.random.Generator, int], np.ndarray]:
    """The out-of-sample initial states its system declares for ``env_id`` (a one-line error where none is)."""
    system = get_system(env_id)
    if system is None or system.out_of_sample is None:
        raise ValueError(
            f"model-eval needs a system that declares an out-of-sample set (System.out_of_sample), and {env_id!r} declares none"
        )
    return system.out_of_sample


def _random_env_actions(task: Task, rng: np.random.Generator, n: int) -> Any:
    space = task.action_space
    if isinstance(space, gym.spaces.Discrete):
        return rng.integers(space.n, size=n) + int(space.start)
    if isinstance(space, gym.spaces.Box):
        return rng.uniform(space.low, space.high, size=(n, *space.shape)).astype(space.dtype)
    raise TypeError(f"random actions need a Discrete or Box action space, got {space}")


def collect_transitions(
    task: Task,
    rng: np.random.Generator,
    n: int,
    initial_states: Callable[[np.random.Generator, int], np.ndarray],
    batch: int = 64,
    max_steps: int | None = None,
) -> TransitionData:
    """``n`` physical transitions under a uniformly random policy, ``batch`` environments at a time."""
    horizon = max_steps or task.max_episode_steps
    u = initial_states(rng, batch)
    k = np.zeros(batch, dtype=np.int64)
    states, actions, nexts = [], [], []
    count = 0
    while count < n:
        a_phys = task.physical_action(_random_env_actions(task, rng, batch), batch)
        out = task.advance(u, a_phys, k)
        ok = ~out.diverged
        states.append(u[ok])
        actions.append(a_phys[ok])
        nexts.append(out.state[ok])
        count += int(ok.sum())
        u = out.state
        k = k + 1
        done = out.terminated | (k >= horizon)
        if done.any():
            u[done] = initial_states(rng, int(done.sum()))
            k[done] = 0
    cat = lambda parts: torch.as_tensor(np.concatenate(parts)[:n], dtype=torch.float32)
    canonical = task.physics.canonical
    return TransitionData(cat([canonical(s) for s in states]), cat(actions), cat([canonical(s) for s in nexts]))


def _random_actions(task: Task, rng: np.random.Generator, n: int) -> torch.Tensor:
    """``n`` physical actions of the uniformly random policy."""
    return torch.as_tensor(task.physical_action(_random_env_actions(task, rng, n), n), dtype=torch.float32)


def study_pairs(
    task: Task,
    physics: Physics,
    model: TransitionModel,
    sources: tuple[str, ...],
    observed: torch.Tensor,
    length: int,
    rng: np.random.Generator,
) -> tuple[PhysicsPairs, Callable[[], None]]:
    """The physics loss's pairs for a model trained on collected data, drawn as the training loop draws them.

    The same sampler (:class:`~pimbrl.models.state_sources.PhysicsPairs`) and the same imagination
    (:class:`~pimbrl.models.ModelEnv`) as a PiMBRL run; the policy is the uniformly random one that collected
    the data. ``policy``: observed states with random actions; ``imagined``: the pairs of ``length``-step
    model rollouts from the observed states (made again by the returned function, as the model changes);
    the broad sources from the observed states. Returns the sampler and that refresh function.
    """
    adapter = ActionAdapter(task.action_space)
    imagination = ModelEnv(model, task, adapter, rng, use_path=False, physics=physics)
    pool: dict[str, torch.Tensor] = {"state": observed[:0], "action": torch.zeros(0, physics.action_dim)}

    def refresh() -> None:
        if "imagined" not in sources or length < 1:
            return
        start = observed.double().numpy()
        policy = lambda obs: rng.uniform(-1.0, 1.0, size=(len(obs), adapter.dim)).astype(np.float32)
        batch = imagination.rollout(start, np.zeros(len(start), dtype=np.int64), policy, length)
        pool["state"] = torch.as_tensor(batch.state, dtype=torch.float32)
        pool["action"] = torch.as_tensor(batch.physical_action, dtype=torch.float32)

    pairs = PhysicsPairs(
        physics,
        sources,
        lambda rows: observed.index_select(0, rows),
        len(observed),
        lambda rows, g: _random_actions(task, g, len(rows)),
        lambda: len(pool["state"]),
        lambda rows: (pool["state"].index_select(0, rows), pool["action"].index_select(0, rows)),
        rng,
    )
    return pairs, refresh


def network_of(cfg: ModelEvalConfig, physics: Physics) -> str:
    """The network model-eval trains: ``cfg.network``, with ``auto`` the paper's (ConvLSTM for a PDE, an MLP for an ODE)."""
    if cfg.network == "auto":
        return "convlstm" if physics.is_field else "mlp"
    if (cfg.network == "mlp") == bool(physics.is_field):
        kind = "a PDE" if physics.is_field else "an ODE"
        raise ValueError(f"--network {cfg.network} is not a network for {kind}: use auto (the paper's)")
    return cfg.network


def check_physics_settings(cfg: ModelEvalConfig) -> None:
    """A one-line error for a physics-loss setting that model-eval does not read (it has no training schedule)."""
    default = PhysicsLoss()
    for f in dataclasses.fields(PhysicsLoss):
        if f.name not in PHYSICS_FLAGS and getattr(cfg.physics, f.name) != getattr(default, f.name):
            flag = f"--physics.{f.name.replace('_', '-')}"
            raise ValueError(f"{flag} sets when a training run's physics loss starts; model-eval uses it from the first step")


def spec_sha256(env_id: str, config: dict[str, Any]) -> str:
    """SHA-256 of a model evaluation's spec: the environment and its configuration as canonical JSON."""
    text = json.dumps({"env": env_id, "config": config}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def run_model_eval(
    env_id: str, run_dir: str | Path, config: ModelEvalConfig | None = None, log: Callable[[str], None] = print
) -> dict[str, Any]:
    """Run the comparison for ``env_id`` and write its outputs into ``run_dir``; returns the summary."""
    cfg = config or ModelEvalConfig(**defaults(env_id))
    validate(cfg)
    check_physics_settings(cfg)
    oos = out_of_sample(env_id)
    pin_threads(cfg.threads)
    out_dir = Path(run_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    env = gym.make(env_id)
    assert isinstance(env.unwrapped, PhysicsEnv)
    task = env.unwrapped.task
    physics = task.physics
    rng = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()

    in_data = collect_transitions(task, rng, cfg.transitions + cfg.test_transitions, task.sample_initial_states)
    perm = torch.from_numpy(rng.permutation(len(in_data)))
    train, test_in = in_data.take(perm[cfg.test_transitions :]), in_data.take(perm[: cfg.test_transitions])
    test_out = collect_transitions(task, rng, cfg.test_transitions, lambda g, n: oos(task, g, n), max_steps=10)
    log(f"{env_id}: {len(train)} training, {len(test_in)} in-sample and {len(test_out)} out-of-sample test transitions")

    models = {}
    settings = dataclasses.asdict(cfg)
    summary: dict[str, Any] = {
        "env": env_id,
        "machine": provenance(),
        "config": settings,
        "spec_sha256": spec_sha256(env_id, settings),
        "train_s": {},
    }
    sources = choose_sources(cfg.physics.sources, physics)
    for name in ("data", "physics"):
        torch.manual_seed(cfg.seed)
        model = make_model(physics, n_intermediate=cfg.n_intermediate, kind=network_of(cfg, physics))
        scheme = as_scheme(cfg.scheme)
        residual = PhysicsResidual(physics, model.n_intermediate, scheme, cfg.physics.units) if name == "physics" else None
        trainer = ModelTrainer(model, residual, lr=cfg.lr, weight_physics=cfg.physics.weight)
        trainer.ensure_normalization(train)
        batch_rng = np.random.default_rng(cfg.seed + 1)
        start = time.perf_counter()
        unlabelled, refresh = None, None
        if residual is not None:
            unlabelled, refresh = study_pairs(task, physics, model, sources, train.state, cfg.imagined_length, batch_rng)
        done = 0
        while done < cfg.steps:
            chunk = min(cfg.refresh_every, cfg.steps - done)
            if refresh is not None:
                refresh()
            metrics = trainer.fit(chunk, cfg.batch_size, batch_rng, labelled=train, unlabelled=unlabelled)
            done += chunk
            log(f"  {name:7s} step {done:5d}: " + ", ".join(f"{k} {v:.3e}" for k, v in metrics.items()))
        summary["train_s"][name] = time.perf_counter() - start
        models[name] = trainer

    rows = []
    for name, trainer in models.items():
        for split, data in (("in", test_in), ("out", test_out)):
            mse = trainer.per_transition_mse(data)
            rows += [(name, split, float(v)) for v in mse]
            summary[f"{name}_{split}"] = {
                "mean": float(mse.mean()),
                "median": float(np.median(mse)),
                "p90": float(np.percentile(mse, 90)),
            }
    csv_text = "model,split,mse\n" + "".join(f"{m},{s},{v!r}\n" for m, s, v in rows)
    atomic_write_bytes(out_dir / "model_errors.csv", csv_text.encode())
    summary["wall_s"] = time.perf_counter() - t0
    atomic_write_bytes(out_dir / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
    _plot(rows, out_dir / "model_errors.png", env_id)
    for split in ("in", "out"):
        d, p = summary[f"data_{split}"], summary[f"physics_{split}"]
        log(
            f"  {split + '-sample':14s} MSE  data-only: mean {d['mean']:.3e} median {d['median']:.3e}   "
            f"physics-informed: mean {p['mean']:.3e} median {p['median']:.3e}"
        )
    return summary


def _plot(rows: list[tuple[str, str, float]], path: Path, title: str) -> None:
    from ..plotting import plt, save_figure

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, split in zip(axes, ("in", "out")):
        vals = {m: np.log10(np.maximum([v for mm, s, v in rows if mm == m and s == split], 1e-16)) for m in ("data", "physics")}
        lo = min(v.min() for v in vals.values())
        hi = max(v.max() for v in vals.values())
        bins = np.linspace(lo, hi if hi > lo else lo + 1, 40)
        for m, color in (("data", "tab:orange"), ("physics", "tab:blue")):
            label = f"{'data-only (MBRL)' if m == 'data' else 'physics-informed (PiMBRL)'}: median {10 ** np.median(vals[m]):.2e}"
            ax.hist(vals[m], bins=bins, alpha=0.55, color=color, label=label)
        ax.set_title(f"{title}: {'in-sample' if split == 'in' else 'out-of-sample'}")
        ax.set_xlabel("log10 next-state MSE")
        ax.legend(fontsize=8)
    axes[0].set_ylabel("test transitions")
    fig.tight_layout()
    save_figure(fig, path)
