"""Control that knows the physics: feedback floors, model-predictive control and differentiable predictive control.

These are the methods a user who knows (part of) the equation can run instead of, or beside, reinforcement
learning (``pimbrl train ENV --method feedback|mpc|dpc``):

* :mod:`.feedback` - a feedback floor per system, with one gain tuned on the validation draws: proportional
  feedback under each actuator for the PDEs, LQR around the upright state for Cart-Pole, energy-based
  swing-up plus LQR for the pendulum, LQR around the origin for a declared ODE;
* :mod:`.mpc` - receding-horizon control whose action plan is optimised by gradient through the prior's
  differentiable coarse scheme (:class:`~pimbrl.models.residual.PhysicsResidual`, the model object of the
  known-scheme Dyna method), warm-started from the previous plan;
* :mod:`.dpc` - differentiable predictive control: a policy network trained by back-propagating the return
  of short horizons through the same scheme, no reinforcement learning;
* :mod:`.identify` - under partial physics, the coefficients fitted to real transitions first (as the
  identified-scheme method fits them), so that these methods count their real steps like every other.

Every controller maps physical states to physical actions (:class:`~.base.Controller`); :func:`~.base.play`
runs it on a batch of initial states of the real environment and measures its inference cost.
"""

from __future__ import annotations

from .base import Controller, ControlResult, play

__all__ = ["ControlResult", "Controller", "play"]
