"""Gymnasium shells around a task: the single and native vector environments every system's envs derive from.

The systems (and their registered ids ``pimbrl/<Name>-v0``) are declared in :mod:`pimbrl.systems`.
"""

from __future__ import annotations

from .base import PHYSICS_INFO_KEYS, PhysicsEnv, PhysicsVectorEnv
from .task import HOLDOUT_SEED, VALIDATION_SEED, StepOutcome, Task

__all__ = ["HOLDOUT_SEED", "PHYSICS_INFO_KEYS", "VALIDATION_SEED", "PhysicsEnv", "PhysicsVectorEnv", "StepOutcome", "Task"]
