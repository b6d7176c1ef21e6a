"""A hierarchical teacher built to learn (issue #26): ``hmdp-x`` (DDPG teacher) and ``shed-x`` (plus SHED's diffusion synthesiser).

The paper-faithful h-MDP and SHED (``shed_jax.methods.hierarchical``, ``shed_jax.methods.shed``) make
students worse on the lander (docs/results.md, "A teacher that learns"). This method is composed of
the same parts (``DDPGTeacher``, ``DiffusionSynthesiser``, the evaluation of the teacher state) and
changes, each behind a switch of :class:`HMDPXConfig` whose default is the chosen teacher:

* ``action='box'``: the action is a sub-box of Θ, not n points: per parameter a centre c = u_c and a
  half-width w = 2^{u_w} in the unit cube, the box [max(-1, c - w), min(1, c + w)]; levels are drawn
  uniformly from it. With ``actor_out_init='zeros'`` the untrained actor gives u = 0, the whole Θ:
  the untrained teacher is domain randomisation. The box is never narrower than half of Θ's range
  per parameter, so a saturated actor cannot send every level to a bound. ``'levels'``: h-MDP's n points.
* ``level_switch='episode'``: each student slot takes a fresh level from the action when its
  episode ends (``student.rollout(next_levels=)``, as DR's ``level_switch='episode'``); no episode
  is cut. ``'block'``: h-MDP's, n levels, every slot reset at each budget step onto level j % n.
* ``crn``: s and s' are evaluated with the same keys (one evaluation key per teacher episode), so
  s' - s measures the student's change, not the evaluation's noise.
* the reward: R = sum_i (s'_i - s_i) / ``reward_scale`` (``signed_sum`` with eta = 0), a signed
  improvement with a fixed scale, not z-scored per batch (``reward_norm='none'``); t/T in the state.
* DDPG against saturation: ``actor_lr`` 1e-4, ``tau`` 0.01, ``preact_penalty`` on the pre-tanh
  actor outputs.

Diagnostics as the paper teacher's (``at_bound_fraction`` over the levels played, ``td_error_heldout``,
``state_noise_sd``). The hyperparameter pytrees are the paper teacher's (``TeacherHyperparams``,
``SHEDHyperparams``), so sweeps over ``actor_lr``, ``explore_sigma``, ... work unchanged.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar, Literal

import jax
import jax.numpy as jnp
from flax import struct

from shed_jax.levels import LevelCodec, new_seeds, teacher_space
from shed_jax.configs import coerce
from shed_jax.methods.base import StepInfo, mean_metrics
from shed_jax.methods.hierarchical import (
    HierarchicalTeacher,
    TeacherConfig,
    TeacherHyperparams,
    at_bound_fraction,
    buffer_zscore,
    evaluation_levels,
    noise_sd,
)
from shed_jax.methods.shed import SHEDConfig, SHEDHyperparams
from shed_jax.teacher.buffers import RingBuffer, Transition
from shed_jax.teacher.ddpg import DDPGConfig, DDPGState, make_ddpg
from shed_jax.teacher.ddpg_teacher import DDPGTeacher
from shed_jax.teacher.diffusion import DiffusionConfig, make_diffusion
from shed_jax.teacher.reward import RewardConfig, make_reward_fn
from shed_jax.teacher.synthesiser import DiffusionSynthesiser

@dataclasses.dataclass(frozen=True)
class HMDPXConfig(TeacherConfig):
    """``hmdp-x``: the paper teacher's settings with this teacher's defaults, and its switches (module doc)."""

    time_in_state: bool = True
    reward_norm: Literal["batch", "none"] = "none"
    reward: RewardConfig = RewardConfig(form="signed_sum", eta=0.0)
    reward_scale: float = 100.0  # R is divided by this fixed scale
    actor_lr: float = 1e-4
    action: Literal["box", "levels"] = "box"
    level_switch: Literal["episode", "block"] = "episode"
    crn: bool = True
    tau: float = 0.01
    preact_penalty: float = 0.01
    actor_out_init: Literal["lecun", "zeros"] = "zeros"
    ddpg_updates: int = 2  # DDPG updates per budget step once |B_real| > ddpg_threshold (without a synthesiser)

    POSITIVE: ClassVar[tuple] = TeacherConfig.POSITIVE + ("ddpg_updates",)

    def __post_init__(self):
        super().__post_init__()
        name = type(self).__name__
        if not isinstance(self.crn, bool):
            raise ValueError(f"{name}.crn must be True or False, got {self.crn!r}")
        if not (isinstance(self.reward_scale, (int, float)) and math.isfinite(self.reward_scale) and self.reward_scale > 0):
            raise ValueError(f"{name}.reward_scale must be a finite number > 0, got {self.reward_scale!r}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"{name}.tau must lie in (0, 1], got {self.tau!r}")
        if not (isinstance(self.preact_penalty, (int, float)) and self.preact_penalty >= 0):
            raise ValueError(f"{name}.preact_penalty must be a number >= 0, got {self.preact_penalty!r}")


@dataclasses.dataclass(frozen=True)
class SHEDXConfig(HMDPXConfig, SHEDConfig):
    """``shed-x``: ``hmdp-x``'s settings plus SHED's synthesiser (B_real of 2,048, psi, B_syn, thresholds)."""

    real_capacity: int = 2048  # SHED's (HMDPXConfig's fields, TeacherConfig's default included, come later in the MRO)

    POSITIVE: ClassVar[tuple] = SHEDConfig.POSITIVE + ("ddpg_updates",)


@struct.dataclass
class LearningState:
    hparams: Any
    ddpg: DDPGState
    real: RingBuffer
    synth: Any  # the synthesiser's state, None without one
    s: jax.Array  # [m] current performance vector
    t: jax.Array  # int32 step within the teacher episode
    pending_eval_steps: jax.Array  # int32
    eval_key: jax.Array  # this teacher episode's evaluation key (used for every evaluation with crn)


def teacher_x_dims(env, config: HMDPXConfig) -> tuple[int, int]:
    """(state_dim, action_dim): m (+ 1 for t/T); 2 d for a box (centre and width per parameter), n d for points."""
    d = teacher_space(env, config.low, config.high).dim
    return config.num_eval_levels + int(config.time_in_state), (2 * d if config.action == "box" else config.num_levels * d)


@dataclasses.dataclass(frozen=True)
class LearningTeacher:
    """The learning teacher (module doc). Build with :func:`make_hmdp_x` or :func:`make_shed_x`."""

    env: Any
    student: Any
    config: HMDPXConfig = HMDPXConfig()
    name: str = "hmdp-x"
    eval_levels: Any = None
    synthesiser: Any = None
    hparams_class: type = TeacherHyperparams

    # shared with the paper teacher: they read only student, eval_params, eval_max, config, teacher, hparams_class
    performance = HierarchicalTeacher.performance
    performance_and_test = HierarchicalTeacher.performance_and_test
    teacher_state = HierarchicalTeacher.teacher_state
    hparam_names = HierarchicalTeacher.hparam_names
    default_hparams = HierarchicalTeacher.default_hparams
    _check_hparams = HierarchicalTeacher._check_hparams
    with_hparams = HierarchicalTeacher.with_hparams
    fuses_test_eval = HierarchicalTeacher.fuses_test_eval
    step = HierarchicalTeacher.step
    step_with_test = HierarchicalTeacher.step_with_test

    def __post_init__(self):
        cfg = self.config
        n, e = cfg.num_levels, self.student.config.num_envs
        if cfg.level_switch == "block" and e % n:
            raise ValueError(f"{self.name}: the student's num_envs ({e}) must be a multiple of num_levels ({n})")
        codec = LevelCodec(teacher_space(self.env, cfg.low, cfg.high))
        if self.eval_levels is None:
            eval_params, eval_max = evaluation_levels(self.env, cfg)
        else:
            eval_params, eval_max = self.eval_levels, cfg.eval_max_steps
            m = jax.tree_util.tree_leaves(eval_params)[0].shape[0]
            if m != cfg.num_eval_levels:
                raise ValueError(f"{self.name}: {m} evaluation levels given but num_eval_levels={cfg.num_eval_levels}")
        m, da = teacher_x_dims(self.env, cfg)
        if self.synthesiser is not None:
            sc = self.synthesiser.model.config
            if (sc.state_dim, sc.action_dim) != (m, da):
                raise ValueError(f"{self.name}: the synthesiser models (s, u) of sizes ({sc.state_dim}, {sc.action_dim}), "
                                 f"the teacher's are ({m}, {da})")
        ddpg = make_ddpg(DDPGConfig(m, da, actor_lr=cfg.actor_lr, critic_lr=cfg.critic_lr, explore_sigma=cfg.explore_sigma,
                                    reward_norm=cfg.reward_norm == "batch", tau=cfg.tau, preact_penalty=cfg.preact_penalty,
                                    actor_out_init=cfg.actor_out_init))
        teacher = DDPGTeacher(ddpg, capacity=cfg.real_capacity, batch_size=cfg.ddpg_batch, threshold=cfg.ddpg_threshold,
                              num_updates=cfg.ddpg_updates, state_scale=cfg.state_scale)
        for k, v in dict(codec=codec, eval_params=eval_params, eval_max=eval_max, teacher=teacher,
                         reward_fn=make_reward_fn(cfg.reward), state_dim=m, action_dim=da).items():
            object.__setattr__(self, k, v)

    def reward_fn_for(self, eta):
        """The paper teacher's ``(s, a, s') -> R`` (t/T stripped) divided by ``reward_scale``."""
        base = HierarchicalTeacher.reward_fn_for(self, eta)
        k = 1.0 / self.config.reward_scale
        return lambda s, a, s_next: base(s, a, s_next) * k

    # ---- levels from an action -------------------------------------------------------------

    def box(self, u):
        """(lo, hi) in the unit cube [-1, 1]^d of the box action u [2 d]."""
        d = self.codec.dim
        c, w = u[:d], 2.0 ** u[d:]
        return jnp.maximum(-1.0, c - w), jnp.minimum(1.0, c + w)

    def draw(self, key, u, count: int):
        """``count`` levels from action u -> (vectors [count, d] in Θ, params). A box: uniform in it;
        points: level j is point j % n."""
        d = self.codec.dim
        k_u, k_seed = jax.random.split(key)
        if self.config.action == "box":
            lo, hi = self.box(u)
            unit = lo + (hi - lo) * jax.random.uniform(k_u, (count, d))
        else:
            unit = u.reshape(self.config.num_levels, d)[jnp.arange(count) % self.config.num_levels]
        vecs = self.codec.space.from_unit(unit)
        return vecs, self.codec.to_params(vecs, new_seeds(k_seed, count))

    # ---- interface -------------------------------------------------------------------------

    def init(self, key: jax.Array, hparams=None) -> LearningState:
        hparams = self.default_hparams if hparams is None else hparams
        self._check_hparams(hparams)
        k_ddpg, k_synth = jax.random.split(key)
        ddpg, real = self.teacher.init(k_ddpg)
        state = LearningState(
            hparams=self.default_hparams, ddpg=ddpg, real=real,
            synth=None if self.synthesiser is None else self.synthesiser.init(k_synth),
            s=jnp.zeros((self.config.num_eval_levels,), jnp.float32), t=jnp.int32(0), pending_eval_steps=jnp.int32(0),
            eval_key=jax.random.PRNGKey(0),
        )
        return self.with_hparams(state, hparams)

    def begin_episode(self, key: jax.Array, mstate: LearningState, sstate):
        """s_0 (with this episode's evaluation key) and, with ``level_switch='episode'``, the fresh
        student's first levels, drawn from the teacher's noise-free action at s_0."""
        k_eval, k_lvl, k_assign = jax.random.split(key, 3)
        s0, steps = self.performance(k_eval, sstate)
        if self.config.level_switch == "episode":
            u0 = self.teacher.act(mstate.ddpg, self.teacher_state(s0, 0), None, 0.0)
            sstate = self.student.assign_levels(sstate, k_assign, self.draw(k_lvl, u0, self.student.config.num_envs)[1])
        return mstate.replace(s=s0, t=jnp.int32(0), pending_eval_steps=steps, eval_key=k_eval), sstate

    def _train(self, key, sstate, u):
        """The budget step's student training on levels from u -> (sstate, vecs [L, d], played [L], PPO metrics)."""
        cfg, student = self.config, self.student
        k_lvl, k_train = jax.random.split(key)
        if cfg.level_switch == "block":
            vecs, params = self.draw(k_lvl, u, cfg.num_levels)
            sstate, ppo = student.train(sstate, k_train, params, cfg.updates_per_step)
            return sstate, vecs, jnp.ones((cfg.num_levels,), bool), ppo
        e = student.config.num_envs

        def one_update(s, k):  # slot j takes level j of a fresh draw when its episode ends
            k_lvl, k_roll, k_upd = jax.random.split(k, 3)
            vecs, params = self.draw(k_lvl, u, e)
            s, traj = student.rollout(s, k_roll, next_levels=params)
            s, metrics = student.update(s, k_upd, traj)
            return s, (vecs, traj.dones.any(axis=0), metrics)

        c = cfg.updates_per_step
        sstate, (vecs, used, ppo) = jax.lax.scan(one_update, sstate, jax.random.split(k_train, c))
        return sstate, vecs.reshape(c * e, -1), used.reshape(c * e), ppo

    def _step(self, key, mstate: LearningState, sstate, test):
        cfg, student, hp = self.config, self.student, mstate.hparams
        reward_fn = self.reward_fn_for(hp.eta)
        k_act, k_train, k_eval, k_synth, k_ddpg, k_noise = jax.random.split(key, 6)
        eval_key = mstate.eval_key if cfg.crn else k_eval
        ts = self.teacher_state(mstate.s, mstate.t)
        u = self.teacher.act(mstate.ddpg, ts, k_act, hp.explore_sigma)
        sstate, vecs, played, ppo = self._train(k_train, sstate, u)
        if test is None:
            s_next, eval_steps = self.performance(eval_key, sstate)
            test_rets = None
        else:
            s_next, eval_steps, test_rets = self.performance_and_test(eval_key, sstate, test)
        ts_next = self.teacher_state(s_next, mstate.t + 1)
        r = reward_fn(ts, u, ts_next)
        done = (mstate.t == cfg.budget_steps - 1).astype(jnp.float32)
        transition = Transition(s=ts, u=u, r=r, s_next=ts_next, done=done)
        real = self.teacher.store(mstate.real, transition)
        ddpg = self.teacher.ddpg.with_learning_rates(mstate.ddpg, hp.actor_lr, hp.critic_lr)
        td_heldout = self.teacher.td_error(ddpg, transition, buffer_zscore(r, real) if cfg.reward_norm == "batch" else r)
        if cfg.state_noise_check:
            s_again, again_steps = self.performance(k_noise, sstate)
            state_noise, eval_steps = noise_sd(s_next, s_again), eval_steps + again_steps
        else:
            state_noise = jnp.float32(jnp.nan)
        if self.synthesiser is None:
            synth, synth_loss, syn_size = None, jnp.float32(jnp.nan), jnp.int32(0)
            ddpg, branch = self.teacher.updates(k_ddpg, ddpg, real)
        else:
            synth, synth_loss = self.synthesiser.grow(k_synth, mstate.synth, real, reward_fn)
            ddpg, branch = self.synthesiser.updates(k_ddpg, self.teacher, ddpg, real, synth, hp.psi)
            syn_size = synth.syn.count
        extras = {
            "ppo": mean_metrics(ppo),
            "teacher_state": s_next,
            "real_size": real.count,
            "syn_size": syn_size,
            "ddpg_branch": branch,
            "diffusion_loss": synth_loss,
            "at_bound_fraction": at_bound_fraction(self.codec.space, vecs, played),
            "td_error_heldout": td_heldout,
            "state_noise_sd": state_noise,
            "action_abs_mean": jnp.mean(jnp.abs(u)),
        }
        if cfg.level_switch == "episode":
            extras["levels_trained_mask"] = played
        if cfg.action == "box":  # the box's width per parameter, as a fraction of Θ's range
            lo, hi = self.box(u)
            extras["box_width"] = (hi - lo) / 2.0
        info = StepInfo(
            levels=vecs,
            env_steps_train=jnp.int32(cfg.updates_per_step * student.env_steps_per_update),
            env_steps_eval=eval_steps + mstate.pending_eval_steps,
            teacher_reward=r,
            num_new_levels=played.sum().astype(jnp.int32),
            extras=extras,
        )
        mstate = mstate.replace(ddpg=ddpg, real=real, synth=synth, s=s_next, t=mstate.t + 1, pending_eval_steps=jnp.int32(0))
        return mstate, sstate, info, test_rets


def make_hmdp_x(env, student, config: Any = None, eval_levels=None, name: str = "hmdp-x") -> LearningTeacher:
    """``hmdp-x``: the learning teacher without a synthesiser. ``config``: None, a dict or an :class:`HMDPXConfig`."""
    return LearningTeacher(env, student, coerce(HMDPXConfig, config, f"method {name!r}"), name=name, eval_levels=eval_levels)


def make_shed_x(env, student, config: Any = None, eval_levels=None, name: str = "shed-x") -> LearningTeacher:
    """``shed-x``: the learning teacher with SHED's diffusion synthesiser. ``config``: None, a dict or a :class:`SHEDXConfig`."""
    cfg = coerce(SHEDXConfig, config, f"method {name!r}")
    m, da = teacher_x_dims(env, cfg)
    model = make_diffusion(DiffusionConfig(m, da, lr=cfg.diffusion_lr, sampler=cfg.sampler, train_bc=cfg.syn_action == "bc",
                                           ema_decay=cfg.diffusion_ema))
    synthesiser = DiffusionSynthesiser(model, capacity=cfg.syn_capacity, train_threshold=cfg.diffusion_threshold,
                                       train_steps=cfg.diffusion_steps, num_syn=cfg.num_syn, mix_threshold=cfg.syn_threshold,
                                       syn_action=cfg.syn_action, syn_reward=cfg.syn_reward)
    return LearningTeacher(env, student, cfg, name=name, eval_levels=eval_levels, synthesiser=synthesiser,
                           hparams_class=SHEDHyperparams)
