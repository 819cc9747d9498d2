"""A run of a control method (feedback, mpc, dpc): the same run directory as an RL run, and resumable.

What it does, in order (each stage's outcome saved in ``control.json`` before the next starts, so that a
killed run resumes at the stage it was in):

1. **identify** (mpc, dpc with ``learn.coefficients``): real transitions with random actions from the
   training resets, the coefficients fitted to them (:mod:`pimbrl.control.identify`); those are the
   method's real steps;
2. **tune** (feedback): the gain with the best mean return on the validation draws;
   **train** (dpc): the policy through the scheme, the best on the validation draws kept
   (``checkpoints/latest.pt`` at every validation);
3. **test**: the controller on the test states (``eval_protocol``: or the validation draws, in a tuning
   study), in chunks of ``batch`` episodes (mpc), each chunk's returns saved as it ends;
4. **holdout** (``holdout_episodes``): the same on the holdout pool, into ``holdout.json``
   (:mod:`.holdout`).

The outcome is one row of ``evaluations.csv`` at the real steps used, and the summary in ``config.json``:
real transitions, scheme transitions (MPC's planning, DPC's training rollouts), validation transitions
(the real simulator's validation episodes), wall time, and the inference cost per control step and state.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import ConfigError
from ..control.base import Controller, ControlResult, play, task_of
from ..control.feedback import declared_feedback, make_feedback, tune_gain
from ..envs import Task
from ..fileio import MAX_JSON_BYTES, read_below, strict_json
from .config import TrainConfig
from .evaluation import check_pool_sizes
from .holdout import holdout_summary, read_holdout, write_holdout
from .methods import DPC, MPC, Feedback
from .rundir import RunDirectory, steps_to_threshold
from .summary import RunSummary
from .threads import pin_threads

__all__ = ["CONTROL_FILE", "ControlRun", "dpc_progress", "read_stages"]

#: the stage file of a control run
CONTROL_FILE = "control.json"


def read_stages(run_dir: RunDirectory) -> dict[str, Any] | None:
    """A control run's ``control.json`` (``None`` before its first stage); a damaged one is a :class:`ValueError`."""
    path = run_dir.path / CONTROL_FILE
    if not path.exists():
        return None
    payload = strict_json(read_below(run_dir.path, CONTROL_FILE, MAX_JSON_BYTES), path)
    if not isinstance(payload, dict):
        raise ValueError(f"{path} is not a JSON object; delete it to restart the run")
    return payload


def dpc_progress(rd: RunDirectory) -> tuple[int, float | None]:
    """A DPC run's gradient steps and wall-clock from its ``control.json`` (0 and ``None`` before it exists).

    A damaged file (not JSON, or a field of the wrong type) is a :class:`ValueError` naming it.
    """
    payload = read_stages(rd)
    if payload is None:
        return 0, None
    path = rd.path / CONTROL_FILE
    dpc = payload.get("dpc", {})
    steps = dpc.get("steps", 0) if isinstance(dpc, dict) else None
    wall = payload.get("wall_s")
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
        raise ValueError(f"{path}: no count of DPC steps (dpc.steps) in it; delete the run's directory to restart it")
    if wall is not None and (not isinstance(wall, (int, float)) or isinstance(wall, bool)):
        raise ValueError(f"{path}: wall_s is not a number; delete the run's directory to restart it")
    return steps, None if wall is None else float(wall)


@dataclass
class ControlRun:
    """A control method's run in ``run_dir`` (see the module docstring)."""

    cfg: TrainConfig
    run_dir: RunDirectory
    task: Task
    progress: bool = True
    state: dict[str, Any] = dataclasses.field(default_factory=dict)

    # ------------------------------------------------------------------ the surface the CLI and drivers use
    @property
    def t(self) -> int:
        """The real steps used so far (identification's transitions)."""
        return int(self.state.get("identify", {}).get("real_transitions", 0))

    @property
    def finished(self) -> bool:
        """Whether the test evaluation is done."""
        return bool(self.state.get("done"))

    @classmethod
    def build(cls, cfg: TrainConfig, run_dir: RunDirectory, progress: bool = True) -> ControlRun:
        """The run of ``cfg`` (nothing written); a configuration that cannot run is a one-line error here."""
        try:
            task = task_of(cfg.env, cfg.env_kwargs)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        pin_threads(cfg.threads)
        check_pool_sizes(task, cfg.eval_protocol, cfg.eval_episodes, cfg.holdout_episodes)
        return cls(cfg, run_dir, task, progress)

    def load(self) -> None:
        """The stages already done, from ``control.json`` (none where it is missing)."""
        stages = read_stages(self.run_dir)
        if stages is not None:
            self.state = stages

    def _save(self) -> None:
        self.state["wall_s"] = self.wall_s
        self.run_dir.write_json(CONTROL_FILE, self.state)

    def _say(self, text: str) -> None:
        if self.progress:
            print(f"{self.cfg.method.name} {self.cfg.env}: {text}", file=sys.stderr, flush=True)

    # ------------------------------------------------------------------ the stages
    def train(self) -> RunSummary:
        """Run the stages not yet done and return the summary (:class:`~pimbrl.training.loop.RunSummary`)."""
        self._started = time.perf_counter()
        self._offset = float(self.state.get("wall_s", 0.0))
        try:
            controller = None
            if not self.finished:
                controller = self._controller()
                self._test(controller)
                self.state["done"] = True
                self._save()
            played = False
            if self.cfg.holdout_episodes and read_holdout(self.run_dir, self.t) is None:  # after the test, or resumed
                controller = controller or self._controller()
                result = self._play_pool(controller, "holdout", self.cfg.holdout_episodes)
                write_holdout(self.run_dir, self.t, result.returns, result.lengths)
                played = True
            return self._finish(update=played)
        finally:
            self.run_dir.close()

    @property
    def wall_s(self) -> float:
        """Wall seconds of the run over all its sessions."""
        started = getattr(self, "_started", None)
        return float(self.state.get("wall_s", 0.0)) if started is None else self._offset + time.perf_counter() - started

    def _controller(self) -> Controller:
        m = self.cfg.method
        if isinstance(m, Feedback):
            return self._feedback(m)
        assert isinstance(m, (MPC, DPC))
        physics = self._physics(m)
        from ..control.plant import make_plant

        plant = make_plant(physics, m.n_intermediate)
        if isinstance(m, MPC):
            from ..control.mpc import GradientMPC

            return GradientMPC(plant, m.horizon, m.iterations, m.lr, m.first_iterations, self.task.max_episode_steps)
        return self._dpc(m, plant)

    def _physics(self, m: MPC | DPC) -> Any:
        """The physics the controller believes: the prior, with identified coefficients where it learns some."""
        prior = self.task.physics.with_coefficients(**m.prior)
        if not m.learn.coefficients:
            return prior
        if "identify" not in self.state:
            from ..control.identify import collect_random, identify_coefficients

            self._say(f"identifying {', '.join(m.learn.coefficients)} from {m.identify.steps:,d} real transitions")
            data = collect_random(self.cfg.env, self.cfg.env_kwargs, m.identify.steps, self.cfg.seed)
            values = identify_coefficients(
                prior,
                m.learn.ranges(),
                data,
                m.n_intermediate,
                m.identify.iterations,
                m.identify.batch_size,
                m.learn.lr,
                self.cfg.seed,
            )
            truth = self.task.physics.coefficient_values()
            self.state["identify"] = {
                "real_transitions": m.identify.steps,
                "prior": {k: prior.coefficient_values()[k] for k in values},
                "identified": values,
                "true": {k: truth[k] for k in values},
            }
            self._say(f"identified {values} (true {self.state['identify']['true']})")
            self._save()
        return prior.with_coefficients(**self.state["identify"]["identified"])

    def _validation_states(self, episodes: int) -> np.ndarray:
        return self.task.validation_initial_states(episodes)

    def _feedback(self, m: Feedback) -> Controller:
        kind, options, gains = declared_feedback(self.cfg.env, self.task.physics, m.kind)
        if "feedback" not in self.state:
            states = self._validation_states(m.validation_episodes)
            best, scores, steps = tune_gain(self.cfg.env, self.cfg.env_kwargs, self.task, kind, m.gains or gains, states, options)
            validation = [{"gain": g, "return": r if math.isfinite(r) else None} for g, r in scores]  # None: no LQR
            self.state["feedback"] = {"kind": kind, "gain": best, "validation": validation}
            self.state["validation_transitions"] = steps
            self._say(f"{kind} gain {best:g} chosen on {m.validation_episodes} validation episodes")
            self._save()
        chosen = self.state["feedback"]
        return make_feedback(self.task, chosen["kind"], float(chosen["gain"]), options)

    def _dpc(self, m: DPC, plant: Any) -> Controller:
        from ..control.dpc import DPCPolicy, DPCTrainer

        policy = DPCPolicy(plant, m.hidden, self.cfg.seed)
        trainer = DPCTrainer(policy, self.task, m.horizon, m.batch_size, m.lr, m.continue_fraction, self.cfg.seed)
        if self.run_dir.checkpoint_path.exists():
            trainer.load_state_dict(self.run_dir.load_checkpoint()["dpc"])
            self._dpc_state(trainer)  # control.json follows the checkpoint (a kill may have come between the two)
        validation = self._validation_states(m.validation_episodes)

        def score(p: Controller) -> tuple[float, int]:
            result = play(self.cfg.env, self.cfg.env_kwargs, p, validation)
            return result.mean, result.control_steps

        while trainer.steps < m.iterations:
            predicted = trainer.step()
            if trainer.steps % m.validate_every == 0 or trainer.steps == m.iterations:
                value = trainer.validate(score)
                self._say(f"step {trainer.steps:,d}: predicted {predicted:.2f}, validation {value:.2f}")
                self.run_dir.save_checkpoint({"dpc": trainer.state_dict()})
                self._dpc_state(trainer)
        trainer.check_applied()  # also for a run resumed after its last step (the loop above then takes none)
        if trainer.best_state is not None:
            policy.load_state_dict(trainer.best_state)
        return policy

    def _dpc_state(self, trainer: Any) -> None:
        """DPC's counters and validation history in ``control.json``, from the trainer (its checkpoint's state)."""
        self.state["validation_transitions"] = trainer.validation_transitions
        self.state["dpc"] = {
            "steps": trainer.steps,
            "scheme_transitions": trainer.scheme_transitions,
            "skipped_steps": trainer.skipped,
            "best_step": trainer.best_step,
            "best_validation_return": trainer.best_return,
            "history": trainer.history,
        }
        self._save()

    def _play_pool(self, controller: Controller, protocol: str, episodes: int) -> ControlResult:
        """``controller`` on the draws of ``protocol``, in resumable chunks of ``model.batch`` (``control.json``)."""
        states = self.task.protocol_initial_states(protocol, episodes, self.cfg.eval_seed)
        batch = getattr(self.cfg.method, "batch", len(states))
        key = "test" if protocol == self.cfg.eval_protocol else protocol
        chunks: list[dict[str, Any]] = self.state.setdefault(key, {"chunks": []})["chunks"]
        done = sum(len(c["returns"]) for c in chunks)
        while done < len(states):
            part = states[done : done + batch]
            result = play(self.cfg.env, self.cfg.env_kwargs, controller, part)
            chunks.append(
                {
                    "returns": result.returns.tolist(),
                    "lengths": result.lengths.tolist(),
                    "inference_s": result.inference_s,
                    "control_steps": result.control_steps,
                    "scheme_transitions": result.scheme_transitions,
                    "acted": result.acted,
                    "blown_up": result.blown_up,
                }
            )
            done += len(part)
            self._say(
                f"{protocol} episodes {done}/{len(states)}: mean return so far "
                f"{np.mean([r for c in chunks for r in c['returns']]):.3f}"
            )
            self._save()
        return ControlResult(
            np.array([r for c in chunks for r in c["returns"]]),
            np.array([n for c in chunks for n in c["lengths"]]),
            sum(c["inference_s"] for c in chunks),
            sum(c["control_steps"] for c in chunks),
            sum(c["scheme_transitions"] for c in chunks),
            sum(c.get("acted", c["control_steps"]) for c in chunks),
            sum(c.get("blown_up", 0) for c in chunks),
        )

    def _test(self, controller: Controller) -> None:
        """The evaluation (``eval_protocol``'s draws, the test pool by default): its row of ``evaluations.csv``."""
        result = self._play_pool(controller, self.cfg.eval_protocol, self.cfg.eval_episodes)
        returns, lengths = result.returns, result.lengths
        row = {
            "step": self.t,
            "return_mean": result.mean,
            "return_min": float(returns.min()),
            "return_max": float(returns.max()),
            "return_std": float(returns.std()),
            "length_mean": float(lengths.mean()),
            "episodes": len(returns),
            "updates": self._updates(),
            "wall_s": self.wall_s,
        }
        self.run_dir.evaluations.truncate_after(-1)  # one row: a resumed run writes it again
        self.run_dir.evaluations.append(row)
        self.state["inference_s_per_step"] = result.inference_s_per_step
        self._save()
        cost = result.inference_s_per_step * 1e3
        self._say(
            f"{self.cfg.eval_protocol} return {result.mean:.3f} over {len(returns)} episodes; {cost:.3f} ms per control step"
        )
        if result.blown_up:  # MPC kept an earlier plan where the scheme blew up: said even in a quiet run
            print(
                f"warning: the scheme blew up while planning {result.blown_up:,} of {result.acted or result.control_steps:,} "
                "decisions (control.json: blown_up per chunk), whose plans kept their last finite step; give the scheme "
                "more steps per control step (--model.n-intermediate)",
                file=sys.stderr,
            )

    def _updates(self) -> int:
        """Gradient steps of the controller's training (DPC), 0 for the others."""
        return int(self.state.get("dpc", {}).get("steps", 0))

    def _finish(self, update: bool = False) -> RunSummary:
        rows = self.run_dir.evaluations.read()
        final = float(rows[-1]["return_mean"]) if rows else None
        scheme = int(self.state.get("dpc", {}).get("scheme_transitions", 0)) + sum(
            int(c["scheme_transitions"]) for pool in ("test", "holdout") for c in self.state.get(pool, {}).get("chunks", [])
        )
        summary = RunSummary(
            steps=self.t,
            updates=self._updates(),
            final_return_mean=final,
            best_return_mean=final,
            steps_to_threshold=steps_to_threshold(rows, self.cfg.threshold),
            wall_s=self.wall_s,
            real_transitions=self.t,
            imagined_transitions=0,
            scheme_transitions=scheme,
            validation_transitions=int(self.state.get("validation_transitions", 0)),
            inference_s_per_step=self.state.get("inference_s_per_step"),
            **holdout_summary(self.run_dir, self.t, self.cfg.holdout_episodes),
        )
        if update or self.run_dir.status != "finished":
            self.run_dir.update_status(status="finished", summary=dataclasses.asdict(summary))
        return summary
