"""The paper's figures, each made from run directories by one function (and one `pimbrl figure` command).

* :func:`ks_contours` — KS space-time contours: one uncontrolled and three controlled test episodes
  (the paper's Fig. 9);
* :func:`burgers_episodes` — the Burgers state surface with random and with learned control, with the
  actions and rewards of each episode (Fig. 7);
* :func:`model_error_histograms` — histograms of the model errors written by `pimbrl model-eval`
  (Figs. 6 and 11);
* :func:`rollout_snapshots` — model-predicted KS states after l_M chained model steps against the true
  environment, from three test states, for several rollout lengths (Fig. 12).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from .. import training
from ..envs import PhysicsEnv
from ..fileio import MAX_CSV_BYTES, MAX_JSON_BYTES, UnsafeFileError, read_below, strict_json
from ..plotting import plot_spacetime, plt, save_figure
from ..simulate import EpisodeRecord, run_episode
from ..training import Run
from ..training.legacy import method_and_agent

__all__ = ["burgers_episodes", "check_fits", "ks_contours", "load_run", "model_error_histograms", "rollout_snapshots"]


#: the environment of each environment-specific figure: (id, name in messages)
_FIGURE_ENVS = {
    "ks-contours": ("pimbrl/KuramotoSivashinsky-v0", "Kuramoto-Sivashinsky"),
    "burgers": ("pimbrl/Burgers-v0", "Burgers"),
}


def load_run(run_dir: str | Path) -> Run:
    """A run at its latest checkpoint (agent, model, config, environments); no file is changed."""
    return training.load_run(run_dir, require_checkpoint=True)


def check_fits(kind: str, run_dir: str | Path) -> None:
    """Raise ``ValueError`` where the figure ``kind`` cannot be drawn from the run in ``run_dir``.

    Read from its ``config.json`` before anything is loaded: ``ks-contours`` needs a KS run, ``burgers`` a
    Burgers run, ``rollouts`` a run with a model. The message names the run's environment and method and
    the figure that fits it.
    """
    run = training.RunDirectory(run_dir)
    run.check_entries()
    cfg = run.recorded_config()
    env, (method, _) = cfg.get("env"), method_and_agent(cfg)
    if kind in _FIGURE_ENVS:
        want, name = _FIGURE_ENVS[kind]
        if env != want:
            other = [k for k, (e, _) in _FIGURE_ENVS.items() if e == env]
            hint = f"; `pimbrl figure {other[0]}` draws that one" if other else ""
            raise ValueError(f"`pimbrl figure {kind}` needs a {name} run; {run_dir} is a {env} run{hint}")
    if kind == "rollouts" and method == "mfrl":
        raise ValueError(f"`pimbrl figure rollouts` needs a run with a model (mbrl, pimbrl, ...); {run_dir} is an mfrl run")


def _policy(trainer: Any) -> Any:
    adapter = trainer.adapter
    return lambda obs: adapter.to_env(trainer.agent.act(np.asarray(obs)[None], deterministic=True)[0])


def _test_states(trainer: Run, n: int) -> np.ndarray:
    """The first ``n`` initial states of the run's test episodes (those its evaluations start from)."""
    return trainer.task.test_initial_states(n, trainer.cfg.eval_seed)


def _make_env(trainer: Run) -> tuple[gym.Env, Any, gym.spaces.Box]:
    """A fresh single environment of the run's task, its physics and its (continuous) action space."""
    env = gym.make(trainer.cfg.env, **trainer.cfg.env_kwargs)
    unwrapped = env.unwrapped
    if not isinstance(unwrapped, PhysicsEnv):
        raise TypeError(f"{trainer.cfg.env} is not a pimbrl environment")
    space = env.action_space
    if not isinstance(space, gym.spaces.Box):
        raise TypeError(f"{trainer.cfg.env} has a {type(space).__name__} action space; this figure needs a Box")
    return env, unwrapped.physics, space


def ks_contours(run_dir: str | Path, out: str | Path, controlled: int = 3) -> Path:
    """Space-time contours of an uncontrolled and ``controlled`` agent-controlled KS test episodes."""
    check_fits("ks-contours", run_dir)
    trainer = load_run(run_dir)
    env, physics, space = _make_env(trainer)
    states = _test_states(trainer, controlled + 1)
    records: list[tuple[str, EpisodeRecord]] = []
    zero = np.zeros(space.shape, np.float32)
    records.append(("uncontrolled", run_episode(env, lambda o: zero, options={"initial_state": states[0]})))
    policy = _policy(trainer)
    for i in range(1, controlled + 1):
        records.append((f"controlled (test state {i})", run_episode(env, policy, options={"initial_state": states[i]})))
    lim = max(float(np.abs(r.states).max()) for _, r in records)
    fig, axes = plt.subplots(len(records), 1, figsize=(10, 2.6 * len(records)), sharex=True)
    for ax, (name, rec) in zip(axes, records):
        plot_spacetime(ax, rec.states, physics.x, rec.control_dt, title=f"{name}: return {rec.total_return:.1f}", vlim=lim)
    fig.suptitle(f"{trainer.cfg.method.name} {trainer.cfg.agent.name}, step {trainer.t:,d}")
    fig.tight_layout()
    return save_figure(fig, out)


def burgers_episodes(run_dir: str | Path, out: str | Path, seed: int = 0) -> Path:
    """Burgers: the state surface and the actions and rewards of a random-action and a controlled episode."""
    check_fits("burgers", run_dir)
    trainer = load_run(run_dir)
    env, physics, space = _make_env(trainer)
    start = _test_states(trainer, 1)[0]
    rng = np.random.default_rng(seed)
    random_rec = run_episode(
        env, lambda o: rng.uniform(space.low, space.high).astype(np.float32), options={"initial_state": start}
    )
    control_rec = run_episode(env, _policy(trainer), options={"initial_state": start})
    fig = plt.figure(figsize=(13, 8))
    for row, (name, rec) in enumerate((("random actions", random_rec), ("learned control", control_rec))):
        t = np.arange(rec.states.shape[0]) * rec.control_dt
        ax = fig.add_subplot(2, 2, 2 * row + 1, projection="3d")
        tt, xx = np.meshgrid(t, physics.x, indexing="ij")
        ax.plot_surface(tt, xx, rec.states, cmap="viridis", linewidth=0, antialiased=True)
        ref = physics.reference(np.arange(rec.states.shape[0]))
        ax.plot(t, np.full_like(t, physics.x[-1]), ref, color="r", lw=1.5, label="reference")
        ax.set_xlabel("time")
        ax.set_ylabel("x")
        ax.set_zlabel("u")
        ax.set_title(f"{name}: return {rec.total_return:.2f}")
        ax2 = fig.add_subplot(2, 2, 2 * row + 2)
        ta = np.arange(rec.length) * rec.control_dt
        for i in range(rec.actions.shape[1]):
            ax2.step(ta, rec.actions[:, i], where="post", label=f"a{i + 1}")
        ax2.set_ylabel("action")
        ax2.set_xlabel("time")
        twin = ax2.twinx()
        twin.plot(ta, rec.rewards, color="k", lw=1.2, label="reward")
        twin.set_ylabel("reward")
        ax2.legend(loc="upper left", fontsize=8)
        twin.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, out)


def model_error_histograms(model_eval_dir: str | Path, out: str | Path) -> Path:
    """Histograms of the per-transition errors in ``model_errors.csv`` (written by `pimbrl model-eval`)."""
    from .model_eval import _plot

    path = Path(model_eval_dir) / "model_errors.csv"
    try:
        text = read_below(model_eval_dir, "model_errors.csv", MAX_CSV_BYTES).decode("utf-8", errors="replace")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path} not found: run `pimbrl model-eval ENV --run-dir {model_eval_dir}` first") from None
    try:
        rows = [(str(r["model"]), str(r["split"]), float(r["mse"])) for r in csv.DictReader(io.StringIO(text))]
    except (KeyError, TypeError, ValueError, csv.Error) as exc:
        raise UnsafeFileError(f"{path}: not a table `pimbrl model-eval` wrote ({type(exc).__name__}: {exc})") from None
    if not all(math.isfinite(mse) and mse >= 0 for _, _, mse in rows):
        raise UnsafeFileError(f"{path}: an mse that is not a finite number >= 0; the table was edited or damaged")
    title = Path(model_eval_dir).name
    try:
        summary = strict_json(read_below(model_eval_dir, "summary.json", MAX_JSON_BYTES), Path(model_eval_dir) / "summary.json")
    except FileNotFoundError:
        summary = {}
    if isinstance(summary, dict) and isinstance(summary.get("env"), str):
        title = summary["env"]
    _plot(rows, Path(out), title)
    return Path(out)


def rollout_snapshots(run_dir: str | Path, out: str | Path, lengths: Sequence[int] = (3, 8, 40, 120), n_states: int = 3) -> Path:
    """Model-predicted states after ``l`` chained model steps against the true environment (same actions).

    A run whose model was never trained (its budget ended before ``dyna.start_model_after``) is refused.
    """
    check_fits("rollouts", run_dir)
    trainer = load_run(run_dir)
    model = trainer.transition_model
    if model is None or trainer.model is None:
        raise ValueError(f"{run_dir} is a {trainer.cfg.method.name} run without a model; use a run of a method with one")
    if trainer.model.trainer.steps == 0 and trainer.model.trainer.optimizer is not None:  # a physics model: no training
        start = trainer.cfg.dyna.start_after
        raise ValueError(
            f"{run_dir}: its model was never trained (the run has {trainer.t:,d} steps and its model starts after "
            f"model.start_after = {start}); train a run with more --steps or a lower --model.start-after"
        )
    physics = trainer.physics
    task = trainer.task
    states = _test_states(trainer, n_states)
    horizon = max(lengths)
    true = np.empty((horizon + 1, n_states, physics.state_dim))
    pred = np.empty_like(true)
    true[0] = pred[0] = states
    k = np.zeros(n_states, dtype=np.int64)
    with torch.no_grad():
        for step in range(horizon):
            obs = task.observe(true[step], k)
            a_phys = task.physical_action(trainer.adapter.to_env(trainer.agent.act(obs, deterministic=True)), n_states)
            true[step + 1], _ = physics.advance(true[step], a_phys, k)
            pred[step + 1] = (
                model.predict_next(torch.as_tensor(pred[step], dtype=torch.float32), torch.as_tensor(a_phys, dtype=torch.float32))
                .double()
                .numpy()
            )
            k = k + 1
    x = getattr(physics, "x", np.arange(physics.state_dim))
    fig, axes = plt.subplots(n_states, len(lengths), figsize=(3.4 * len(lengths), 2.4 * n_states), sharex=True, squeeze=False)
    for i in range(n_states):
        for j, length in enumerate(lengths):
            ax = axes[i, j]
            ax.plot(x, true[length, i], color="k", lw=1.4, label="true")
            ax.plot(x, pred[length, i], color="tab:red", lw=1.2, ls="--", label="model")
            err = float(np.mean((true[length, i] - pred[length, i]) ** 2))
            ax.set_title(f"state {i + 1}, l_M = {length}: MSE {err:.1e}", fontsize=9)
            if i == n_states - 1:
                ax.set_xlabel("x")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"model rollouts vs the true environment ({trainer.cfg.method.name}, step {trainer.t:,d})")
    fig.tight_layout()
    return save_figure(fig, out)
