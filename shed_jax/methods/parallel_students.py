"""K students under one teacher (issue #26): more teacher transitions per teacher episode.

A hierarchical teacher gets one transition per budget step, T = 20 per teacher episode. Here K
students train side by side under one teacher, so each budget step gives the teacher K transitions:

* **one teacher**: one DDPG, one B_real, one synthesiser (``shed-x``), one set of hyperparameters;
* **K students**, each with its own parameters, optimiser, env states and evaluation key (a leading
  K axis on the student state, ``vmap`` over the students): student k has its own teacher state
  s_k, its own action u_k = actor(s_k) + its own exploration noise, its own levels, its own s'_k and
  reward r_k. The K transitions (s_k, u_k, r_k, s'_k) go into B_real together, in student order,
  every budget step (``HierarchicalTeacher.experience`` per student, ``learn`` once on the batch).
* **DDPG updates per budget step are unchanged** (``ddpg_updates``, or the synthesiser's rule): the
  same number of updates and the same batch size, drawn from K times as many transitions. The
  teacher's optimiser sees the same number of steps per teacher episode as with one student (its
  learning rates and the actor's drift towards saturation were tuned per update), each batch is
  drawn from K times the data (K times fewer replays per transition), and the extra GPU time is the
  K students' only. More updates are a separate switch (``--set ddpg_updates=...``, hmdp-x).

Keys: student k draws with ``student_keys(key, K)[k]``: ``key`` itself for student 0 and
``fold_in(key, k)`` for the others, for every key of a step (and the students' initialisation and
evaluations). Until the teacher's first DDPG update student 0 is therefore the one-student run's.

What the loop sees (:class:`StudentPool`, the loop's student): the student state has the K axis;
an evaluation runs all K students and pools their episodes per level, returns [levels, K x
episodes]. So the **reported test return is the mean over the K students** (each student's mean
over levels and episodes, averaged): the expected score of a student trained by this teacher, with
a smaller variance than one student's. ``eval`` and ``--final-eval`` pool the same way.

The step's record (``StepInfo``) keeps the one-student shapes: ``levels`` (and ``levels_*``) hold
every student's levels, student after student; ``num_new_levels`` is their total;
``eval_longest_episode`` is the longest of the students' (their evaluations run as one vmapped
rollout, which lasts as long as its longest); every other entry is the mean over the students (NaN-aware), so ``teacher_reward``, ``teacher_state`` and the
diagnostics are the students' means, and the env-step counts are per student (each student trains
the preset's budget; the run costs K times as many env steps). Per student it adds
``teacher_reward_per_student`` [K], ``teacher_state_per_student`` [K, m] and
``test_return_per_student`` [K] (NaN where the test set did not run).

Built by ``make_hmdp_x``/``make_shed_x`` when ``students`` > 1; with ``students=1`` they return the
learning teacher itself, so one student is exactly today's method.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from shed_jax.methods.base import EvalRequest, StepInfo
from shed_jax.methods.hierarchical import HierarchicalState, HierarchicalTeacher, Learned

#: the fields of the teacher state that belong to each student (a leading K axis); the rest are the teacher's
PER_STUDENT = ("s", "eval_key", "pending_eval_steps")


def student_keys(key: jax.Array, k: int) -> jax.Array:
    """K keys [K, ...] from one: ``key`` itself for student 0, ``fold_in(key, i)`` for student i > 0."""
    rest = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(1, k))
    return jnp.concatenate([key[None], rest])


def pool_episodes(returns: jax.Array) -> jax.Array:
    """Per-student returns [K, levels, episodes] -> [levels, K x episodes], student after student."""
    k, n, e = returns.shape
    return jnp.moveaxis(returns, 0, 1).reshape(n, k * e)


def _mean(x: jax.Array) -> jax.Array:
    """The mean over the leading (student) axis: NaN-aware for floats, the dtype kept for ints and bools."""
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.floating):
        return jnp.nanmean(x, axis=0)
    return jnp.mean(x, axis=0).astype(x.dtype)


#: ``extra_info`` entries pooled over the students by their maximum, not their mean (module doc)
POOLED_BY_MAX = ("eval_longest_episode",)


def _flat(x: jax.Array) -> jax.Array:
    """[K, n, ...] -> [K * n, ...]: the students' rows, student after student."""
    return x.reshape((-1,) + x.shape[2:])


def _pool_extra(key: str, v):
    """One ``extra_info`` entry [K, ...] as one student's (module doc): ``levels_*`` concatenated, those
    in ``POOLED_BY_MAX`` the largest, the rest averaged."""
    if key.startswith("levels_"):
        return _flat(v)
    if key in POOLED_BY_MAX:
        return jnp.max(v, axis=0)
    return jax.tree_util.tree_map(_mean, v)


@dataclasses.dataclass(frozen=True)
class StudentPool:
    """``size`` students of one kind with a leading K axis on the state: the loop's student for
    :class:`ParallelStudents`. ``init`` and ``evaluate`` have the student's signatures."""

    student: Any
    size: int

    @property
    def config(self):
        return self.student.config

    @property
    def obs_shape(self):
        return self.student.obs_shape

    @property
    def env_steps_per_update(self) -> int:
        """Per student."""
        return self.student.env_steps_per_update

    @property
    def train_envs(self) -> int:
        """Of all K students: their rollouts are one vmapped batch."""
        return self.size * self.student.train_envs

    def init(self, key: jax.Array, hparams=None):
        """K fresh students (student i from ``student_keys(key, K)[i]``). ``hparams``: None, one set for
        all (scalar leaves) or one per student (leaves [K], as a pool state's own ``hparams``)."""
        leaves = jax.tree_util.tree_leaves(hparams)
        per_student = bool(leaves) and jnp.ndim(leaves[0]) > 0
        return jax.vmap(self.student.init, in_axes=(0, 0 if per_student else None))(student_keys(key, self.size), hparams)

    def evaluate(self, state, key, levels, num_episodes: int, max_steps: int | None = None, deterministic: bool = False):
        """Every student on ``levels`` (student i with ``student_keys(key, K)[i]``), episodes pooled per
        level: returns [levels, K x num_episodes] (``pool_episodes``)."""
        run = lambda s, k: self.student.evaluate(s, k, levels, num_episodes, max_steps, deterministic)
        return pool_episodes(jax.vmap(run)(state, student_keys(key, self.size)))

    @staticmethod
    def member(state, i: int, axis: int = 0):
        """Student ``i`` of a pool state whose student axis is ``axis`` (1 under a leading seed axis)."""
        return jax.tree_util.tree_map(lambda x: jnp.take(x, i, axis=axis), state)


@dataclasses.dataclass(frozen=True)
class ParallelStudents:
    """``size`` students under one hierarchical teacher ``base`` (module doc). The UED method
    interface; the loop's student must be ``pool``."""

    base: HierarchicalTeacher
    size: int

    def __post_init__(self):
        if not (isinstance(self.size, int) and self.size >= 2):
            raise ValueError(f"{self.base.name}: ParallelStudents needs >= 2 students, got {self.size!r} "
                             "(one student is the teacher itself)")
        object.__setattr__(self, "pool", StudentPool(self.base.student, self.size))

    # ---- what the driver and sweeps read: the base teacher's ---------------------------------

    @property
    def name(self) -> str:
        return self.base.name

    @property
    def config(self):
        return self.base.config

    @property
    def env(self):
        return self.base.env

    @property
    def hparam_names(self) -> tuple[str, ...]:
        return self.base.hparam_names

    @property
    def default_hparams(self):
        return self.base.default_hparams

    def with_hparams(self, mstate: HierarchicalState, hparams) -> HierarchicalState:
        return self.base.with_hparams(mstate, hparams)  # the hyperparameters are the teacher's, shared

    @property
    def fuses_test_eval(self) -> bool:
        return self.base.fuses_test_eval

    # ---- the K axis --------------------------------------------------------------------------

    def axes(self, mstate: HierarchicalState) -> HierarchicalState:
        """``vmap`` axes of a teacher state: 0 on the students' fields (``PER_STUDENT``), None on the teacher's."""
        return mstate.replace(**{f.name: 0 if f.name in PER_STUDENT else None for f in dataclasses.fields(mstate)})

    def init(self, key: jax.Array, hparams=None) -> HierarchicalState:
        """The teacher's state with its students' fields repeated K times."""
        mstate = self.base.init(key, hparams)
        k = self.size
        return mstate.replace(**{f: jnp.broadcast_to(getattr(mstate, f), (k,) + jnp.shape(getattr(mstate, f)))
                                 for f in PER_STUDENT})

    def begin_episode(self, key: jax.Array, mstate: HierarchicalState, sstate):
        """The base's ``begin_episode`` for each student (its s_0, evaluation key, first levels);
        the teacher's fields must come back unchanged by any student (``out_axes`` None checks it)."""
        axes = self.axes(mstate)
        return jax.vmap(self.base.begin_episode, in_axes=(0, axes, 0), out_axes=(axes, 0))(
            student_keys(key, self.size), mstate, sstate)

    def step(self, key: jax.Array, mstate: HierarchicalState, sstate):
        return self._step(key, mstate, sstate, None)[:3]

    def step_with_test(self, key: jax.Array, mstate: HierarchicalState, sstate, test: EvalRequest):
        return self._step(key, mstate, sstate, test)

    def _step(self, key, mstate: HierarchicalState, sstate, test: EvalRequest | None):
        base, k = self.base, self.size
        k_act, k_seed, k_train, k_eval, k_synth, k_ddpg = jax.random.split(key, 6)  # as the base's step
        keys = tuple(student_keys(x, k) for x in (k_act, k_seed, k_train, k_eval))
        k_test = None if test is None else student_keys(test.key, k)

        def one(keys, m, s, k_test):
            request = None if test is None else dataclasses.replace(test, key=k_test)
            return base.experience(keys, m, s, request)

        sstate, exp, test_rets = jax.vmap(one, in_axes=(0, self.axes(mstate), 0, None if test is None else 0))(
            keys, mstate, sstate, k_test)
        learned_state, learned = base.learn((k_synth, k_ddpg), mstate, exp.transition)  # all K transitions, one teacher
        per_learned = Learned(td_heldout=0, real_size=None, syn_size=None, branch=None, synth_loss=None,
                              synth_heldout=None)
        infos = jax.vmap(base.step_info, in_axes=(0, per_learned))(exp, learned)
        info = self.pooled_info(infos, exp, test_rets)
        mstate = learned_state.replace(s=exp.s_next, t=mstate.t + 1, pending_eval_steps=jnp.zeros((k,), jnp.int32))
        return mstate, sstate, info, (None if test_rets is None else pool_episodes(test_rets))

    def pooled_info(self, infos: StepInfo, exp, test_rets) -> StepInfo:
        """The K students' records [K, ...] as one (module doc): levels concatenated, counts summed, the
        evaluations' longest episode the longest, the rest averaged."""
        extras = {key: _pool_extra(key, v) for key, v in infos.extras.items()}
        extras["teacher_reward_per_student"] = exp.transition.r
        extras["teacher_state_per_student"] = exp.s_next
        n = exp.s_next.shape[0]
        extras["test_return_per_student"] = (jnp.full((n,), jnp.nan, jnp.float32) if test_rets is None
                                             else jnp.mean(test_rets, axis=(1, 2)))
        return StepInfo(levels=_flat(infos.levels), env_steps_train=_mean(infos.env_steps_train),
                        env_steps_eval=_mean(infos.env_steps_eval), teacher_reward=_mean(infos.teacher_reward),
                        num_new_levels=jnp.sum(infos.num_new_levels).astype(jnp.int32), extras=extras)
