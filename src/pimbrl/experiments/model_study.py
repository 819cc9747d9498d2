"""Model-error study: data-only against physics-informed models, by number of labelled transitions.

For each seed and each number of labels ``L`` (e.g. 0, 100, 300, 1000): collect random-policy transitions
from the task's initial states; the first ``L`` carry labels, the first ``max(L, seed_states)`` states
are *observed* (the physics loss may start from them without labels). Train from the same
initialisation, for the same number of gradient steps:

* ``data``: ``L_D`` on the ``L`` labelled transitions (none for ``L = 0``: the no-change prediction);
* ``physics``: ``L_D`` on the same labels plus ``w_E L_E`` on unlabelled state-action pairs, drawn as a
  PiMBRL run draws them (:func:`pimbrl.experiments.model_eval.study_pairs`; the physics loss's settings and
  defaults are the training's, ``--physics.*``): ``policy`` = the observed states with the random policy's
  actions, ``imagined`` = the pairs of short model rollouts from them, and the broad sources of
  :mod:`pimbrl.models.state_sources`. With ``L = 0`` its normalisation comes from the equation (the coarse
  scheme's increments), not from labels.

With a physics prior that differs from the environment (``env_coefficients``, ``physics_prior``) the
``physics`` model is held to the wrong prior; ``physics-true`` is trained with the environment's own
coefficients (the upper reference) and, with ``learn_coefficients``, ``physics-learned`` with the prior's
coefficients fitted to the labels (:mod:`pimbrl.models.coefficients`; the identified values are recorded).

``physics-only`` is the prior's coarse scheme itself as the model (:class:`pimbrl.models.PhysicsModel`,
trained on nothing, so the same at every label count); with ``learn_coefficients``, ``physics-only-learned``
is that scheme with the coefficients fitted to the labels (no network). ``models`` restricts the study to some of these (the
test transitions depend only on the seed, so rows of separate studies with the same seeds compare).

All are tested on the same held-out in-sample transitions and on the out-of-sample transitions of
the system's out-of-sample set (:attr:`pimbrl.systems.System.out_of_sample`), one step ahead and ``rollout_lengths`` chained
steps ahead (open loop, the same random actions as the truth). Outputs: ``study.csv`` (one row per seed,
labels, model, split, horizon: mean, median and 90th percentile of the per-transition MSE),
``study.json`` and ``study.png`` (error against labels, mean over seeds with the min-max band).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..envs import PhysicsEnv, Task
from ..fileio import atomic_write_bytes
from ..models import ModelTrainer, PhysicsResidual, TransitionData, TransitionModel, make_model
from ..models.coefficients import LearnedCoefficients
from ..models.residual import as_scheme
from ..models.state_sources import broad_actions, choose_sources
from ..physics import Physics
from ..training.threads import pin_threads
from .model_eval import (
    ModelEvalConfig,
    _random_env_actions,
    check_physics_settings,
    collect_transitions,
    network_of,
    out_of_sample,
    study_pairs,
)

__all__ = ["run_model_study"]


def _rollout_mse(model: TransitionModel | None, data: list[TransitionData], horizon: int, task: Task) -> np.ndarray:
    """Per-trajectory MSE after ``horizon`` chained steps (``data[i]`` is step ``i`` of every trajectory).

    Measured in the state's own geometry: the pendulum's angle difference is wrapped, as in the data loss.
    """
    u = data[0].state
    with torch.no_grad():
        for i in range(horizon):
            u = u if model is None else model.predict_next(u, data[i].action)
    truth = data[horizon - 1].next_state
    assert truth is not None
    return task.physics.state_difference(u.double(), truth.double()).pow(2).mean(dim=-1).numpy()


def _trajectories(
    task: Task, rng: np.random.Generator, n: int, horizon: int, initial: Callable[..., np.ndarray]
) -> list[TransitionData]:
    """``n`` open-loop random-action trajectories of ``horizon`` steps, step by step (no resets)."""
    u = initial(rng, n)
    k = np.zeros(n, dtype=np.int64)
    steps = []
    for _ in range(horizon):
        a = task.physical_action(_random_env_actions(task, rng, n), n)
        out = task.advance(u, a, k)
        canonical = task.physics.canonical
        steps.append(
            TransitionData(
                torch.as_tensor(canonical(u), dtype=torch.float32),
                torch.as_tensor(a, dtype=torch.float32),
                torch.as_tensor(canonical(out.state), dtype=torch.float32),
            )
        )
        u, k = out.state, k + 1
    return steps


def run_model_study(env_id: str, run_dir: str | Path, cfg: ModelEvalConfig, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run the study for ``env_id`` (see the module docstring) and write its outputs into ``run_dir``."""
    import gymnasium as gym

    from ..config import validate

    validate(cfg)
    check_physics_settings(cfg)
    pin_threads(cfg.threads)
    oos = out_of_sample(env_id)
    env_kwargs: dict[str, Any] = dict(cfg.env_coefficients)
    env = gym.make(env_id, **env_kwargs)
    if not isinstance(env.unwrapped, PhysicsEnv):
        raise ValueError(f"model-eval needs a pimbrl environment (a PhysicsEnv, whose task and physics it reads), not {env_id!r}")
    task = env.unwrapped.task
    prior = task.physics.with_coefficients(**cfg.physics_prior)
    learned = {name: None if r is None else (float(r[0]), float(r[1])) for name, r in cfg.learn_coefficients.items()}
    if learned:  # every problem now, before any model is trained
        leaked = [n for n in learned if n in env_kwargs and n not in cfg.physics_prior]
        if leaked:
            raise ValueError(
                f"learn_coefficients: {leaked[0]} would start from the environment's true value; "
                f"give the believed one with --physics-prior {leaked[0]}=..."
            )
        if cfg.scheme != "etd":
            raise ValueError("learn_coefficients needs the etd residual (--scheme etd)")
        LearnedCoefficients(prior, learned)
    variants: dict[str, tuple[Physics, dict]] = {"physics": (prior, {})}
    if cfg.physics_prior:
        variants["physics-true"] = (task.physics, {})
    if learned:
        variants["physics-learned"] = (prior, learned)
    # physics-only: the prior's coarse scheme, trained on nothing; physics-only-learned: that scheme with the
    # learned coefficients fitted to the labels (the network-free model of the same inverse problem)
    names = ["data", *variants, "physics-only", *(["physics-only-learned"] if learned else [])]
    if cfg.models:
        chosen = [m.strip() for m in cfg.models.split(",") if m.strip()]
        unknown = [m for m in chosen if m not in names]
        if not chosen:
            raise ValueError(f"models: name at least one of {', '.join(names)}")
        if unknown:
            raise ValueError(f"models: {', '.join(unknown)} not in this study; choose from {', '.join(names)}")
        names = [m for m in names if m in chosen]
    identified: list[dict[str, Any]] = []
    sources = choose_sources(cfg.physics.sources, prior)
    labels = sorted(set(cfg.labels))
    horizons = sorted(set((1, *cfg.rollout_lengths)))
    out_dir = Path(run_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for seed in range(cfg.seed, cfg.seed + cfg.seeds):
        rng = np.random.default_rng(seed)
        n_obs = max(max(labels), cfg.seed_states)
        pool = collect_transitions(task, rng, n_obs, task.sample_initial_states)
        tests = {
            "in": _trajectories(task, rng, cfg.test_transitions, max(horizons), task.sample_initial_states),
            "out": _trajectories(task, rng, cfg.test_transitions, max(horizons), lambda g, n: oos(task, g, n)),
        }
        observed = pool.state[: max(cfg.seed_states, 1)]
        for n_labels in labels:
            labelled = pool.take(torch.arange(n_labels)) if n_labels else None
            for name in names:
                physics, learn = variants.get(name, (prior, {}))
                if name == "data" and labelled is None:
                    model = None  # no labels, no physics: predict no change
                elif name == "physics-only" or (name == "physics-only-learned" and labelled is None):
                    model, _ = _scheme_model(cfg, prior)  # learns nothing
                elif name == "physics-only-learned":
                    assert labelled is not None
                    model, found = _fit_scheme(cfg, prior, learned, labelled, seed)
                    identified.append({"seed": seed, "labels": n_labels, "model": name, **found})
                else:
                    model, found = _train(task, cfg, name, labelled, observed, sources, seed, physics, learn)
                    if found:
                        identified.append({"seed": seed, "labels": n_labels, "model": name, **found})
                for split, traj in tests.items():
                    for h in horizons:
                        mse = _rollout_mse(model, traj, h, task)
                        rows.append(
                            {
                                "seed": seed,
                                "labels": n_labels,
                                "model": name if model is not None else "no-change",
                                "split": split,
                                "horizon": h,
                                "mean": float(mse.mean()),
                                "median": float(np.median(mse)),
                                "p90": float(np.percentile(mse, 90)),
                            }
                        )
                one = [
                    r for r in rows if r["seed"] == seed and r["labels"] == n_labels and r["horizon"] == 1 and r["split"] == "out"
                ]
                log(f"{env_id} seed {seed} labels {n_labels:5d} {name:15s}: out-of-sample 1-step MSE {one[-1]['mean']:.3e}")
    cols = ["seed", "labels", "model", "split", "horizon", "mean", "median", "p90"]
    text = (
        ",".join(cols)
        + "\n"
        + "".join(",".join(repr(r[c]) if isinstance(r[c], float) else str(r[c]) for c in cols) + "\n" for r in rows)
    )
    atomic_write_bytes(out_dir / "study.csv", text.encode())
    summary = _summarise(rows)
    payload = {
        "env": env_id,
        "sources": sources,
        "units": cfg.physics.units,
        "model_kind": network_of(cfg, prior),
        "env_coefficients": task.physics.coefficient_values(),
        "physics_prior": prior.coefficient_values(),
        "learned": list(learned),
        "identified": identified,
        "wall_s": time.perf_counter() - t0,
        "summary": summary,
    }
    atomic_write_bytes(out_dir / "study.json", (json.dumps(payload, indent=2) + "\n").encode())
    _plot(summary, out_dir / "study.png", env_id)
    return payload


def _scheme_model(cfg: ModelEvalConfig, prior: Physics, learned: dict | None = None) -> tuple[TransitionModel, PhysicsResidual]:
    """The prior's coarse scheme as the model (physics-only), with ``learned`` coefficients free to fit if given."""
    n = PhysicsResidual.states_per_step(prior, cfg.n_intermediate)
    residual = PhysicsResidual(prior, n, as_scheme(cfg.scheme), learned=learned or None)
    return make_model(prior, n_intermediate=n, kind="physics", scheme=residual), residual


def _fit_scheme(
    cfg: ModelEvalConfig, prior: Physics, learned: dict, labelled: TransitionData, seed: int
) -> tuple[TransitionModel, dict[str, float]]:
    """The prior's coarse scheme with ``learned`` coefficients fitted to the labels (``cfg.steps`` Adam steps)."""
    model, residual = _scheme_model(cfg, prior, learned)
    trainer = ModelTrainer(model, residual, coefficient_lr=cfg.coefficient_lr)
    trainer.fit(cfg.steps, cfg.batch_size, np.random.default_rng(seed + 1), labelled=labelled)
    assert residual.coefficients is not None
    return model, residual.coefficients.current()


def _train(
    task: Task,
    cfg: ModelEvalConfig,
    name: str,
    labelled: TransitionData | None,
    observed: torch.Tensor,
    sources: tuple[str, ...],
    seed: int,
    physics: Physics,
    learned: dict,
) -> tuple[TransitionModel, dict[str, float]]:
    """A model trained with the data loss (``data``) or with the physics loss of ``physics`` too.

    Returns the model and the learned coefficients' identified values (empty where none is learned).
    """
    torch.manual_seed(seed)
    model = make_model(physics, n_intermediate=cfg.n_intermediate, kind=network_of(cfg, physics))
    scheme = as_scheme(cfg.scheme)
    residual = PhysicsResidual(
        physics, model.n_intermediate, scheme, cfg.physics.units, learned=learned if labelled is not None else None
    )
    trainer = ModelTrainer(
        model,
        residual if name != "data" else None,
        lr=cfg.lr,
        weight_physics=cfg.physics.weight,
        coefficient_lr=cfg.coefficient_lr,
    )
    rng = np.random.default_rng(seed + 1)
    if labelled is not None:
        trainer.ensure_normalization(labelled)
    else:  # zero labels: state statistics from the observed states, increments from the equation
        a = broad_actions(physics, len(observed), rng)
        with torch.no_grad():
            nxt = residual.rollout(observed.double(), a.double())[:, -1].float()
        model.fit_normalization(observed, nxt)
    pairs, refresh = None, None
    if name != "data":
        pairs, refresh = study_pairs(task, physics, model, sources, observed, cfg.imagined_length, rng)
    done = 0
    while done < cfg.steps:
        chunk = min(cfg.refresh_every, cfg.steps - done)
        if refresh is not None:
            refresh()
        trainer.fit(chunk, cfg.batch_size, rng, labelled=labelled, unlabelled=pairs)
        done += chunk
    return model, ({} if trainer.coefficients is None else trainer.coefficients.current())


def _summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean, min and max over seeds of the mean MSE, per labels, model, split and horizon."""
    keys = sorted({(r["labels"], r["model"], r["split"], r["horizon"]) for r in rows})
    out = []
    for labels, model, split, horizon in keys:
        vals = [r["mean"] for r in rows if (r["labels"], r["model"], r["split"], r["horizon"]) == (labels, model, split, horizon)]
        out.append({"labels": labels, "model": model, "split": split, "horizon": horizon, "mean": float(np.mean(vals)),
                    "min": float(np.min(vals)), "max": float(np.max(vals)), "seeds": len(vals)})  # fmt: skip
    return out


def _plot(summary: list[dict[str, Any]], path: Path, title: str) -> None:
    from ..plotting import plt, save_figure

    horizons = sorted({r["horizon"] for r in summary})
    fig, axes = plt.subplots(2, len(horizons), figsize=(3.6 * len(horizons), 6.4), squeeze=False)
    colors = {
        "data": "tab:orange",
        "physics": "tab:blue",
        "physics-learned": "tab:green",
        "physics-true": "tab:purple",
        "physics-only": "tab:brown",
        "physics-only-learned": "tab:olive",
        "no-change": "tab:gray",
    }
    for i, split in enumerate(("in", "out")):
        for j, h in enumerate(horizons):
            ax = axes[i, j]
            for model, color in colors.items():
                pts = sorted(
                    (r["labels"], r["mean"], r["min"], r["max"])
                    for r in summary
                    if r["model"] == model and r["split"] == split and r["horizon"] == h
                )
                if not pts:
                    continue
                x = [max(p[0], 10) for p in pts]  # zero labels drawn at 10 on the log axis
                ax.plot(x, [p[1] for p in pts], "o-", color=color, label=model)
                ax.fill_between(x, [p[2] for p in pts], [p[3] for p in pts], color=color, alpha=0.2)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_title(f"{split}-sample, {h} step{'s' if h > 1 else ''}", fontsize=9)
            if i == 1:
                ax.set_xlabel("labelled transitions (0 drawn at 10)")
            if j == 0:
                ax.set_ylabel("next-state MSE")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path)
