"""The whole outer loop of a UED run as one ``lax.scan`` (PureJaxRL's ``make_train``, for UED).

One *budget step* of the scan:

1. at the first step of a teacher episode, re-initialise the student (the paper's Algorithm 1) and
   let the method begin the episode (SHED evaluates the fresh student to get s_0);
2. ``method.step``: generate levels, train the student, evaluate, reward, store, synthesise,
   update the teacher (what exactly is the method's business; see ``shed_jax.methods``);
3. evaluate the student on the fixed test set (stochastic policy, as the paper and DCD do) and
   record it with the method's ``StepInfo``. A method that evaluates the student at the end of its
   step anyway (``fuses_test_eval``: SHED, h-MDP) runs the test set in the same rollout
   (``step_with_test``), with the same keys.

``make_run`` returns ``(init, run)``: ``init(key) -> RunState`` and
``run(state, num_steps, start_step) -> (state, metrics)`` where ``metrics`` is stacked over the
``num_steps`` budget steps starting at global step ``start_step``. Jit ``run`` with ``num_steps``
static: calling it on consecutive chunks (for progress bars and checkpoints) compiles once and gives
exactly the same result as one long call. Seeds are batched with ``jax.vmap`` over ``init``'s key and
``run``'s state, with ``start_step`` *not* mapped (``in_axes=(0, None, None)``): all seeds share the
schedule, so the episode-start and test-set ``lax.cond``s keep an unbatched predicate and stay real
branches under ``vmap`` (a batched predicate would turn them into selects that re-initialise the
student and run the test set at every step).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from shed_jax.methods.base import EvalRequest, nan_like, thin_levels


@struct.dataclass
class RunState:
    student: Any  # StudentState of the reported student
    method: Any  # the method's teacher state
    key: jax.Array
    step: jax.Array  # global budget-step index (int32)


@dataclasses.dataclass(frozen=True)
class LoopSpec:
    """Static description of the loop: episodes, budget steps and the test protocol."""

    steps_per_episode: int  # T, budget steps per teacher episode
    num_episodes: int  # N_ep
    test_episodes: int = 10  # episodes per test level, per budget step
    test_max_steps: int | None = None  # None: the test levels' own time limit
    # Evaluate on the test set at every k-th budget step of a tested episode and at its last step
    # (NaN in between), so every tested episode has a final test return whatever T is.
    test_every: int = 1
    # Test only in teacher episodes e with e % k == 0, and always in the last one (NaN in the
    # others). Reports need the first and last episodes' curves (docs/design.md §9.3); testing the students of
    # the episodes between costs a 500-step evaluation per budget step, about a fifth of a SHED step.
    test_episode_every: int = 1
    # At most this many of a budget step's levels go into the metrics record (evenly spaced rows,
    # methods.base.thin_levels); None records all of them, as runs saved before this field did.
    max_recorded_levels: int | None = 64

    def __post_init__(self):
        for name in ("steps_per_episode", "num_episodes", "test_episodes", "test_every", "test_episode_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"LoopSpec.{name} must be >= 1, got {getattr(self, name)}")
        m = self.max_recorded_levels
        if m is not None and (isinstance(m, bool) or not isinstance(m, int) or m < 1):
            raise ValueError(f"LoopSpec.max_recorded_levels must be a positive int or None, got {m!r}")

    @property
    def total_steps(self) -> int:
        return self.steps_per_episode * self.num_episodes

    def tests_at(self, step):
        """Whether the loop evaluates the test set at global budget step(s) ``step``.

        Works on Python ints, numpy arrays and (unbatched) JAX values alike, so the compiled loop
        and the host-side checks share one definition.
        """
        T = self.steps_per_episode
        episode, in_step = step // T, step % T
        in_episode = (episode % self.test_episode_every == 0) | (episode == self.num_episodes - 1)
        return (((in_step + 1) % self.test_every == 0) | (in_step == T - 1)) & in_episode


def make_run(student, method, test_levels, spec: LoopSpec) -> tuple[Callable, Callable]:
    """Build ``init`` and ``run`` for one seed (vmap them for several).

    ``student`` is the object from ``shed_jax.student.make_student``; ``method`` implements
    ``shed_jax.methods.base.UEDMethod``; ``test_levels`` is an env params pytree with a leading
    axis (one entry per test level).
    """

    def init(key: jax.Array, hparams=None) -> RunState:
        k_student, k_method, k_run = jax.random.split(key, 3)
        return RunState(
            student=student.init(k_student, hparams),
            method=method.init(k_method),
            key=k_run,
            step=jnp.zeros((), jnp.int32),
        )

    def budget_step(state: RunState, t):
        # t: the global budget step, unbatched across vmapped seeds (state.step is its batched copy)
        key, k_init, k_begin, k_step, k_test = jax.random.split(state.key, 5)
        t_in_episode = t % spec.steps_per_episode
        episode = t // spec.steps_per_episode

        def start_episode(operand):
            mstate, sstate = operand
            fresh = student.init(k_init, sstate.hparams)
            return method.begin_episode(k_begin, mstate, fresh)

        mstate, sstate = jax.lax.cond(
            t_in_episode == 0, start_episode, lambda operand: operand, (state.method, state.student)
        )
        if getattr(method, "fuses_test_eval", False):
            # The method evaluates the stepped student anyway (SHED's teacher state): the test set
            # joins that rollout (``step_with_test``), so a latency-bound simulator pays its
            # sequential steps once. Same keys as the separate evaluation below; the same floats
            # only where the backend computes a row the same at any batch size (docs/running.md).
            # Whether to test: static True when every step tests, else ``tests_at(t)``, a traced
            # bool computed from the unbatched ``t`` (all seeds share it), so the method's
            # ``lax.cond`` stays a real branch under vmap and the test set runs only on test steps.
            always = spec.test_every == 1 and spec.test_episode_every == 1
            test = EvalRequest(k_test, test_levels, spec.test_episodes, spec.test_max_steps,
                               True if always else spec.tests_at(t))
            mstate, sstate, info, test_returns = method.step_with_test(k_step, mstate, sstate, test)
            info = thin_levels(info, spec.max_recorded_levels)
        else:
            mstate, sstate, info = method.step(k_step, mstate, sstate)
            info = thin_levels(info, spec.max_recorded_levels)

            def run_test(s):
                return student.evaluate(s, k_test, test_levels, spec.test_episodes, spec.test_max_steps)

            test_returns = jax.lax.cond(spec.tests_at(t), run_test, lambda s: nan_like(jax.eval_shape(run_test, s)), sstate)
        metrics = {
            "step": t,
            "episode": episode,
            "step_in_episode": t_in_episode,
            "test_return_per_level": jnp.mean(test_returns, axis=-1),
            "test_return": jnp.mean(test_returns),
            "info": info,
        }
        return RunState(student=sstate, method=mstate, key=key, step=state.step + 1), metrics

    def run(state: RunState, num_steps: int, start_step=0):
        steps = jnp.asarray(start_step, jnp.int32) + jnp.arange(num_steps, dtype=jnp.int32)
        return jax.lax.scan(budget_step, state, steps)

    return init, run
