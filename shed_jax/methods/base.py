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

Shared by the methods: :func:`nan_like`, :func:`mean_metrics` and :func:`update_metrics_shape` for
the PPO metrics of a step, and :func:`warn_if_rollouts_cut_episodes` (native mode resets every slot
at each rollout, so it warns when a training episode can outlast a rollout). Level code is in
``shed_jax.levels``.
"""
from __future__ import annotations

import dataclasses
import warnings
from typing import Any, Protocol

import jax
import jax.numpy as jnp
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


# --------------------------------------------------------------------------------------------
# shared by the methods
# --------------------------------------------------------------------------------------------


def nan_like(tree: Any) -> Any:
    """A pytree of NaNs (floats) / zeros (ints, bools) shaped like ``tree`` (or its ShapeDtypeStructs)."""

    def fill(x):
        dt = jnp.dtype(x.dtype)
        return jnp.full(x.shape, jnp.nan if jnp.issubdtype(dt, jnp.floating) else 0, dt)

    return jax.tree_util.tree_map(fill, tree)


def mean_metrics(metrics: Any) -> Any:
    """Mean over the leading (update) axis, ignoring NaN placeholders of skipped updates."""
    return jax.tree_util.tree_map(lambda x: jnp.nanmean(jnp.asarray(x, jnp.float32), axis=0), metrics)


def update_metrics_shape(student, sstate, key):
    """Shapes of ``student.update``'s metrics, without running it (for NaN placeholders)."""
    traj_shape = jax.eval_shape(student.rollout, sstate, key)[1]
    return jax.eval_shape(student.update, sstate, key, traj_shape)[1]


class RolloutTruncationWarning(UserWarning):
    """A native-mode method whose rollouts are shorter than a training episode may last."""


def warn_if_rollouts_cut_episodes(name: str, student, space, other_fix: str = "") -> None:
    """Warn when native-mode rollouts cannot hold a whole training episode.

    Native mode (docs/design.md §8.1) resets every slot onto its new level at the start of each rollout, so an
    episode longer than ``student.config.num_steps`` is cut off and its end (a landing, the walker's
    goal) is never seen in training. DCD's and JaxUED's rollouts are as long as an episode; the
    lander (128 < 600) and walker (32 < 2000) presets' are not (docs/baselines.md).
    """
    limit = getattr(space.base, "max_steps", None) if space.base is not None else None
    if limit is None or student is None:  # a method built without a student only samples levels
        return
    limit, steps = int(np.max(np.asarray(limit))), int(student.config.num_steps)
    if steps >= limit:
        return
    batch = steps * int(student.config.num_envs)
    longer = next((k * steps for k in range(-(-limit // steps), batch // steps + 1) if batch % (k * steps) == 0), None)
    hint = (f", e.g. --ppo num_envs={batch // longer} --ppo num_steps={longer} (the same {batch:,} steps per update)"
            if longer is not None else "")
    warnings.warn(
        f"{name}: native-mode rollouts of {steps} steps reset every slot, but a training episode may last "
        f"{limit} steps; longer episodes are cut off and their ends never reach the student (docs/baselines.md, "
        f"'Rollout length in native mode'). Rollouts of >= {limit} steps avoid it{hint}.{other_fix}",
        RolloutTruncationWarning, stacklevel=3)
