"""The one interface every UED method implements, so the outer loop never knows which it runs.

A method is a frozen object of pure functions (built once from static configuration) over an
explicit method state pytree:

    m = method.init(key)                         # teacher state: networks, optimisers, buffers
    m, s = method.begin_episode(key, m, s)       # s: a freshly initialised StudentState
    m, s, info = method.step(key, m, s)          # one budget step (see docs/architecture.md)

``step`` generates levels, trains the student for the budget step's env steps on them (the method
decides how: one block of C steps on n levels for SHED/h-MDP/ACCEL-NR, or a new level per slot per
PPO rollout for DR/PLR/ACCEL/PAIRED), evaluates as the method needs, computes teacher rewards,
stores experience and updates the teacher. All of it must be jittable and usable inside
``lax.scan``; nothing here touches the host.
"""
from __future__ import annotations

from typing import Any, Protocol

import jax
from flax import struct


@struct.dataclass
class StepInfo:
    """Per-budget-step record shared by all methods (stacked by the loop's scan).

    levels:          [L, d] parameter vectors (box units, ``env.param_space`` order) of the levels the
                     student trained on during this step; L is static per method.
    env_steps_train: student env steps used for gradient updates in this step.
    env_steps_eval:  env steps spent on evaluation rollouts (teacher state, scoring, antagonist...).
    teacher_reward:  the teacher's reward for this step (NaN for methods without one).
    num_new_levels:  distinct newly generated levels in this step (the paper's resource).
    extras:          method-specific scalars/arrays (losses, buffer sizes, ...).
    """

    levels: jax.Array
    env_steps_train: jax.Array
    env_steps_eval: jax.Array
    teacher_reward: jax.Array
    num_new_levels: jax.Array
    extras: dict = struct.field(default_factory=dict)


class UEDMethod(Protocol):
    name: str

    def init(self, key: jax.Array) -> Any: ...

    def begin_episode(self, key: jax.Array, mstate: Any, student_state: Any) -> tuple[Any, Any]: ...

    def step(self, key: jax.Array, mstate: Any, student_state: Any) -> tuple[Any, Any, StepInfo]: ...
