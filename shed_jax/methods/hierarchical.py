"""Hierarchical teachers behind the UED method interface (docs/design.md §3): a DDPG teacher over performance vectors.

A :class:`HierarchicalTeacher` is composed of a DDPG teacher (``shed_jax.teacher.ddpg_teacher``:
acts, stores real transitions, updates on them) and an optional synthesiser
(``shed_jax.teacher.synthesiser``: a diffusion model and a synthetic buffer, with its mixed-update
rule). h-MDP is the teacher alone (:func:`make_hmdp`); SHED adds the diffusion synthesiser
(``shed_jax.methods.shed.make_shed``).

One budget step, top to bottom (all inside one jitted function, thresholds as ``lax.cond``):

1. u = clip(actor(s / scale) + N(0, sigma^2), -1, 1); levels theta_i = affine(u_i) into the box Θ.
2. Train the student ``updates_per_step`` PPO iterations on the n levels (slot j runs level j % n).
3. s' = mean return of ``num_eval_episodes`` episodes on each of the m fixed evaluation levels.
4. r = R(s, u, s') (``shed_jax.teacher.reward``); done = [t = T - 1]; store (s, u, r, s', done) in B_real.
5. With a synthesiser: its ``grow`` (SHED: once |B_real| > 64, train the diffusion model 250 steps
   and add 10 synthetic transitions to B_syn).
6. DDPG updates: the synthesiser's rule if there is one (SHED: 2 mixed updates, 24 real + 8
   synthetic, if |B_syn| > 500 and both buffers > 32, else 3 real updates if |B_real| > 32), else
   the teacher's (h-MDP: 2 real updates if |B_real| > 32) [official code].

The step is three parts: ``experience`` (1.-4. for one student: act, train, evaluate, reward; it
changes nothing of the teacher), ``learn`` (the teacher: store, synthesise, update) and
``step_info`` (the record). ``shed_jax.methods.parallel_students`` runs ``experience`` for K students
and ``learn`` once on their K transitions.

Buffers hold raw performance vectors (returns); rewards are computed on them and z-scored per DDPG
batch (``reward_norm='batch'``; 'none' keeps them raw). With ``time_in_state`` the teacher state is
[s, t/T] [paper]; off by default [official code].

Diagnostics in every step's ``extras``: ``at_bound_fraction`` (generated parameters within 1 % of the
range of a bound of Θ), ``td_error_heldout`` (the critic's |TD error| on the new transition before
any update has used it) and, with ``state_noise_check``, ``state_noise_sd`` (the SD of one evaluation
of the teacher state, from a second evaluation of the same student with another key; NaN when off)
and, with ``reward_noise_check``, ``reward_again``, ``reward_crossed`` and ``reward_crossed_back``
(the step's reward from a second evaluation of the students before and after its training; NaN when
off). The teacher's networks, the synthesiser and both buffers persist across teacher episodes;
``begin_episode`` only evaluates the fresh student to get s_0 and resets the step counter.

Static settings live in a frozen config (:class:`HMDPConfig` here, ``SHEDConfig`` for SHED); the
hyperparameters one may sweep live in a pytree inside the method state (:class:`TeacherHyperparams`,
``SHEDHyperparams`` adds psi), so a sweep over them is one ``vmap`` and one compile (as
``PPOHyperparams`` for the student). ``method.init(key, hparams=None)`` takes overrides;
``method.with_hparams(mstate, hparams)`` swaps them into an existing state.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar, Literal

import jax
import jax.numpy as jnp
from flax import struct

from shed_jax.configs import check_modes, check_number, coerce
from shed_jax.levels import LevelCodec, evaluation_set, new_seeds, teacher_space
from shed_jax.methods.base import EvalRequest, StepInfo, mean_metrics
from shed_jax.teacher.buffers import RingBuffer, Transition
from shed_jax.teacher.ddpg import DDPGConfig, DDPGState, make_ddpg
from shed_jax.teacher.ddpg_teacher import DDPGTeacher
from shed_jax.teacher.reward import RewardConfig, coefficient_of_variation, make_reward_fn


# ---- configuration ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TeacherConfig:
    """Settings every hierarchical teacher has; defaults are docs/design.md §3 / §10.2 (official thresholds) and §10.3 (lander).

    Use a method's own config: :class:`HMDPConfig` or ``shed_jax.methods.shed.SHEDConfig``.
    """

    updates_per_step: int = 10  # C in PPO iterations
    num_levels: int = 5  # n (lander 5, walker 4)
    budget_steps: int = 20  # T: done = 1 on the T-th transition
    num_eval_episodes: int = 8  # E_eval
    eval_set: Literal["official", "paper"] = "official"  # lander: 'official' (code's 10) or 'paper' (covering, any m); walker: ladder
    num_eval_levels: int = 10  # m
    eval_max_steps: int | None = None  # override the evaluation episode cap (default: the set's max_steps)
    state_scale: float = 100.0  # the DDPG networks see s / state_scale
    reward: RewardConfig = RewardConfig()
    explore_sigma: float = 0.1  # default of the hyperparameter explore_sigma
    actor_lr: float = 1e-3  # default of the hyperparameter actor_lr (Adam) [official code]
    critic_lr: float = 1e-3  # default of the hyperparameter critic_lr (Adam) [official code]
    ddpg_batch: int = 32
    real_capacity: int = 10000  # |B_real|
    ddpg_threshold: int = 32  # DDPG updates once |B_real| > this
    low: tuple | None = None  # Θ override
    high: tuple | None = None
    # The paper's state extension: the teacher state is [s, t/T] (the networks see [s / state_scale, t/T];
    # the buffers hold [s, state_scale * t/T]). Off: s alone [official code].
    time_in_state: bool = False
    # Rewards the critic sees: 'batch' z-scores them per sampled DDPG batch (real and synthetic parts
    # separately) [official code]; 'none' leaves them raw.
    reward_norm: Literal["batch", "none"] = "batch"
    # Diagnostic: evaluate the stepped student a second time with another key and log the noise SD of
    # the teacher state (``state_noise_sd``); costs one evaluation per budget step, charged as eval steps.
    state_noise_check: bool = False
    # Diagnostic: evaluate the student before and after the step's training again with a second key,
    # and log the reward computed three more ways (``reward_again``: both with the second key;
    # ``reward_crossed`` / ``reward_crossed_back``: s and s' with different keys). With the
    # step's own reward they give the noise SD of a reward from one key for s and s' (common random
    # numbers) and from two keys (``experiments.teacher_runs``). Costs two evaluations per budget step.
    reward_noise_check: bool = False

    #: fields that must be positive ints
    POSITIVE: ClassVar[tuple] = ("updates_per_step", "num_levels", "budget_steps", "num_eval_episodes", "num_eval_levels",
                                 "ddpg_batch", "real_capacity")

    def __post_init__(self):
        name = type(self).__name__
        for field in self.POSITIVE:
            v = getattr(self, field)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}.{field} must be a positive int, got {v!r}")
        check_modes(self)
        for field in ("time_in_state", "state_noise_check", "reward_noise_check"):
            if not isinstance(getattr(self, field), bool):
                raise ValueError(f"{name}.{field} must be True or False, got {getattr(self, field)!r}")
        for field in ("actor_lr", "critic_lr"):
            check_number(self, field, above=0)
        check_number(self, "explore_sigma", at_least=0)
        if not self.state_scale > 0:
            raise ValueError(f"{name}.state_scale must be > 0, got {self.state_scale}")
        if self.real_capacity < self.ddpg_batch:
            raise ValueError(f"{name}.real_capacity must be >= ddpg_batch ({self.ddpg_batch}), got {self.real_capacity}")


@dataclasses.dataclass(frozen=True)
class HMDPConfig(TeacherConfig):
    """h-MDP: the teacher's settings only (B_real holds 10,000 transitions [official code])."""


# ---- dynamic hyperparameters -----------------------------------------------------------------


@struct.dataclass
class TeacherHyperparams:
    """Dynamic teacher hyperparameters: float scalars (or batches of them, for ``vmap``).

    eta:           weight of the coefficient of variation in the paper's reward forms
                   (R = gain - eta * cv). Ignored by ``RewardConfig(form='code_mean')``, which has no
                   eta. Used for real rewards and for recomputed synthetic rewards alike.
    actor_lr, critic_lr: Adam learning rates of the DDPG actor and critic, held in
                   ``optax.inject_hyperparams`` optimiser states (written from here before the
                   updates of every step, so this pytree is the one source of truth).
    explore_sigma: std of the Gaussian exploration noise added to the actor's u in [-1, 1]^{n d}.

    Defaults come from the method's config (``from_config``); ``as_arrays`` validates and gives
    float32 leaves, ``stack`` a batch with a leading axis.
    """

    eta: Any = 0.05
    actor_lr: Any = 1e-3
    critic_lr: Any = 1e-3
    explore_sigma: Any = 0.1

    #: name -> (low, high, low_inclusive, high_inclusive)
    RANGES: ClassVar[dict] = {
        "eta": (0.0, math.inf, True, False),
        "actor_lr": (0.0, math.inf, False, False),
        "critic_lr": (0.0, math.inf, False, False),
        "explore_sigma": (0.0, math.inf, True, False),
    }

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_config(cls, config) -> "TeacherHyperparams":
        return cls(eta=float(config.reward.eta), actor_lr=float(config.actor_lr), critic_lr=float(config.critic_lr),
                   explore_sigma=float(config.explore_sigma))

    def validate(self) -> "TeacherHyperparams":
        """Raise ValueError naming the field for concrete values outside their valid range."""
        from envs.core import check_ranges

        check_ranges(self, {name: self.RANGES[name] for name in self.names()})
        return self

    def as_arrays(self):
        return self.validate().replace(**{f: jnp.asarray(getattr(self, f), jnp.float32) for f in self.names()})

    @classmethod
    def stack(cls, items: list) -> "TeacherHyperparams":
        """A batch (leading axis) of hyperparameter sets, ready for ``jax.vmap``."""
        items = [h.validate() for h in items]
        return cls(**{f: jnp.asarray([getattr(h, f) for h in items], jnp.float32) for f in cls.names()})


# ---- the method ------------------------------------------------------------------------------


@struct.dataclass
class HierarchicalState:
    hparams: Any  # the method's hyperparameter pytree (TeacherHyperparams or a subclass)
    ddpg: DDPGState
    real: RingBuffer  # B_real
    synth: Any  # the synthesiser's state (SHED: SynthState), None without one
    s: jax.Array  # [m] current teacher state (raw mean returns)
    t: jax.Array  # int32 step within the teacher episode
    pending_eval_steps: jax.Array  # int32 eval env steps of begin_episode, charged to the next step
    eval_key: Any = None  # a teacher episode's evaluation key, for teachers that reuse it (common random numbers)


def _longest(info) -> jax.Array:
    """The longest episode of an evaluation (``info["lengths"]``, [levels, episodes]) as int32."""
    return jnp.max(info["lengths"]).astype(jnp.int32)


@struct.dataclass
class Experience:
    """One student's part of a budget step (``HierarchicalTeacher.experience``)."""

    transition: Transition  # (s, u, r, s', done) as the teacher stores it (t/T in s and s' if on)
    s_next: jax.Array  # [m] the student's new performance vector (raw mean returns)
    levels: jax.Array  # [L, d] the levels of the step
    played: jax.Array  # [L] bool, which of them the student trained on
    ppo: Any  # the PPO metrics, mean over the step's updates
    env_steps_eval: jax.Array  # int32 evaluation env steps (with begin_episode's, pending)
    eval_longest: jax.Array  # int32 the longest episode of the evaluation that measured s' (its sequential steps)
    state_noise: jax.Array  # the noise SD of s' (NaN without ``state_noise_check``)
    reward_checks: jax.Array  # [3] the reward again, crossed, crossed back (NaN without ``reward_noise_check``)
    extras: dict  # a variant's ``extra_info``


@struct.dataclass
class Learned:
    """What the teacher's learning reports (``HierarchicalTeacher.learn``)."""

    td_heldout: jax.Array  # the critic's |TD error| on each new transition before any update
    real_size: jax.Array  # |B_real|
    syn_size: jax.Array  # |B_syn| (0 without a synthesiser)
    branch: jax.Array  # DDPG updates: 0 none, 1 real-only, 2 mixed
    synth_loss: jax.Array  # the synthesiser's mean diffusion loss (NaN when it did not train)
    synth_heldout: jax.Array  # its loss on the step's new transitions before training on them (NaN likewise)


def evaluation_levels(env, config: TeacherConfig):
    """(params with leading m, max_steps for evaluation) of the teacher's evaluation set."""
    params, cap = _evaluation_levels(env, config)
    return params, (config.eval_max_steps or cap)


def _evaluation_levels(env, config: TeacherConfig):
    return evaluation_set(env, config.eval_set, config.num_eval_levels)  # the env's own set (env.ued)


def at_bound_fraction(space, vecs, weights=None, tol: float = 0.01) -> jax.Array:
    """Fraction of the parameters in ``vecs`` [L, d] within ``tol`` of the range of a bound of the box ``space``.

    Dimensions with an empty range (low = high) are left out; ``weights`` [L] (e.g. which levels were
    played) weight the rows, all 1 when None.
    """
    low, high = jnp.asarray(space.low, jnp.float32), jnp.asarray(space.high, jnp.float32)
    span = high - low
    near = ((vecs - low) <= tol * span) | ((high - vecs) <= tol * span)
    w = jnp.ones(vecs.shape[:1], jnp.float32) if weights is None else jnp.asarray(weights, jnp.float32)
    cell = w[:, None] * (span > 0).astype(jnp.float32)[None, :]
    return jnp.sum(cell * near) / jnp.maximum(jnp.sum(cell), 1.0)


def buffer_zscore(r, buf: RingBuffer, eps: float = 1e-6) -> jax.Array:
    """``r`` z-scored with the mean and std of the rewards held in ``buf`` (its valid entries)."""
    valid = (jnp.arange(buf.capacity) < buf.count).astype(jnp.float32)
    n = jnp.maximum(jnp.sum(valid), 1.0)
    mean = jnp.sum(valid * buf.data.r) / n
    std = jnp.sqrt(jnp.sum(valid * (buf.data.r - mean) ** 2) / n)
    return (r - mean) / (std + eps)


def noise_sd(s_a, s_b) -> jax.Array:
    """SD of one evaluation from two independent ones of the same student: sqrt(mean((s_a - s_b)^2) / 2)."""
    return jnp.sqrt(jnp.mean((s_a - s_b) ** 2) / 2.0)


def teacher_dims(env, config: TeacherConfig) -> tuple[int, int]:
    """(state_dim, action_dim n * d) of the DDPG teacher: m evaluation levels (+ 1 for t/T), n levels of the box Θ."""
    return config.num_eval_levels + int(config.time_in_state), config.num_levels * teacher_space(env, config.low, config.high).dim


@dataclasses.dataclass(frozen=True)
class HierarchicalTeacher:
    """A DDPG teacher over performance vectors, with an optional synthesiser (see the module doc).

    ``synthesiser``: None (h-MDP) or e.g. a ``DiffusionSynthesiser`` sized by ``teacher_dims``.
    ``hparams_class``: the hyperparameter pytree; its defaults come from ``config``.
    ``eval_levels``: optional explicit evaluation levels (params, leading axis m), e.g. for small envs.
    """

    env: Any
    student: Any
    config: TeacherConfig = HMDPConfig()
    name: str = "hmdp"
    eval_levels: Any = None
    synthesiser: Any = None
    hparams_class: type = TeacherHyperparams

    def __post_init__(self):
        cfg = self.config
        n, e = cfg.num_levels, self.student.config.num_envs
        if self.levels_per_slot_group and e % n:
            raise ValueError(f"{self.name}: the student's num_envs ({e}) must be a multiple of num_levels ({n})")
        codec = LevelCodec(teacher_space(self.env, cfg.low, cfg.high))
        if self.eval_levels is None:
            eval_params, eval_max = evaluation_levels(self.env, cfg)
        else:
            eval_params, eval_max = self.eval_levels, cfg.eval_max_steps
            m = jax.tree_util.tree_leaves(eval_params)[0].shape[0]
            if m != cfg.num_eval_levels:
                raise ValueError(f"{self.name}: {m} evaluation levels given but num_eval_levels={cfg.num_eval_levels}")
        m, da = self.dims()
        if self.synthesiser is not None:
            sc = self.synthesiser.model.config
            if (sc.state_dim, sc.action_dim) != (m, da):
                raise ValueError(f"{self.name}: the synthesiser models (s, u) of sizes ({sc.state_dim}, {sc.action_dim}), "
                                 f"the teacher's are ({m}, {da})")
        teacher = self.make_teacher(m, da)
        for k, v in dict(codec=codec, eval_params=eval_params, eval_max=eval_max, teacher=teacher,
                         reward_fn=make_reward_fn(cfg.reward), state_dim=m, action_dim=da).items():
            object.__setattr__(self, k, v)

    # ---- what a variant of this teacher may change (shed_jax.methods.learning_teacher does) --------

    #: whether slot j trains on level j % num_levels (so num_envs must be a multiple of num_levels)
    levels_per_slot_group: ClassVar[bool] = True

    def dims(self) -> tuple[int, int]:
        """(state_dim, action_dim) of the DDPG teacher."""
        return teacher_dims(self.env, self.config)

    def make_teacher(self, m: int, da: int) -> DDPGTeacher:
        """The DDPG teacher with B_real [official code settings from the config]."""
        cfg = self.config
        ddpg = make_ddpg(DDPGConfig(m, da, actor_lr=cfg.actor_lr, critic_lr=cfg.critic_lr, explore_sigma=cfg.explore_sigma,
                                    reward_norm=cfg.reward_norm == "batch"))
        return DDPGTeacher(ddpg, capacity=cfg.real_capacity, batch_size=cfg.ddpg_batch, threshold=cfg.ddpg_threshold,
                           state_scale=cfg.state_scale)

    def train_on_action(self, keys, sstate, u):
        """The budget step's student training on the levels of action u ->
        (sstate, level vectors [L, d], played [L] bool, PPO metrics). h-MDP: level j is point j of u
        (n points of Θ in [-1, 1]^d), slot i trains on level i % n for C updates. ``keys``: (seed, train)."""
        cfg = self.config
        k_seed, k_train = keys
        vecs = self.codec.space.from_unit(u.reshape(cfg.num_levels, self.codec.dim))
        sstate, ppo = self.student.train(sstate, k_train, self.codec.to_params(vecs, new_seeds(k_seed, cfg.num_levels)),
                                         cfg.updates_per_step)
        return sstate, vecs, jnp.ones((cfg.num_levels,), bool), ppo

    def evaluation_key(self, mstate, key):
        """The key of this step's evaluation of s' (a fresh one; a variant may reuse the episode's)."""
        return key

    def extra_info(self, u, vecs, played) -> dict:
        """Entries a variant adds to the step's ``extras``."""
        return {}

    # ---- hyperparameters -------------------------------------------------------------------

    @property
    def hparam_names(self) -> tuple[str, ...]:
        """The dynamic hyperparameters of this method (a sweep's shared-compile keys)."""
        return self.hparams_class.names()

    @property
    def default_hparams(self):
        """The config's values as a hyperparameter pytree of Python floats."""
        return self.hparams_class.from_config(self.config)

    def _check_hparams(self, hparams):
        if type(hparams) is not self.hparams_class:
            raise TypeError(f"{self.name}: hparams must be a {self.hparams_class.__name__}, got {type(hparams).__name__}")
        return hparams.validate()

    def with_hparams(self, mstate: HierarchicalState, hparams) -> HierarchicalState:
        """``mstate`` with ``hparams`` in place of its hyperparameters (optimiser states synced).

        ``with_hparams(init(key), h)`` equals ``init(key, h)``: nothing random depends on them.
        """
        hp = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), self._check_hparams(hparams))
        return mstate.replace(hparams=hp, ddpg=self.teacher.ddpg.with_learning_rates(mstate.ddpg, hp.actor_lr, hp.critic_lr))

    def reward_fn_for(self, eta) -> Any:
        """``(s, a, s') -> R`` with a dynamic eta (the config's reward form and guards otherwise).

        For the paper forms R = gain - eta * cv; the gain comes from the config's reward with eta = 0,
        so this gives the same float32 numbers as ``make_reward_fn`` with that eta.
        """
        rc = self.config.reward
        if rc.form == "code_mean":
            fn = self.reward_fn
        else:
            gain_fn = make_reward_fn(dataclasses.replace(rc, eta=0.0))
            fn = lambda s, a, s_next: gain_fn(s, a, s_next) - eta * coefficient_of_variation(s, s_next, rc.cv_guard, rc.cv_clip)
        if not self.config.time_in_state:
            return fn
        m = self.config.num_eval_levels  # the reward reads the performance part, not t/T
        return lambda s, a, s_next: fn(s[..., :m], a, s_next[..., :m])

    def teacher_state(self, s, t):
        """The state the teacher acts on and stores: s [m], or [s, state_scale * t/T] with ``time_in_state``."""
        cfg = self.config
        if not cfg.time_in_state:
            return s
        frac = jnp.asarray(t, jnp.float32) / cfg.budget_steps * cfg.state_scale
        return jnp.concatenate([s, frac[None]], axis=-1)

    # ---- evaluation ------------------------------------------------------------------------

    def performance(self, key, sstate):
        """s = mean return per evaluation level [m], and the env steps it cost."""
        return self.performance_with_longest(key, sstate)[:2]

    def performance_with_longest(self, key, sstate):
        """``performance`` and its longest episode (steps; an episode cut at the step limit counts the
        limit): the rollout stops once every row has ended, so on a simulator paid by the sequential
        step this is what the evaluation costs."""
        rets, info = self.student.evaluate_with_info(sstate, key, self.eval_params, self.config.num_eval_episodes, self.eval_max)
        return rets.mean(axis=-1), jnp.asarray(info["env_steps"], jnp.int32), _longest(info)

    def performance_and_test(self, key, sstate, test: EvalRequest):
        """``performance_with_longest`` plus the loop's test set as one rollout: (s, env steps, longest
        episode of the teacher's rows, test returns [n, E]).

        The test returns are NaN when ``test.run`` is false. A traced ``test.run`` (the loop's
        schedule) makes the test rows an inactive request of the same rollout on the steps without
        a test (``PPOStudent.evaluate_many``): they step beside the teacher's rows but record
        nothing and end the rollout no later, so the program holds one evaluation, not one per
        branch of a ``lax.cond`` (on the 2-D walker each is a copy of the physics to compile), and
        the teacher's rows are computed in the same batch on every step. A Python False runs the
        teacher's evaluation alone. Every row's keys are drawn as ``performance(key, sstate)`` and a
        separate test evaluation with ``test.key`` draw them; the results are theirs where the
        backend computes a row the same at any batch size.
        """
        cfg = self.config
        n_test = jax.tree_util.tree_leaves(test.levels)[0].shape[0]
        steps = jnp.int32(self.student.eval_env_steps(cfg.num_eval_levels, cfg.num_eval_episodes, self.eval_max))
        if test.run is False:
            s, _, longest = self.performance_with_longest(key, sstate)
            return s, steps, longest, jnp.full((n_test, test.num_episodes), jnp.nan, jnp.float32)
        (rets, info), (test_rets, _) = self.student.evaluate_many(
            sstate, [(key, self.eval_params, cfg.num_eval_episodes, self.eval_max),
                     (test.key, test.levels, test.num_episodes, test.max_steps, test.run)])
        if test.run is not True:
            test_rets = jnp.where(test.run, test_rets, jnp.nan)
        return rets.mean(axis=-1), steps, _longest(info), test_rets

    # ---- interface -------------------------------------------------------------------------

    def init(self, key: jax.Array, hparams=None) -> HierarchicalState:
        """Fresh teacher state; ``hparams`` overrides the config's hyperparameters (``default_hparams``)."""
        hparams = self.default_hparams if hparams is None else hparams
        self._check_hparams(hparams)  # before building anything, so a bad value fails fast
        k_ddpg, k_synth = jax.random.split(key)
        ddpg, real = self.teacher.init(k_ddpg)
        state = HierarchicalState(
            hparams=self.default_hparams,
            ddpg=ddpg,
            real=real,
            synth=None if self.synthesiser is None else self.synthesiser.init(k_synth),
            s=jnp.zeros((self.config.num_eval_levels,), jnp.float32),
            t=jnp.int32(0),
            pending_eval_steps=jnp.int32(0),
        )
        return self.with_hparams(state, hparams)

    def begin_episode(self, key: jax.Array, mstate: HierarchicalState, sstate):
        s0, steps = self.performance(key, sstate)
        return mstate.replace(s=s0, t=jnp.int32(0), pending_eval_steps=steps), sstate

    def step(self, key: jax.Array, mstate: HierarchicalState, sstate):
        return self._step(key, mstate, sstate, None)[:3]

    @property
    def fuses_test_eval(self) -> bool:
        """Whether the loop may call ``step_with_test``: the student runs evaluations as one rollout."""
        return hasattr(self.student, "evaluate_many")

    def step_with_test(self, key: jax.Array, mstate: HierarchicalState, sstate, test: EvalRequest):
        """``step`` whose evaluation also runs the loop's test set (``methods.base``): one rollout."""
        return self._step(key, mstate, sstate, test)

    def _step(self, key, mstate: HierarchicalState, sstate, test: EvalRequest | None):
        k_act, k_seed, k_train, k_eval, k_synth, k_ddpg = jax.random.split(key, 6)
        sstate, exp, test_rets = self.experience((k_act, k_seed, k_train, k_eval), mstate, sstate, test)
        mstate, learned = self.learn((k_synth, k_ddpg), mstate, exp.transition)
        mstate = mstate.replace(s=exp.s_next, t=mstate.t + 1, pending_eval_steps=jnp.int32(0))
        return mstate, sstate, self.step_info(exp, learned), test_rets

    # ---- the parts of a step: one student's experience, the teacher's learning, the record ----------

    def experience(self, keys, mstate: HierarchicalState, sstate, test: EvalRequest | None):
        """One student's part of a budget step -> (sstate, :class:`Experience`, test returns or None):
        act on its state ``mstate.s`` (1.), train it (2.), evaluate s' (3.) and reward the transition (4.).

        Reads the teacher (``mstate.ddpg``, hyperparameters, ``t``) and changes nothing of it, so
        several students may take this part under one teacher (``shed_jax.methods.parallel_students``).
        ``keys``: (act, seed, train, eval).
        """
        cfg, hp = self.config, mstate.hparams
        k_act, k_seed, k_train, k_eval = keys
        ts = self.teacher_state(mstate.s, mstate.t)
        u = self.teacher.act(mstate.ddpg, ts, k_act, hp.explore_sigma)
        before = sstate
        sstate, vecs, played, ppo = self.train_on_action((k_seed, k_train), sstate, u)
        k_eval = self.evaluation_key(mstate, k_eval)
        if test is None:
            s_next, eval_steps, longest = self.performance_with_longest(k_eval, sstate)
            test_rets = None
        else:
            s_next, eval_steps, longest, test_rets = self.performance_and_test(k_eval, sstate, test)
        ts_next = self.teacher_state(s_next, mstate.t + 1)
        r = self.reward_fn_for(hp.eta)(ts, u, ts_next)
        done = (mstate.t == cfg.budget_steps - 1).astype(jnp.float32)
        if cfg.state_noise_check:  # the same student evaluated again with another key
            s_again, again_steps = self.performance(jax.random.fold_in(k_eval, 1), sstate)
            state_noise, eval_steps = noise_sd(s_next, s_again), eval_steps + again_steps
        else:
            state_noise = jnp.float32(jnp.nan)
        if cfg.reward_noise_check:  # s (the student before training) and s' again, with a second key
            k2 = jax.random.fold_in(k_eval, 2)
            # the two students side by side: one rollout's sequential steps, not two
            pair = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), before, sstate)
            (s2, s_next2), n_pair = jax.vmap(lambda st: self.performance(k2, st))(pair)
            ts2, ts_next2 = self.teacher_state(s2, mstate.t), self.teacher_state(s_next2, mstate.t + 1)
            reward = self.reward_fn_for(hp.eta)
            checks = jnp.stack([reward(ts2, u, ts_next2), reward(ts, u, ts_next2), reward(ts2, u, ts_next)])
            eval_steps = eval_steps + n_pair.sum()
        else:
            checks = jnp.full((3,), jnp.nan, jnp.float32)
        exp = Experience(transition=Transition(s=ts, u=u, r=r, s_next=ts_next, done=done), s_next=s_next, levels=vecs,
                         played=played, ppo=mean_metrics(ppo), env_steps_eval=eval_steps + mstate.pending_eval_steps,
                         eval_longest=longest,
                         state_noise=state_noise, reward_checks=checks, extras=self.extra_info(u, vecs, played))
        return sstate, exp, test_rets

    def learn(self, keys, mstate: HierarchicalState, transition: Transition) -> tuple[HierarchicalState, Learned]:
        """The teacher's part of a budget step -> (mstate with new DDPG, buffers and synthesiser, :class:`Learned`):
        store ``transition`` (one, or a batch with a leading axis) in B_real, the held-out TD error
        of each, the synthesiser's ``grow`` (5.) and the DDPG updates (6.). ``keys``: (synth, ddpg)."""
        cfg, hp = self.config, mstate.hparams
        k_synth, k_ddpg = keys
        real = self.teacher.store(mstate.real, transition)
        ddpg = self.teacher.ddpg.with_learning_rates(mstate.ddpg, hp.actor_lr, hp.critic_lr)
        # diagnostics: the critic's TD error on the new transition, before any update has seen it, its
        # reward normalised as the critic's batches are (B_real's statistics stand in for a batch's)
        r_seen = buffer_zscore(transition.r, real) if cfg.reward_norm == "batch" else transition.r
        td_heldout = self.teacher.td_error(ddpg, transition, r_seen)
        if self.synthesiser is None:
            synth, synth_loss, synth_heldout, syn_size = None, jnp.float32(jnp.nan), jnp.float32(jnp.nan), jnp.int32(0)
            ddpg, branch = self.teacher.updates(k_ddpg, ddpg, real)
        else:
            policy = lambda k, s, sigma, st=ddpg: self.teacher.act(st, s, k, sigma)  # before this step's updates
            synth, synth_loss, synth_heldout = self.synthesiser.grow(k_synth, mstate.synth, real, self.reward_fn_for(hp.eta),
                                                                     transition, policy)
            ddpg, branch = self.synthesiser.updates(k_ddpg, self.teacher, ddpg, real, synth, hp.psi, synth_heldout)
            syn_size = synth.syn.count
        learned = Learned(td_heldout=td_heldout, real_size=real.count, syn_size=syn_size, branch=branch,
                          synth_loss=synth_loss, synth_heldout=synth_heldout)
        return mstate.replace(ddpg=ddpg, real=real, synth=synth), learned

    def step_info(self, exp: Experience, learned: Learned) -> StepInfo:
        """The step's record from one student's experience and the teacher's learning."""
        return StepInfo(
            levels=exp.levels,
            env_steps_train=jnp.int32(self.config.updates_per_step * self.student.env_steps_per_update),
            env_steps_eval=exp.env_steps_eval,
            teacher_reward=exp.transition.r,
            num_new_levels=exp.played.sum().astype(jnp.int32),
            extras={  # the same keys with or without a synthesiser (0 and NaN without)
                "ppo": exp.ppo,
                "teacher_state": exp.s_next,
                "real_size": learned.real_size,
                "syn_size": learned.syn_size,
                "ddpg_branch": learned.branch,  # 0 none, 1 real-only, 2 mixed
                "diffusion_loss": learned.synth_loss,
                "diffusion_heldout_loss": learned.synth_heldout,
                "at_bound_fraction": at_bound_fraction(self.codec.space, exp.levels, exp.played),
                "td_error_heldout": learned.td_heldout,
                # the s' evaluation's sequential steps: on a latency-bound simulator, most of the step's time
                "eval_longest_episode": exp.eval_longest,
                "state_noise_sd": exp.state_noise,
                "reward_again": exp.reward_checks[..., 0],
                "reward_crossed": exp.reward_checks[..., 1],
                "reward_crossed_back": exp.reward_checks[..., 2],
                **exp.extras,
            },
        )


def make_hmdp(env, student, config: Any = None, eval_levels=None, name: str = "hmdp") -> HierarchicalTeacher:
    """h-MDP (docs/design.md §8.7): the DDPG teacher alone. ``config``: None, a dict or an :class:`HMDPConfig`."""
    return HierarchicalTeacher(env, student, coerce(HMDPConfig, config, f"method {name!r}"), name=name, eval_levels=eval_levels)
