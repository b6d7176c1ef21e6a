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
* DDPG against saturation: ``actor_lr`` 1e-5, ``tau`` 0.01, ``preact_penalty`` on the pre-tanh
  actor outputs, and TD3's ``twin_critics`` with ``actor_delay`` 2 (the best of the lander runs in
  docs/results.md; until 2026-11-27 the defaults were actor_lr 1e-4, one critic, no delay).
* ``students``: K students trained side by side under the one teacher, K transitions per budget
  step (``shed_jax.methods.parallel_students``); 1 (the default) is this teacher alone.
* ``shed-x``'s synthesiser, where it could help: ``syn_action='policy'`` (the default) draws
  synthetic actions from the current policy plus N(0, ``syn_sigma``²) noise instead of uniformly
  (SHED's ``'uniform'``), so B_syn covers the actions the critic is asked about; with uniform
  actions mixed from the start the lander's critic diverged (docs/results.md). ``syn_threshold``
  32 (the default; SHED's is 500) mixes from the start; ``syn_loss_bar`` allows mixed updates only
  while the diffusion model's loss on the step's new, unseen transitions is below the bar (the
  ``diffusion_heldout_loss`` diagnostic).

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

from shed_jax.configs import check_number, coerce
from shed_jax.levels import new_seeds, teacher_space
from shed_jax.methods.hierarchical import HierarchicalState, HierarchicalTeacher, TeacherConfig
from shed_jax.methods.parallel_students import ParallelStudents
from shed_jax.methods.shed import SHEDConfig, SHEDHyperparams, diffusion_synthesiser
from shed_jax.teacher.ddpg import DDPGConfig, make_ddpg
from shed_jax.teacher.ddpg_teacher import DDPGTeacher
from shed_jax.teacher.diffusion import SynAction
from shed_jax.teacher.reward import RewardConfig

@dataclasses.dataclass(frozen=True)
class HMDPXConfig(TeacherConfig):
    """``hmdp-x``: the paper teacher's settings with this teacher's defaults, and its switches (module doc)."""

    time_in_state: bool = True
    reward_norm: Literal["batch", "none"] = "none"
    reward: RewardConfig = RewardConfig(form="signed_sum", eta=0.0)
    reward_scale: float = 100.0  # R is divided by this fixed scale
    actor_lr: float = 1e-5
    action: Literal["box", "levels"] = "box"
    level_switch: Literal["episode", "block"] = "episode"
    crn: bool = True
    tau: float = 0.01
    preact_penalty: float = 0.01
    actor_out_init: Literal["lecun", "zeros"] = "zeros"
    ddpg_updates: int = 2  # DDPG updates per budget step once |B_real| > ddpg_threshold (without a synthesiser)
    twin_critics: bool = True  # TD3's clipped double Q (DDPGConfig.twin_critics)
    actor_delay: int = 2  # the actor and targets update every k-th DDPG update (DDPGConfig.actor_delay)
    students: int = 1  # K students under the one teacher, K transitions per budget step (methods.parallel_students)

    POSITIVE: ClassVar[tuple] = TeacherConfig.POSITIVE + ("ddpg_updates", "actor_delay", "students")

    def __post_init__(self):
        super().__post_init__()
        name = type(self).__name__
        for flag in ("crn", "twin_critics"):
            if not isinstance(getattr(self, flag), bool):
                raise ValueError(f"{name}.{flag} must be True or False, got {getattr(self, flag)!r}")
        check_number(self, "reward_scale", above=0)
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"{name}.tau must lie in (0, 1], got {self.tau!r}")
        check_number(self, "preact_penalty", at_least=0, finite=False)
        if self.students > self.real_capacity:
            raise ValueError(f"{name}.students must be <= real_capacity ({self.real_capacity}): a budget step stores "
                             f"one transition per student, got {self.students}")


@dataclasses.dataclass(frozen=True)
class SHEDXConfig(HMDPXConfig, SHEDConfig):
    """``shed-x``: ``hmdp-x``'s settings plus SHED's synthesiser (B_real of 2,048, psi, B_syn, thresholds)."""

    real_capacity: int = 2048  # SHED's (HMDPXConfig's fields, TeacherConfig's default included, come later in the MRO)
    syn_action: SynAction = "policy"  # synthetic actions around the current policy, not uniform (module doc)
    syn_threshold: int = 32  # mixed updates as soon as B_syn can fill a batch
    syn_sigma: float = 0.1  # syn_action='policy': noise SD around the policy's synthetic actions
    syn_loss_bar: float = math.inf  # mixed updates only while D's held-out loss is below this (inf: SHED's rule)

    POSITIVE: ClassVar[tuple] = SHEDConfig.POSITIVE + ("ddpg_updates", "actor_delay", "students")

    def __post_init__(self):
        super().__post_init__()
        check_number(self, "syn_sigma", at_least=0)
        check_number(self, "syn_loss_bar", above=0, finite=False)  # inf: no bar


def teacher_x_dims(env, config: HMDPXConfig) -> tuple[int, int]:
    """(state_dim, action_dim): m (+ 1 for t/T); 2 d for a box (centre and width per parameter), n d for points."""
    d = teacher_space(env, config.low, config.high).dim
    return config.num_eval_levels + int(config.time_in_state), (2 * d if config.action == "box" else config.num_levels * d)


@dataclasses.dataclass(frozen=True)
class LearningTeacher(HierarchicalTeacher):
    """The learning teacher (module doc): the paper teacher's step with its own action, level switching,
    evaluation keys and DDPG settings, for one student (``config.students`` is read by the builders).
    Build with :func:`make_hmdp_x` or :func:`make_shed_x`."""

    config: HMDPXConfig = HMDPXConfig()
    name: str = "hmdp-x"

    @property
    def levels_per_slot_group(self) -> bool:
        return self.config.level_switch == "block"

    def dims(self) -> tuple[int, int]:
        return teacher_x_dims(self.env, self.config)

    def make_teacher(self, m: int, da: int) -> DDPGTeacher:
        cfg = self.config
        ddpg = make_ddpg(DDPGConfig(m, da, actor_lr=cfg.actor_lr, critic_lr=cfg.critic_lr, explore_sigma=cfg.explore_sigma,
                                    reward_norm=cfg.reward_norm == "batch", tau=cfg.tau, preact_penalty=cfg.preact_penalty,
                                    actor_out_init=cfg.actor_out_init, twin_critics=cfg.twin_critics,
                                    actor_delay=cfg.actor_delay))
        return DDPGTeacher(ddpg, capacity=cfg.real_capacity, batch_size=cfg.ddpg_batch, threshold=cfg.ddpg_threshold,
                           num_updates=cfg.ddpg_updates, state_scale=cfg.state_scale)

    def reward_fn_for(self, eta):
        """The paper teacher's ``(s, a, s') -> R`` (t/T stripped) divided by ``reward_scale``."""
        base = HierarchicalTeacher.reward_fn_for(self, eta)
        k = 1.0 / self.config.reward_scale
        return lambda s, a, s_next: base(s, a, s_next) * k

    def evaluation_key(self, mstate, key):
        """With ``crn`` every evaluation of a teacher episode uses the episode's key (s and s' alike)."""
        return mstate.eval_key if self.config.crn else key

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

    def train_on_action(self, keys, sstate, u):
        """'block': the n levels drawn from u, slot i on level i % n (h-MDP's rule). 'episode': each
        update draws one level per slot from u, which the slot takes when its episode ends."""
        cfg, student = self.config, self.student
        k_lvl, k_train = keys
        if cfg.level_switch == "block":
            vecs, params = self.draw(k_lvl, u, cfg.num_levels)
            sstate, ppo = student.train(sstate, k_train, params, cfg.updates_per_step)
            return sstate, vecs, jnp.ones((cfg.num_levels,), bool), ppo
        e = student.config.num_envs

        def one_update(s, k):
            k_lvl, k_roll, k_upd = jax.random.split(k, 3)
            vecs, params = self.draw(k_lvl, u, e)
            s, traj = student.rollout(s, k_roll, next_levels=params)
            s, metrics = student.update(s, k_upd, traj)
            return s, (vecs, traj.dones.any(axis=0), metrics)

        c = cfg.updates_per_step
        sstate, (vecs, used, ppo) = jax.lax.scan(one_update, sstate, jax.random.split(k_train, c))
        return sstate, vecs.reshape(c * e, -1), used.reshape(c * e), ppo

    def extra_info(self, u, vecs, played) -> dict:
        extras = {"action_abs_mean": jnp.mean(jnp.abs(u))}
        if self.config.level_switch == "episode":
            extras["levels_trained_mask"] = played
        if self.config.action == "box":  # the box's width per parameter, as a fraction of Θ's range
            lo, hi = self.box(u)
            extras["box_width"] = (hi - lo) / 2.0
        return extras

    # ---- interface -------------------------------------------------------------------------

    def init(self, key: jax.Array, hparams=None) -> HierarchicalState:
        return super().init(key, hparams).replace(eval_key=jax.random.PRNGKey(0))

    def begin_episode(self, key: jax.Array, mstate: HierarchicalState, sstate):
        """s_0 (with this episode's evaluation key) and, with ``level_switch='episode'``, the fresh
        student's first levels, drawn from the teacher's noise-free action at s_0."""
        k_eval, k_lvl, k_assign = jax.random.split(key, 3)
        s0, steps = self.performance(k_eval, sstate)
        if self.config.level_switch == "episode":
            u0 = self.teacher.act(mstate.ddpg, self.teacher_state(s0, 0), None, 0.0)
            sstate = self.student.assign_levels(sstate, k_assign, self.draw(k_lvl, u0, self.student.config.num_envs)[1])
        return mstate.replace(s=s0, t=jnp.int32(0), pending_eval_steps=steps, eval_key=k_eval), sstate


def with_students(teacher: LearningTeacher):
    """The teacher for ``config.students`` students: itself for one, else a ``ParallelStudents`` of it
    (whose ``pool`` is the loop's student)."""
    k = teacher.config.students
    return teacher if k == 1 else ParallelStudents(teacher, k)


def make_hmdp_x(env, student, config: Any = None, eval_levels=None, name: str = "hmdp-x"):
    """``hmdp-x``: the learning teacher without a synthesiser. ``config``: None, a dict or an :class:`HMDPXConfig`."""
    cfg = coerce(HMDPXConfig, config, f"method {name!r}")
    return with_students(LearningTeacher(env, student, cfg, name=name, eval_levels=eval_levels))


def make_shed_x(env, student, config: Any = None, eval_levels=None, name: str = "shed-x"):
    """``shed-x``: the learning teacher with SHED's diffusion synthesiser. ``config``: None, a dict or a :class:`SHEDXConfig`."""
    cfg = coerce(SHEDXConfig, config, f"method {name!r}")
    return with_students(LearningTeacher(env, student, cfg, name=name, eval_levels=eval_levels,
                                         synthesiser=dataclasses.replace(diffusion_synthesiser(cfg, *teacher_x_dims(env, cfg)),
                                                                         syn_sigma=cfg.syn_sigma, loss_bar=cfg.syn_loss_bar),
                                         hparams_class=SHEDHyperparams))
