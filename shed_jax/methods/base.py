"""The one interface every UED method implements, so the outer loop never knows which it runs.

A method is a frozen object of pure functions (built once from static configuration) over an
explicit method state pytree:

    m = method.init(key)                         # teacher state: networks, optimisers, buffers
    m, s = method.begin_episode(key, m, s)       # s: a freshly initialised StudentState
    m, s, info = method.step(key, m, s)          # one budget step (see docs/architecture.md)

Optional: a method that evaluates its student at the end of ``step`` (SHED, h-MDP) may also offer

    m, s, info, test_returns = method.step_with_test(key, m, s, test)   # test: an EvalRequest

(with ``method.fuses_test_eval`` true), which is ``step`` plus the loop's test-set evaluation of
the stepped student, run as one batched rollout with the method's own evaluation
(``PPOStudent.evaluate_many``): a latency-bound simulator (MJX) then pays its per-step latency once. It draws the keys that ``step`` and a separate
``student.evaluate(s, test.key, test.levels, test.num_episodes, test.max_steps)`` draw, so the
results are equal where the backend computes a row the same at any batch size (see
``PPOStudent.evaluate_many``; elsewhere they agree up to last-bit differences and their growth).

``step`` generates levels, trains the student for the budget step's env steps on them (the method
decides how: one block of C steps on n levels for SHED/h-MDP/ACCEL-NR, or a new level per slot per
PPO rollout for DR/PLR/ACCEL/PAIRED), evaluates as the method needs, computes teacher rewards,
stores experience and updates the teacher. All of it must be jittable and usable inside
``lax.scan``; nothing here touches the host.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import jax
import numpy as np
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
    extras:          method-specific scalars/arrays (losses, buffer sizes, ...). An entry whose key
                     starts with ``levels_`` is per level: its leading axis is aligned with
                     ``levels`` (e.g. ``levels_trained_mask``), and ``thin_levels`` thins it with them.
    """

    levels: jax.Array
    env_steps_train: jax.Array
    env_steps_eval: jax.Array
    teacher_reward: jax.Array
    num_new_levels: jax.Array
    extras: dict = struct.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class EvalRequest:
    """The loop's test-set evaluation, handed to ``step_with_test`` (built inside the trace).

    ``run`` says whether the test set runs at this step: a Python bool, or a traced bool that must be
    unbatched under ``vmap`` (the loop's is: all seeds share the budget-step schedule), so that the
    method's ``lax.cond`` on it stays a real branch. When it is false the returns are NaN.
    """

    key: jax.Array
    levels: Any  # env params pytree with a leading axis
    num_episodes: int
    max_steps: int | None
    run: Any = True


def thin_levels(info: StepInfo, max_levels: int | None) -> StepInfo:
    """Keep at most ``max_levels`` rows of ``info.levels`` (and of the ``levels_*`` extras) for the record.

    Native-mode methods report every level of a budget step, ``updates_per_step x num_envs`` of
    them: 30,720 walker levels per step and seed at 30 x 1024, about 24 MB of ``metrics.jsonl`` per
    budget step for 5 seeds. The record only feeds plots of the generated parameters, so evenly
    spaced rows over the step (early and late updates alike) are kept. The rows are static, so this
    is free under jit. ``None`` keeps every row. Counts such as ``num_new_levels`` are computed by
    the method before thinning and stay exact.
    """
    n = info.levels.shape[0]
    if max_levels is None or n <= max_levels:
        return info
    rows = np.round(np.linspace(0, n - 1, max_levels)).astype(np.int32)
    extras = {k: (v[rows] if k.startswith("levels_") else v) for k, v in info.extras.items()}
    return info.replace(levels=info.levels[rows], extras=extras)


class UEDMethod(Protocol):
    name: str

    def init(self, key: jax.Array) -> Any: ...

    def begin_episode(self, key: jax.Array, mstate: Any, student_state: Any) -> tuple[Any, Any]: ...

    def step(self, key: jax.Array, mstate: Any, student_state: Any) -> tuple[Any, Any, StepInfo]: ...
