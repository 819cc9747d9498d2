"""The training loop of every method, in one function: :func:`train` (the paper's Algorithm 1).

A :class:`Run` holds the components of one training run, each owning its state:

* ``collector`` - the real environment, the current observation, episode counters (:mod:`.collector`);
* ``real`` - the real replay buffer D^r;
* ``model`` - for mbrl and pimbrl the :class:`~pimbrl.training.dyna.DynaModel` (model, model trainer,
  imagination and the imagined buffer D^f); ``None`` for mfrl, which is the same loop with the model off;
* ``agent`` - TD3, DDPG or SAC;
* ``evaluator`` - the deterministic policy on the held-out test states;
* ``logger`` - CSV logs, metrics, phase timings, TensorBoard, progress (:mod:`.logger`);
* ``streams`` - one random stream per purpose (:mod:`.streams`);
* ``schedule`` - the agent-update credit (a fractional update-to-data ratio carries over).

A checkpoint is the dict of their state dicts, written at an episode end; :func:`open_run` rebuilds the
components from ``config.json`` (validated like a new configuration) and loads it (its counters checked),
so a resumed run continues exactly where the checkpoint was taken. :func:`create_run` and :func:`open_run`
(unless ``inspect_only``) take the run directory's lock, which :func:`train` releases when it ends.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from ..agents import Agent, make_agent
from ..buffers import ReplayBuffer
from ..config import ConfigError
from ..envs import VALIDATION_SEED, Task
from ..models import TransitionModel
from ..physics import Physics
from ..spaces import ActionAdapter
from ..systems import system_origin
from .collector import Collector
from .config import TrainConfig, config_from_dict, config_to_dict
from .control_run import ControlRun
from .dyna import PHASES, DynaModel, agent_batch
from .evaluation import Evaluator, check_pool_sizes
from .holdout import holdout_summary, read_holdout, write_holdout
from .logger import RunLogger
from .rundir import CheckpointError, RunDirectory, package_versions, provenance, steps_to_threshold
from .selection import PolicySelector
from .stopping import RunStopped, StopRequest
from .streams import RandomStreams
from .summary import RunSummary
from .threads import pin_threads

__all__ = [
    "STATE_KEYS",
    "Run",
    "RunSummary",
    "UpdateSchedule",
    "build_run",
    "check_checkpoint",
    "create_run",
    "open_run",
    "read_run_config",
    "train",
]

#: ``on_event(name, run)`` is called after each part of the loop (for tests and instrumentation).
EventHook = Callable[[str, "Run"], None]


class UpdateSchedule:
    """``update_every * utd`` agent updates per update phase; a fractional remainder carries over."""

    def __init__(self, update_every: int, utd: float) -> None:
        self.per_phase = update_every * utd
        self.credit = 0.0

    def take(self) -> int:
        """The number of updates of this phase."""
        self.credit += self.per_phase
        n = math.floor(self.credit + 1e-9)
        self.credit -= n
        return n

    def state_dict(self) -> dict[str, Any]:
        """The carried-over credit."""
        return {"credit": self.credit}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.credit = float(state["credit"])


def lr_scale(t: int, start: int, end: int, final: float) -> float:
    """The learning rates' fraction at real step ``t``: 1 until ``start``, then linear to ``final`` at ``end``."""
    if t <= start:
        return 1.0
    return 1.0 - (1.0 - final) * min(1.0, (t - start) / (end - start))


@dataclass
class Run:
    """The components of one training run (see the module docstring)."""

    cfg: TrainConfig
    run_dir: RunDirectory
    streams: RandomStreams
    collector: Collector
    real: ReplayBuffer
    agent: Agent
    model: DynaModel | None
    evaluator: Evaluator
    logger: RunLogger
    schedule: UpdateSchedule
    t: int = 0
    last_checkpoint_t: int = 0
    #: ``time.monotonic()`` at the last checkpoint or at this process's start (not in checkpoints)
    last_checkpoint_clock: float = dataclasses.field(default_factory=time.monotonic)
    #: the policy's wall seconds per control step at the last test evaluation (not in checkpoints: the final
    #: evaluation of every run measures it again)
    inference_s_per_step: float | None = None

    @property
    def finished(self) -> bool:
        """Whether all ``total_steps`` real steps are done."""
        return self.t >= self.cfg.total_steps

    @property
    def adapter(self) -> ActionAdapter:
        """Maps the agent's normalised actions to environment actions."""
        return self.collector.adapter

    @property
    def task(self) -> Task:
        """The task of a pimbrl environment (raises for other environments)."""
        task = self.collector.task
        if task is None:
            raise ValueError(f"{self.cfg.env} is not a pimbrl environment (it has no Task)")
        return task

    @property
    def physics(self) -> Physics:
        """The physics of a pimbrl environment."""
        return self.task.physics

    @property
    def selector(self) -> PolicySelector | None:
        """Model-based policy selection of a run with ``dyna.select_episodes`` (else ``None``)."""
        return None if self.model is None else self.model.selector

    @property
    def transition_model(self) -> TransitionModel | None:
        """The learned model of an mbrl/pimbrl run (``None`` for mfrl)."""
        return None if self.model is None else self.model.model

    def evaluator_for(self, protocol: str = "test", episodes: int | None = None) -> Evaluator:
        """An evaluator of this run's policy: its own for its test states, else one for ``protocol``/``episodes``."""
        cfg = self.cfg
        if protocol == cfg.eval_protocol and episodes in (None, cfg.eval_episodes):
            return self.evaluator
        if episodes is None and protocol in ("test", "validation"):  # as many as the run's evaluations play
            episodes = cfg.eval_episodes
        return Evaluator(cfg.env, cfg.env_kwargs, episodes, cfg.eval_seed, protocol=protocol)

    def use_selected_policy(self) -> int:
        """Load the policy that model-based policy selection kept into the agent; returns its step.

        Raises ``ValueError`` if the run was trained without selection (``dyna.select_episodes`` 0) or has
        not selected a policy yet.
        """
        selector = self.selector
        if selector is None:
            raise ValueError(
                f"{self.run_dir.path} has no selected policy: it was trained without model-based policy selection "
                "(train with --dyna.select-episodes N, or evaluate its latest policy)"
            )
        if selector.best_policy is None or selector.best_step is None:
            raise ValueError(
                f"{self.run_dir.path} has not selected a policy yet: its checkpoint precedes its first evaluation "
                "(resume it past an evaluation, or evaluate its latest policy)"
            )
        self.agent.load_policy_state(selector.best_policy)
        return selector.best_step

    # ------------------------------------------------------------------ checkpoint = the components' states
    def state_dict(self) -> dict[str, Any]:
        """The full training state: a dict of the components' state dicts."""
        return {
            "t": self.t,
            "streams": self.streams.state_dict(),
            "collector": self.collector.state_dict(),
            "real": self.real.state_dict(),
            "agent": self.agent.state_dict(),
            "model": None if self.model is None else self.model.state_dict(),
            "logger": self.logger.state_dict(),
            "schedule": self.schedule.state_dict(),
            "torch_rng": torch.get_rng_state(),
            "inference_s_per_step": self.inference_s_per_step,  # of the last evaluation: a resume after it reports it
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.t = self.last_checkpoint_t = int(state["t"])
        self.streams.load_state_dict(state["streams"])
        self.collector.load_state_dict(state["collector"])
        self.real.load_state_dict(state["real"])
        self.agent.load_state_dict(state["agent"])
        if self.model is not None:
            self.model.load_state_dict(state["model"])
        self.logger.load_state_dict(state["logger"])
        self.schedule.load_state_dict(state["schedule"])
        torch.set_rng_state(state["torch_rng"])
        cost = state.get("inference_s_per_step")  # absent from checkpoints written before it was kept
        self.inference_s_per_step = float(cost) if isinstance(cost, (int, float)) else None

    def checkpoint_due(self) -> bool:
        """Whether ``checkpoint_every`` real steps or ``checkpoint_minutes`` of wall time passed since the last one."""
        cfg = self.cfg
        if self.t - self.last_checkpoint_t >= cfg.checkpoint_every:
            return True
        minutes = cfg.checkpoint_minutes
        return minutes > 0 and time.monotonic() - self.last_checkpoint_clock >= 60.0 * minutes

    def save_checkpoint(self) -> None:
        """Write the full state atomically (at an episode end, before the next reset)."""
        self.last_checkpoint_t = self.t
        self.last_checkpoint_clock = time.monotonic()
        self.run_dir.save_checkpoint(self.state_dict())

    def summary(self) -> RunSummary:
        """What the run has reached, from its evaluations."""
        rows = self.run_dir.evaluations.read()
        returns = [float(r["return_mean"]) for r in rows]
        selector = self.selector
        return RunSummary(
            steps=self.t,
            updates=self.agent.n_updates,
            final_return_mean=returns[-1] if returns else None,
            best_return_mean=max(returns) if returns else None,
            steps_to_threshold=steps_to_threshold(rows, self.cfg.threshold),
            wall_s=self.logger.wall_s,
            selected_step=None if selector is None else selector.best_step,
            selected_return_mean=None if selector is None else selector.best_test_return,
            real_transitions=self.t,
            imagined_transitions=0 if self.model is None else self.model.imagined_total,
            scheme_transitions=0 if self.model is None else self.model.scheme_transitions,
            validation_transitions=0 if self.model is None else self.model.validation_transitions,
            inference_s_per_step=self.inference_s_per_step,
            **holdout_summary(self.run_dir, self.t, self.cfg.holdout_episodes),
        )

    def lr_scale(self) -> float | None:
        """The learning rates' fraction of their configured values at this step (``None``: no decay configured)."""
        cfg = self.cfg
        x = cfg.experimental
        return None if x.lr_decay_after is None else lr_scale(self.t, x.lr_decay_after, cfg.total_steps, x.lr_decay_to)

    def counters(self) -> dict[str, Any]:
        """The counters of a ``metrics.csv`` row."""
        row: dict[str, Any] = {
            "episodes": self.collector.episode,
            "agent_updates": self.agent.n_updates,
            "update_to_data": self.agent.n_updates / max(self.t, 1),
            "real_buffer": len(self.real),
        }
        scale = self.lr_scale()
        if scale is not None:
            row["lr_scale"] = scale
        if self.model is not None:
            row.update(self.model.metric_row())
        return row


def _log_metrics(run: Run) -> None:
    """A row of ``metrics.csv``; with learned coefficients, ``coefficients.json`` brought up to date too."""
    run.logger.metrics(run.t, run.counters())
    if run.model is not None and run.model.trainer.coefficients is not None:
        run.run_dir.write_json("coefficients.json", run.model.coefficients_report())


def train(run: Run | ControlRun, on_event: EventHook | None = None, stop_on_signal: bool = False) -> RunSummary:
    """Train ``run`` to ``total_steps`` real steps (the paper's Algorithm 1; MFRL when ``run.model`` is None).

    Every real step: act and store the transition. Every ``update_every`` steps after ``update_after``:
    the model phase (fit, check, imagine; model-based only), then ``update_every * utd`` agent updates on
    batches mixing real and imagined transitions. Every ``eval_every`` steps: evaluate the deterministic
    policy on the held-out test states. At an episode end: log it and, when due, checkpoint. At the end:
    a last evaluation, the final checkpoint and the summary in ``config.json``. With ``stop_on_signal`` (the
    command line's), a SIGTERM or SIGINT while it trains stops it at the next episode end, after a checkpoint
    (:class:`~.stopping.RunStopped`).
    """
    if isinstance(run, ControlRun):  # feedback, mpc, dpc: no agent, no replay (pimbrl.control)
        return run.train()
    cfg, log = run.cfg, run.logger
    event = on_event or (lambda name, r: None)
    if run.finished:  # e.g. killed between the final checkpoint and the status update
        try:
            return _finish(run)
        finally:
            run.run_dir.close()  # releases the run's lock
    log.open(run.t, cfg.total_steps, f"{cfg.method.name}/{cfg.agent.name} {cfg.env} seed {cfg.seed}")
    # the log is closed however the run ends; with stop_on_signal a SIGTERM or SIGINT stops it at its next episode end
    with contextlib.closing(log), StopRequest(active=stop_on_signal) as stop:
        run.collector.reset(first=run.t == 0)
        while run.t < cfg.total_steps:
            # 1. act in the real environment (uniformly random during warm-up) and store the transition
            with log.timed("env_step"):
                step = run.collector.step(run.agent, random_action=run.t < cfg.warmup_steps)
                flags: dict[str, np.ndarray] = {}
                if run.model is not None:  # hold-out flag from its own stream; blown-up steps are invalid
                    flags = {"holdout": np.array([[run.model.holdout_flag()]]), "valid": np.array([[float(step.valid)]])}
                run.real.add_transitions(step.transition, **flags)
            run.t += 1
            event("act", run)
            # 2. update phase: model phase (model-based methods), then the agent's updates
            if run.t >= cfg.update_after and run.t % cfg.update_every == 0:
                if run.model is not None:
                    run.model.phase(run.real, run.agent, run.t, log.timed, log.message)
                    event("model_phase", run)
                with log.timed("agent_update"):
                    scale = run.lr_scale()
                    if scale is not None:
                        run.agent.set_lr_scale(scale)
                    for _ in range(run.schedule.take()):
                        size = cfg.agent.batch_size
                        if run.model is not None:
                            batch = run.model.agent_batch(run.real, size, run.streams.replay)
                        else:
                            batch = agent_batch(run.real, None, 1.0, size, run.streams.replay)
                        log.accumulate(run.agent.update(batch))
                event("agent_updates", run)
            # 3. evaluate the deterministic policy on the held-out initial states
            if run.t % cfg.eval_every == 0:
                _evaluate(run)
                event("evaluate", run)
            if run.t % cfg.log_every == 0 or run.t % cfg.eval_every == 0:  # a row at each evaluation too
                _log_metrics(run)
            # 4. episode end: log it, checkpoint when due, reset
            if step.done:
                end = run.collector.end_episode()
                log.episode(run.t, end.episode, end.return_, end.length)
                if (run.checkpoint_due() or stop.requested) and run.t < cfg.total_steps:
                    with log.timed("checkpoint"):
                        run.save_checkpoint()
                    event("checkpoint", run)
                    if stop.signum is not None:  # asked to stop: the checkpoint is written, resume continues it
                        raise RunStopped(stop.signum, run.t)
                if run.t < cfg.total_steps:  # at the end the reset is left to a continuation (resume --total-steps)
                    run.collector.reset(first=False)
        if run.t % cfg.eval_every != 0 or log.last_eval is None:
            _evaluate(run)
        if run.t % cfg.log_every != 0 and run.t % cfg.eval_every != 0:  # not logged in the loop's last step
            _log_metrics(run)
        run.save_checkpoint()
        return _finish(run)


def _evaluate(run: Run) -> None:
    """The deterministic policy on the test states; with policy selection on, also whole episodes in the model.

    A model-based run whose fine-tuning switch waits also evaluates the policy on the validation draws
    (:meth:`~pimbrl.training.dyna.DynaModel.validate`): the switch reads those, never the test return.
    """
    with run.logger.timed("evaluate"):
        result = run.evaluator.run(lambda o: run.agent.act(o, deterministic=True))
    run.inference_s_per_step = result.inference_s_per_step
    run.logger.evaluation(run.t, result, run.agent.n_updates)
    if run.model is not None:  # what the fine-tuning switch reads: the validation draws, never these test states
        with run.logger.timed("evaluate"):
            run.model.validate(run.agent)
    selector = run.selector
    if selector is not None:
        with run.logger.timed("select"):
            run.run_dir.selection.append(selector.observe(run.t, run.agent, result.mean))


def _evaluate_holdout(run: Run) -> bool:
    """The final policy, once, on the holdout pool (``holdout_episodes``), into ``holdout.json``; whether it played.

    Played again only where the file belongs to an earlier final policy (the run was extended since) or is
    missing.
    """
    episodes = run.cfg.holdout_episodes
    if not episodes or read_holdout(run.run_dir, run.t) is not None:
        return False
    with run.logger.timed("evaluate"):
        result = run.evaluator_for("holdout", episodes).run(lambda o: run.agent.act(o, deterministic=True))
    write_holdout(run.run_dir, run.t, result.returns, result.lengths)
    return True


def _finish(run: Run) -> RunSummary:
    """The holdout evaluation where due, then the run marked finished with its summary in ``config.json``.

    Once; it also repairs a missing mark (a run killed between its final checkpoint and the mark).
    """
    played = _evaluate_holdout(run)
    summary = run.summary()
    if played or run.run_dir.status != "finished":
        run.run_dir.update_status(status="finished", summary=dataclasses.asdict(summary))
    return summary


# ---------------------------------------------------------------------- building and reopening runs
def resolve_device(device: str) -> str:
    """``cpu`` or ``cuda``: ``auto`` is CUDA where torch sees a GPU, else the CPU."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def build_run(cfg: TrainConfig, run_dir: RunDirectory, progress: bool = True) -> Run:
    """The components of a fresh run of ``cfg`` (nothing is written to ``run_dir``)."""
    streams = RandomStreams(cfg.seed)
    model_based = cfg.model_based
    try:
        collector = Collector(cfg.env, cfg.env_kwargs, streams, record_physics=model_based)
    except (ImportError, gym.error.Error) as exc:  # a registered id whose package or dependency is missing here
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise ConfigError(
            f"environment {cfg.env} cannot be made here ({type(exc).__name__}: {first}); install what it needs"
        ) from None
    check_pool_sizes(collector.task, cfg.eval_protocol, cfg.eval_episodes, cfg.holdout_episodes)
    pin_threads(cfg.threads)  # once the environment has loaded what it needs (scipy's OpenBLAS, say)
    agent = make_agent(
        cfg.agent,
        collector.obs_dim,
        collector.adapter.dim,
        cfg.seed,
        critic_layer_norm=cfg.experimental.critic_layer_norm,
        device=resolve_device(cfg.device),
    )
    model = None
    extras = None
    if model_based:
        finetune = cfg.dyna.finetune
        validator = (
            Evaluator(cfg.env, cfg.env_kwargs, finetune.episodes, VALIDATION_SEED, protocol="validation")
            if finetune.at_return is not None
            else None
        )
        model = DynaModel(
            cfg.dyna,
            collector.task,
            collector.adapter,
            collector.obs_dim,
            streams,
            validator=validator,
            reset_start_symmetry=cfg.experimental.reset_start_symmetry,
        )
        extras = model.extras
    real = ReplayBuffer(min(cfg.buffer_size, cfg.total_steps), collector.obs_dim, collector.adapter.dim, extras=extras)
    columns = ["agent/critic_loss", "agent/q_mean", "agent/actor_loss"]
    if cfg.agent.sac_family:  # sac, crossq, redq: a learned entropy temperature
        columns += ["agent/entropy", "agent/alpha"]
    if cfg.experimental.lr_decay_after is not None:
        columns.append("lr_scale")
    if model is not None:
        columns += model.metric_names()
    logger = RunLogger(run_dir, columns, PHASES, cfg.threshold, tensorboard=cfg.tensorboard, progress=progress)
    evaluator = Evaluator(cfg.env, cfg.env_kwargs, cfg.eval_episodes, cfg.eval_seed, protocol=cfg.eval_protocol)
    return Run(cfg, run_dir, streams, collector, real, agent, model, evaluator, logger, UpdateSchedule(cfg.update_every, cfg.utd))


def create_run(cfg: TrainConfig, path: str | Path, progress: bool = True, command: str = "") -> Run | ControlRun:
    """A new run of ``cfg`` in ``path`` (which must not hold another run); its ``config.json`` is written.

    The directory is created and locked before it is checked for a run, so of two processes starting a
    run in one directory exactly one succeeds; the other gets :class:`~pimbrl.training.rundir.RunLockedError`
    or ``FileExistsError``. The lock is held until :func:`train` ends (or the process does).
    """
    run_dir = RunDirectory(path)
    if run_dir.config_path.exists():
        raise FileExistsError(_exists_message(path))
    # first: a configuration that cannot run leaves no directory behind
    run: Run | ControlRun = ControlRun.build(cfg, run_dir, progress) if cfg.control else build_run(cfg, run_dir, progress)
    run_dir.path.mkdir(parents=True, exist_ok=True)
    run_dir.lock(command or None)
    try:
        if run_dir.config_path.exists():  # another process created the run meanwhile
            raise FileExistsError(_exists_message(path))
        run_dir.check_entries(writing=True)  # a folder holding planted links or FIFOs is refused
        run_dir.remove_stale_temporaries()
        payload = {
            "status": "running",
            "config": config_to_dict(cfg),
            "versions": package_versions(),
            "provenance": provenance(),
            "command": command,
        }
        run_dir.write_config({**payload, "system": {"id": cfg.env, "origin": system_origin(cfg.env)}})
    except BaseException:
        run_dir.close()
        raise
    return run


def _exists_message(path: str | Path) -> str:
    return f"{path} already holds a run; use `pimbrl resume {path}` or choose another --run-dir"


def read_run_config(run_dir: RunDirectory) -> TrainConfig:
    """The configuration in a run's ``config.json``, type-checked and validated like a new one.

    Errors are :class:`~pimbrl.config.ConfigError` naming the file, e.g.
    ``DIR/config.json: agent.gamma must be in (0.0, 1.0], got 7.5``.
    """
    payload = run_dir.read_config()
    run_dir.require_system(payload)
    config = payload.get("config")
    if config is None:
        raise ConfigError(f"{run_dir.config_path}: has no 'config' object; this is not a run written by pimbrl")
    try:
        return config_from_dict(config)
    except ConfigError as exc:
        raise ConfigError(f"{run_dir.config_path}: {exc}") from None


#: The parts of a checkpoint (:meth:`Run.state_dict`).
STATE_KEYS = ("t", "streams", "collector", "real", "agent", "model", "logger", "schedule", "torch_rng")


def check_checkpoint(state: dict[str, Any], cfg: TrainConfig, path: str | Path) -> None:
    """Check a checkpoint's parts and counters against the run's configuration (:class:`CheckpointError`).

    The step ``t`` must lie in ``[0, total_steps]``, the episode count in ``[0, t]``, the agent's
    update count be ``>= 0`` and the real buffer's counters fit ``t`` and its capacity.
    """
    fix = "the checkpoint was edited or damaged; delete it to restart the run from its beginning"
    missing = [repr(k) for k in STATE_KEYS if k not in state]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks {', '.join(missing)}: {fix}")

    def counter(name: str, value: Any, low: int, high: int | None = None, what: str = "") -> int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise CheckpointError(f"checkpoint {path}: {name} must be an integer, got {value!r}: {fix}")
        if value < low or (high is not None and value > high):
            bound = f"in [{low}, {high}]" if high is not None else f">= {low}"
            raise CheckpointError(f"checkpoint {path}: {name} must be {bound}{what}, got {value}: {fix}")
        return value

    t = state["t"]
    if not isinstance(t, int) or isinstance(t, bool) or t < 0:
        raise CheckpointError(f"checkpoint {path} is at step {t!r}; a step count is an integer >= 0: {fix}")
    if t > cfg.total_steps:
        raise CheckpointError(
            f"checkpoint {path} is at step {t:,d}, beyond the run's total_steps {cfg.total_steps:,d} (config.json): "
            "restore total_steps to at least that, or start a new run"
        )
    try:
        counter("collector.episode", state["collector"]["episode"], 0, t, " (the step)")
        counter("agent.n_updates", state["agent"]["n_updates"], 0)
        real = state["real"]
        capacity = counter("real.capacity", real["capacity"], 1)
        size = counter("real.size", real["size"], 0, min(t, capacity), " (the step and the capacity)")
        counter("real.pos", real["pos"], 0, capacity - 1, " (the capacity)")
        counter("real.total_added", real["total_added"], size, t, " (size to step)")
    except (KeyError, TypeError) as exc:
        raise CheckpointError(f"checkpoint {path} lacks a part or counter ({_describe(exc)}): {fix}") from None
    credit = state["schedule"].get("credit") if isinstance(state["schedule"], dict) else None
    if not isinstance(credit, float) or not math.isfinite(credit):
        raise CheckpointError(f"checkpoint {path}: schedule.credit must be a finite number, got {credit!r}: {fix}")


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}"


def open_run(path: str | Path, progress: bool = True, inspect_only: bool = False) -> Run | ControlRun:
    """The run in ``path`` at its last checkpoint (from the start if it has none).

    To continue training, the run directory is locked (held until :func:`train` ends), stale temporary
    files are removed, the CPU model and commit it goes on with are added to ``resumed_on`` in ``config.json``
    where they differ from those it last ran with, the logs are cut back to the checkpoint, and a run whose final checkpoint is
    there but whose ``config.json`` still says "running" (killed between the two) is marked finished.
    ``inspect_only`` loads the state without taking the lock or touching any file (for evaluation and
    figures, also of a run still in progress). Either way a run directory holding anything pimbrl does not
    make there (a symbolic link, a FIFO, a log with other hard links) is refused first
    (:meth:`~pimbrl.training.rundir.RunDirectory.check_entries`). In both cases ``config.json`` is validated like a new
    configuration and the checkpoint's counters are checked (:func:`check_checkpoint`).
    """
    run_dir = RunDirectory(path)
    if inspect_only:
        run_dir.check_entries()  # links, FIFOs: refused before anything is read
    run_dir.read_config()  # not a run directory: FileNotFoundError, before any lock file is made
    if not inspect_only:
        run_dir.lock()
    try:
        if not inspect_only:
            run_dir.check_entries(writing=True)  # under the lock, before anything is changed
            run_dir.remove_stale_temporaries()
        cfg = read_run_config(run_dir)
        if not inspect_only and run_dir.status != "finished":  # resumed elsewhere: the record says where
            run_dir.note_resume()
        if cfg.control:  # its stages are in control.json (a DPC policy's checkpoint is read by the run itself)
            control = ControlRun.build(cfg, run_dir, progress)
            control.load()
            return control
        run = build_run(cfg, run_dir, progress)
        if run_dir.checkpoint_path.exists():
            state = run_dir.load_checkpoint()
            check_checkpoint(state, cfg, run_dir.checkpoint_path)
            try:
                run.load_state_dict(state)
            except (KeyError, TypeError, ValueError, RuntimeError, IndexError, AttributeError, OverflowError) as exc:
                raise CheckpointError(
                    f"checkpoint {run_dir.checkpoint_path} does not fit the run's configuration ({_describe(exc)}); "
                    "was config.json edited? Restore it, or delete the checkpoint to restart the run"
                ) from None
        if not inspect_only:
            run_dir.truncate_logs(run.t)
            if run.finished:
                _finish(run)  # repairs the mark of a run killed between its final checkpoint and the mark
    except BaseException:
        run_dir.close()
        raise
    return run
