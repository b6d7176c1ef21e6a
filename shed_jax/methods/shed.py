"""SHED and h-MDP behind the UED method interface (docs/design.md §3): a DDPG teacher over performance vectors.

One budget step, top to bottom (all inside one jitted function, thresholds as ``lax.cond``):

1. u = clip(actor(s / scale) + N(0, sigma^2), -1, 1); levels theta_i = affine(u_i) into the box Θ.
2. Train the student ``updates_per_step`` PPO iterations on the n levels (slot j runs level j % n).
3. s' = mean return of ``num_eval_episodes`` episodes on each of the m fixed evaluation levels.
4. r = R(s, u, s') (``shed_jax.teacher.reward``); done = [t = T - 1]; store (s, u, r, s', done) in B_real.
5. SHED: if |B_real| > 64, train the diffusion model 250 steps and add 10 synthetic transitions to
   B_syn. h-MDP has no diffusion model.
6. DDPG: h-MDP 2 real updates if |B_real| > 32. SHED 2 mixed updates (24 real + 8 synthetic) if
   |B_syn| > 500 and both buffers > 32, else 3 real updates if |B_real| > 32 [official code].

Buffers hold raw performance vectors (returns); the DDPG networks see them divided by ``state_scale``
(the teacher sees s/100, docs/design.md §2) and the diffusion model normalises them itself. Rewards are
computed on raw returns; DDPG z-scores them per batch. The teacher's networks, the diffusion model
and both buffers persist across teacher episodes; ``begin_episode`` only evaluates the fresh student
to get s_0 and resets the step counter.

Static settings (shapes, thresholds, switches) live in the frozen :class:`SHEDConfig`; the teacher's
hyperparameters one may sweep (eta, psi, the DDPG learning rates, the exploration noise) live in a
:class:`SHEDHyperparams` pytree inside the method state, so a sweep over them is one ``vmap`` and one
compile (as ``PPOHyperparams`` for the student). ``method.init(key, hparams=None)`` takes overrides;
``method.with_hparams(mstate, hparams)`` swaps them into an existing state.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from shed_jax.levels import LevelCodec, evaluation_set, new_seeds, teacher_space
from shed_jax.methods.base import EvalRequest, StepInfo, mean_metrics
from shed_jax.teacher.buffers import (
    RingBuffer,
    Transition,
    buffer_add,
    buffer_add_many,
    buffer_init,
    buffer_sample,
    make_transition,
)
from shed_jax.teacher.ddpg import Actor, Critic, DDPGConfig, DDPGState, make_ddpg
from shed_jax.teacher.diffusion import DiffusionConfig, DiffusionState, make_diffusion
from shed_jax.teacher.reward import RewardConfig, coefficient_of_variation, make_reward_fn


@dataclasses.dataclass(frozen=True)
class SHEDConfig:
    """SHED / h-MDP settings; defaults are docs/design.md §3 / §10.2 (official thresholds) and §10.3 (lander)."""

    updates_per_step: int = 10  # C in PPO iterations
    num_levels: int = 5  # n (lander 5, walker 4)
    budget_steps: int = 20  # T: done = 1 on the T-th transition
    num_eval_episodes: int = 8  # E_eval
    eval_set: str = "official"  # lander: 'official' (code's 10) or 'paper' (covering, any m); walker: ladder
    num_eval_levels: int = 10  # m
    eval_max_steps: int | None = None  # override the evaluation episode cap (default: the set's max_steps)
    state_scale: float = 100.0  # the DDPG networks see s / state_scale
    reward: RewardConfig = RewardConfig()
    explore_sigma: float = 0.1  # default of SHEDHyperparams.explore_sigma
    actor_lr: float = 1e-3  # default of SHEDHyperparams.actor_lr (Adam) [official code]
    critic_lr: float = 1e-3  # default of SHEDHyperparams.critic_lr (Adam) [official code]
    ddpg_batch: int = 32
    real_capacity: int | None = None  # default 2048 (shed) / 10000 (hmdp)
    syn_capacity: int = 900
    psi: float = 0.75
    diffusion_threshold: int = 64  # train D once |B_real| > this
    diffusion_steps: int = 250
    num_syn: int = 10
    syn_threshold: int = 500  # mixed updates once |B_syn| > this
    ddpg_threshold: int = 32
    syn_action: str = "uniform"
    syn_reward: str = "recompute"
    sampler: str = "ancestral"
    diffusion_lr: float = 1e-3
    diffusion_ema: float = 0.0
    low: tuple | None = None  # Θ override
    high: tuple | None = None

    def __post_init__(self):
        for name in ("updates_per_step", "num_levels", "budget_steps", "num_eval_episodes", "num_eval_levels", "ddpg_batch",
                     "syn_capacity", "diffusion_steps", "num_syn"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"SHEDConfig.{name} must be a positive int, got {v!r}")
        if self.eval_set not in ("official", "paper"):
            raise ValueError(f"SHEDConfig.eval_set must be 'official' or 'paper', got {self.eval_set!r}")
        if not 0.0 <= self.psi <= 1.0:
            raise ValueError(f"SHEDConfig.psi must lie in [0, 1], got {self.psi}")
        for name in ("actor_lr", "critic_lr"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"SHEDConfig.{name} must be a finite number > 0, got {v!r}")
        if not (isinstance(self.explore_sigma, (int, float)) and math.isfinite(self.explore_sigma) and self.explore_sigma >= 0):
            raise ValueError(f"SHEDConfig.explore_sigma must be a finite number >= 0, got {self.explore_sigma!r}")
        if not self.state_scale > 0:
            raise ValueError(f"SHEDConfig.state_scale must be > 0, got {self.state_scale}")
        if self.real_capacity is not None and self.real_capacity < self.ddpg_batch:
            raise ValueError(f"SHEDConfig.real_capacity must be >= ddpg_batch, got {self.real_capacity}")


_HPARAM_RANGES = {
    # name: (low, high, low_inclusive, high_inclusive)
    "eta": (0.0, math.inf, True, False),
    "psi": (0.0, 1.0, True, True),
    "actor_lr": (0.0, math.inf, False, False),
    "critic_lr": (0.0, math.inf, False, False),
    "explore_sigma": (0.0, math.inf, True, False),
}


@struct.dataclass
class SHEDHyperparams:
    """Dynamic teacher hyperparameters: float scalars (or batches of them, for ``vmap``).

    eta:           weight of the coefficient of variation in the paper's reward forms
                   (R = gain - eta * cv). Ignored by ``RewardConfig(form='code_mean')``, which has no
                   eta. Used for real rewards and for recomputed synthetic rewards alike.
    psi:           real-data ratio of a mixed DDPG batch (SHED only; h-MDP never mixes). Implemented
                   as a *fixed split with a dynamic ratio*: each mixed update draws ``ddpg_batch``
                   candidates from each buffer and keeps the first floor(psi * ddpg_batch) real ones
                   and synthetic ones after them (a mask over a static batch), z-scoring the rewards
                   of both parts separately. This is the official code's layout (24 real + 8
                   synthetic for psi = 0.75, batch 32) for every psi, with no extra noise in the part
                   sizes; a per-sample Bernoulli(psi) mask would make the part sizes binomial (and
                   occasionally empty) and so change what the per-part reward z-scoring does.
    actor_lr, critic_lr: Adam learning rates of the DDPG actor and critic, held in
                   ``optax.inject_hyperparams`` optimiser states (written from here before every
                   update, so this pytree is the one source of truth).
    explore_sigma: std of the Gaussian exploration noise added to the actor's u in [-1, 1]^{n d}.

    Defaults come from a :class:`SHEDConfig` (``from_config``); ``as_arrays`` validates and gives
    float32 leaves, ``stack`` a batch with a leading axis.
    """

    eta: Any = 0.05
    psi: Any = 0.75
    actor_lr: Any = 1e-3
    critic_lr: Any = 1e-3
    explore_sigma: Any = 0.1

    @staticmethod
    def from_config(config: "SHEDConfig") -> "SHEDHyperparams":
        return SHEDHyperparams(eta=float(config.reward.eta), psi=float(config.psi), actor_lr=float(config.actor_lr),
                               critic_lr=float(config.critic_lr), explore_sigma=float(config.explore_sigma))

    def validate(self) -> "SHEDHyperparams":
        """Raise ValueError naming the field for concrete values outside their valid range."""
        for name, (lo, hi, lo_inc, hi_inc) in _HPARAM_RANGES.items():
            value = getattr(self, name)
            try:
                v = np.asarray(value, dtype=np.float64)
            except Exception:  # a tracer: nothing to check at trace time
                continue
            ok = (v >= lo if lo_inc else v > lo) & (v <= hi if hi_inc else v < hi) & np.isfinite(v)
            if not np.all(ok):
                interval = f"{'[' if lo_inc else '('}{lo}, {hi}{']' if hi_inc else ')'}"
                raise ValueError(f"SHEDHyperparams.{name} must be a finite value in {interval}, got {value}")
        return self

    def as_arrays(self) -> "SHEDHyperparams":
        return self.validate().replace(**{f: jnp.asarray(getattr(self, f), jnp.float32) for f in _HPARAM_RANGES})

    @staticmethod
    def stack(items: list["SHEDHyperparams"]) -> "SHEDHyperparams":
        """A batch (leading axis) of hyperparameter sets, ready for ``jax.vmap``."""
        items = [h.validate() for h in items]
        return SHEDHyperparams(**{f: jnp.asarray([getattr(h, f) for h in items], jnp.float32) for f in _HPARAM_RANGES})


HPARAM_NAMES = tuple(_HPARAM_RANGES)


def _masked_zscore(r, mask, eps: float = 1e-6):
    """``reward.zscore`` over the entries where ``mask`` holds, written back there (others: 0)."""
    w = mask.astype(jnp.float32)
    n = jnp.maximum(jnp.sum(w), 1.0)
    mean = jnp.sum(w * r) / n
    std = jnp.sqrt(jnp.sum(w * (r - mean) ** 2) / n)
    return jnp.where(mask, (r - mean) / (std + eps), 0.0)


def zscore_split(r, real_mask, eps: float = 1e-6):
    """Z-score the real (``real_mask``) and synthetic entries of a mixed batch separately.

    The dynamic-ratio form of ``reward.zscore_mixed``: the same numbers when ``real_mask`` is a prefix.
    """
    r = jnp.asarray(r, jnp.float32)
    return _masked_zscore(r, real_mask, eps) + _masked_zscore(r, ~real_mask, eps)


@struct.dataclass
class SHEDState:
    hparams: SHEDHyperparams
    ddpg: DDPGState
    diffusion: Any  # DiffusionState (shed) or None (hmdp)
    real: RingBuffer
    syn: Any  # RingBuffer (shed) or None (hmdp)
    s: jax.Array  # [m] current teacher state (raw mean returns)
    t: jax.Array  # int32 step within the teacher episode
    pending_eval_steps: jax.Array  # int32 eval env steps of begin_episode, charged to the next step


def evaluation_levels(env, config: SHEDConfig):
    """(params with leading m, max_steps for evaluation) of the teacher's evaluation set."""
    params, cap = _evaluation_levels(env, config)
    return params, (config.eval_max_steps or cap)


def _evaluation_levels(env, config: SHEDConfig):
    return evaluation_set(env, config.eval_set, config.num_eval_levels)  # the env's own set (env.ued)


@dataclasses.dataclass(frozen=True)
class SHED:
    """SHED (``use_diffusion=True``) or h-MDP (``False``)."""

    env: Any
    student: Any
    config: SHEDConfig = SHEDConfig()
    use_diffusion: bool = True
    name: str = "shed"
    eval_levels: Any = None  # optional explicit evaluation levels (params, leading axis m), e.g. for small envs

    def __post_init__(self):
        cfg = self.config
        n, e = cfg.num_levels, self.student.config.num_envs
        if e % n:
            raise ValueError(f"{self.name}: the student's num_envs ({e}) must be a multiple of num_levels ({n})")
        codec = LevelCodec(teacher_space(self.env, cfg.low, cfg.high))
        if self.eval_levels is None:
            eval_params, eval_max = evaluation_levels(self.env, cfg)
        else:
            eval_params, eval_max = self.eval_levels, cfg.eval_max_steps
            m = jax.tree_util.tree_leaves(eval_params)[0].shape[0]
            if m != cfg.num_eval_levels:
                raise ValueError(f"{self.name}: {m} evaluation levels given but num_eval_levels={cfg.num_eval_levels}")
        m, da = cfg.num_eval_levels, n * codec.dim
        cap = cfg.real_capacity or (2048 if self.use_diffusion else 10000)
        ddpg = make_ddpg(DDPGConfig(m, da, actor_lr=cfg.actor_lr, critic_lr=cfg.critic_lr, explore_sigma=cfg.explore_sigma))
        diff = make_diffusion(
            DiffusionConfig(m, da, lr=cfg.diffusion_lr, sampler=cfg.sampler, train_bc=cfg.syn_action == "bc", ema_decay=cfg.diffusion_ema)
        )
        # Adam with its learning rate held in the optimiser state (set from SHEDHyperparams).
        tx = optax.inject_hyperparams(optax.adam)(learning_rate=1e-3)
        for k, v in dict(codec=codec, eval_params=eval_params, eval_max=eval_max, ddpg=ddpg, diff=diff, capacity=cap,
                         reward_fn=make_reward_fn(cfg.reward), state_dim=m, action_dim=da, tx=tx,
                         actor_net=Actor(da, ddpg.config.hidden), critic_net=Critic(ddpg.config.hidden)).items():
            object.__setattr__(self, k, v)

    # ---- hyperparameters -------------------------------------------------------------------

    @property
    def hparam_names(self) -> tuple[str, ...]:
        """The dynamic hyperparameters that change what this method does (h-MDP has no psi)."""
        return HPARAM_NAMES if self.use_diffusion else tuple(n for n in HPARAM_NAMES if n != "psi")

    @property
    def inert_fields(self) -> tuple[str, ...]:
        """Config fields and hyperparameters this method accepts but never reads (h-MDP: the synthetic side)."""
        if self.use_diffusion:
            return ()
        return ("psi", "syn_capacity", "diffusion_threshold", "diffusion_steps", "num_syn", "syn_threshold",
                "syn_action", "syn_reward", "sampler", "diffusion_lr", "diffusion_ema")

    @property
    def default_hparams(self) -> SHEDHyperparams:
        """The config's values as a hyperparameter pytree of Python floats."""
        return SHEDHyperparams.from_config(self.config)

    def with_hparams(self, mstate: SHEDState, hparams: SHEDHyperparams) -> SHEDState:
        """``mstate`` with ``hparams`` in place of its hyperparameters (optimiser states synced).

        ``with_hparams(init(key), h)`` equals ``init(key, h)``: nothing random depends on them.
        """
        if not isinstance(hparams, SHEDHyperparams):
            raise TypeError(f"{self.name}: hparams must be a SHEDHyperparams, got {type(hparams).__name__}")
        hp = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), hparams.validate())
        ddpg = mstate.ddpg.replace(actor_opt_state=self._with_lr(mstate.ddpg.actor_opt_state, hp.actor_lr),
                                   critic_opt_state=self._with_lr(mstate.ddpg.critic_opt_state, hp.critic_lr))
        return mstate.replace(hparams=hp, ddpg=ddpg)

    @staticmethod
    def _with_lr(opt_state, lr):
        return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": jnp.asarray(lr, jnp.float32)})

    def reward_fn_for(self, eta) -> Any:
        """``(s, a, s') -> R`` with a dynamic eta (the config's reward form and guards otherwise).

        For the paper forms R = gain - eta * cv; the gain comes from the config's reward with eta = 0,
        so this gives the same float32 numbers as ``make_reward_fn`` with that eta.
        """
        rc = self.config.reward
        if rc.form == "code_mean":
            return self.reward_fn
        gain_fn = make_reward_fn(dataclasses.replace(rc, eta=0.0))
        return lambda s, a, s_next: gain_fn(s, a, s_next) - eta * coefficient_of_variation(s, s_next, rc.cv_guard, rc.cv_clip)

    # ---- pieces --------------------------------------------------------------------------

    def performance(self, key, sstate):
        """s = mean return per evaluation level [m], and the env steps it cost."""
        rets, info = self.student.evaluate_with_info(sstate, key, self.eval_params, self.config.num_eval_episodes, self.eval_max)
        return rets.mean(axis=-1), jnp.asarray(info["env_steps"], jnp.int32)

    def performance_and_test(self, key, sstate, test: EvalRequest):
        """``performance`` plus the loop's test set as one rollout: (s, env steps, test returns [n, E]).

        The test returns are NaN when ``test.run`` is false; then only the teacher's evaluation
        runs. A traced ``test.run`` chooses with ``lax.cond``, a real branch as long as it is
        unbatched (the loop's schedule is shared by all vmapped seeds); a Python bool chooses at
        trace time. Every row's keys are drawn as ``performance(key, sstate)`` and a separate test
        evaluation with ``test.key`` draw them; the results are theirs where the backend computes a
        row the same at any batch size (``PPOStudent.evaluate_many``).
        """
        cfg = self.config
        n_test = jax.tree_util.tree_leaves(test.levels)[0].shape[0]
        steps = jnp.int32(self.student.eval_env_steps(cfg.num_eval_levels, cfg.num_eval_episodes, self.eval_max))

        def both(s):
            (rets, _), (test_rets, _) = self.student.evaluate_many(
                s, [(key, self.eval_params, cfg.num_eval_episodes, self.eval_max),
                    (test.key, test.levels, test.num_episodes, test.max_steps)])
            return rets.mean(axis=-1), test_rets

        def teacher_only(s):
            return self.performance(key, s)[0], jnp.full((n_test, test.num_episodes), jnp.nan, jnp.float32)

        if isinstance(test.run, bool):
            s_next, test_rets = (both if test.run else teacher_only)(sstate)
        else:
            s_next, test_rets = jax.lax.cond(test.run, both, teacher_only, sstate)
        return s_next, steps, test_rets

    def _scaled(self, b: Transition) -> Transition:
        k = 1.0 / self.config.state_scale
        return b.replace(s=b.s * k, s_next=b.s_next * k)

    def act(self, mstate: SHEDState, key: jax.Array) -> jax.Array:
        """u = clip(mu(s / scale) + N(0, explore_sigma^2), -1, 1) with the state's dynamic sigma."""
        mu = self.ddpg.act(mstate.ddpg, mstate.s / self.config.state_scale)  # deterministic, in [-1, 1]
        return jnp.clip(mu + mstate.hparams.explore_sigma * jax.random.normal(key, mu.shape), -1.0, 1.0)

    def ddpg_update(self, st: DDPGState, batch: Transition, hp: SHEDHyperparams, real_mask=None) -> DDPGState:
        """One DDPG update (``teacher.ddpg.ddpg_update``) with dynamic learning rates.

        Same steps as the library function: per-batch reward z-scoring (per part of a mixed batch,
        given by ``real_mask``), critic step, actor step on the updated critic, soft target updates.
        The learning rates come from ``hp`` through the injected optimiser states.
        """
        c = self.ddpg.config
        actor, critic = self.actor_net, self.critic_net
        r = batch.r.astype(jnp.float32)
        if c.reward_norm:
            r = zscore_split(r, jnp.ones(r.shape, bool) if real_mask is None else real_mask)
        next_u = actor.apply(st.target_actor_params, batch.s_next)
        q_next = critic.apply(st.target_critic_params, batch.s_next, next_u)
        y = jax.lax.stop_gradient(r + c.gamma * (1.0 - batch.done) * q_next)

        def critic_loss(p):
            return jnp.mean((critic.apply(p, batch.s, batch.u) - y) ** 2)

        c_grads = jax.grad(critic_loss)(st.critic_params)
        c_updates, critic_opt = self.tx.update(c_grads, self._with_lr(st.critic_opt_state, hp.critic_lr), st.critic_params)
        critic_params = optax.apply_updates(st.critic_params, c_updates)

        def actor_loss(p):
            return -jnp.mean(critic.apply(critic_params, batch.s, actor.apply(p, batch.s)))

        a_grads = jax.grad(actor_loss)(st.actor_params)
        a_updates, actor_opt = self.tx.update(a_grads, self._with_lr(st.actor_opt_state, hp.actor_lr), st.actor_params)
        actor_params = optax.apply_updates(st.actor_params, a_updates)
        return DDPGState(
            actor_params=actor_params,
            critic_params=critic_params,
            target_actor_params=optax.incremental_update(actor_params, st.target_actor_params, c.tau),
            target_critic_params=optax.incremental_update(critic_params, st.target_critic_params, c.tau),
            actor_opt_state=actor_opt,
            critic_opt_state=critic_opt,
            num_updates=st.num_updates + 1,
        )

    def sample_mixed(self, real: RingBuffer, syn: RingBuffer, key: jax.Array, psi) -> tuple[Transition, jax.Array]:
        """A mixed batch with a dynamic ratio: floor(psi * B) real items first, synthetic after.

        Returns ``(batch, real_mask)``; see :class:`SHEDHyperparams` for why a fixed split.
        """
        b = self.config.ddpg_batch
        k_real, k_syn = jax.random.split(key)
        n_real = jnp.floor(jnp.asarray(psi, jnp.float32) * b + 1e-4)  # 1e-4: 0.75 * 32 is 24 in any rounding
        mask = jnp.arange(b) < n_real
        b_real, b_syn = buffer_sample(real, k_real, b), buffer_sample(syn, k_syn, b)
        batch = jax.tree_util.tree_map(lambda x, y: jnp.where(mask.reshape((b,) + (1,) * (x.ndim - 1)), x, y), b_real, b_syn)
        return batch, mask

    def _ddpg_updates(self, key, mstate: SHEDState) -> tuple[DDPGState, jax.Array]:
        cfg, hp = self.config, mstate.hparams
        real, syn = mstate.real, mstate.syn

        def real_updates(count):
            def run(st):
                def one(st, k):
                    b = buffer_sample(real, k, cfg.ddpg_batch)
                    return self.ddpg_update(st, self._scaled(b), hp), None

                return jax.lax.scan(one, st, jax.random.split(key, count))[0]

            return run

        def mixed_updates(st):
            def one(st, k):
                b, mask = self.sample_mixed(real, syn, k, hp.psi)
                return self.ddpg_update(st, self._scaled(b), hp, mask), None

            return jax.lax.scan(one, st, jax.random.split(key, 2))[0]

        enough_real = real.count > cfg.ddpg_threshold
        if not self.use_diffusion:  # h-MDP: 2 real updates
            branch = jnp.where(enough_real, 1, 0)
            branches = [lambda st: st, real_updates(2)]
        else:
            mixed = (syn.count > cfg.syn_threshold) & enough_real & (syn.count > cfg.ddpg_threshold)
            branch = jnp.where(mixed, 2, jnp.where(enough_real, 1, 0))
            branches = [lambda st: st, real_updates(3), mixed_updates]
        return jax.lax.switch(branch, branches, mstate.ddpg), branch

    def _diffusion_block(self, key, diff_state: DiffusionState, real: RingBuffer, syn: RingBuffer, reward_fn):
        cfg = self.config
        k_train, k_syn = jax.random.split(key)

        def run(args):
            d, sb = args
            d, losses = self.diff.train_steps(d, k_train, real, cfg.diffusion_steps)
            new = self.diff.synthesize(d, k_syn, real, cfg.num_syn, reward_fn, cfg.syn_action, cfg.syn_reward)
            return (d, buffer_add_many(sb, new)), jnp.mean(losses)

        def skip(args):
            return args, jnp.float32(jnp.nan)

        return jax.lax.cond(real.count > cfg.diffusion_threshold, run, skip, (diff_state, syn))

    # ---- interface -------------------------------------------------------------------------

    def init(self, key: jax.Array, hparams: SHEDHyperparams | None = None) -> SHEDState:
        """Fresh teacher state; ``hparams`` overrides the config's hyperparameters (``default_hparams``)."""
        hparams = self.default_hparams if hparams is None else hparams
        if not isinstance(hparams, SHEDHyperparams):
            raise TypeError(f"{self.name}: hparams must be a SHEDHyperparams, got {type(hparams).__name__}")
        hparams.validate()  # before building anything, so a bad value fails fast
        k_ddpg, k_diff = jax.random.split(key)
        example = make_transition(self.state_dim, self.action_dim)
        ddpg = self.ddpg.init(k_ddpg)
        ddpg = ddpg.replace(actor_opt_state=self.tx.init(ddpg.actor_params), critic_opt_state=self.tx.init(ddpg.critic_params))
        state = SHEDState(
            hparams=self.default_hparams,
            ddpg=ddpg,
            diffusion=self.diff.init(k_diff) if self.use_diffusion else None,
            real=buffer_init(example, self.capacity),
            syn=buffer_init(example, self.config.syn_capacity) if self.use_diffusion else None,
            s=jnp.zeros((self.state_dim,), jnp.float32),
            t=jnp.int32(0),
            pending_eval_steps=jnp.int32(0),
        )
        return self.with_hparams(state, hparams)

    def begin_episode(self, key: jax.Array, mstate: SHEDState, sstate):
        s0, steps = self.performance(key, sstate)
        return mstate.replace(s=s0, t=jnp.int32(0), pending_eval_steps=steps), sstate

    def step(self, key: jax.Array, mstate: SHEDState, sstate):
        return self._step(key, mstate, sstate, None)[:3]

    @property
    def fuses_test_eval(self) -> bool:
        """Whether the loop may call ``step_with_test``: the student runs evaluations as one rollout."""
        return hasattr(self.student, "evaluate_many")

    def step_with_test(self, key: jax.Array, mstate: SHEDState, sstate, test: EvalRequest):
        """``step`` whose evaluation also runs the loop's test set (``methods.base``): one rollout."""
        return self._step(key, mstate, sstate, test)

    def _step(self, key, mstate: SHEDState, sstate, test: EvalRequest | None):
        cfg, student = self.config, self.student
        n, d = cfg.num_levels, self.codec.dim
        reward_fn = self.reward_fn_for(mstate.hparams.eta)
        k_act, k_seed, k_train, k_eval, k_diff, k_ddpg = jax.random.split(key, 6)
        u = self.act(mstate, k_act)  # [n * d]
        vecs = self.codec.space.from_unit(u.reshape(n, d))
        sstate, ppo = student.train(sstate, k_train, self.codec.to_params(vecs, new_seeds(k_seed, n)), cfg.updates_per_step)
        if test is None:
            s_next, eval_steps = self.performance(k_eval, sstate)
            test_rets = None
        else:
            s_next, eval_steps, test_rets = self.performance_and_test(k_eval, sstate, test)
        r = reward_fn(mstate.s, u, s_next)
        done = (mstate.t == cfg.budget_steps - 1).astype(jnp.float32)
        real = buffer_add(mstate.real, Transition(s=mstate.s, u=u, r=r, s_next=s_next, done=done))
        mstate = mstate.replace(real=real)
        diff_loss = jnp.float32(jnp.nan)
        if self.use_diffusion:
            (diffusion, syn), diff_loss = self._diffusion_block(k_diff, mstate.diffusion, real, mstate.syn, reward_fn)
            mstate = mstate.replace(diffusion=diffusion, syn=syn)
        ddpg_state, branch = self._ddpg_updates(k_ddpg, mstate)
        info = StepInfo(
            levels=vecs,
            env_steps_train=jnp.int32(cfg.updates_per_step * student.env_steps_per_update),
            env_steps_eval=eval_steps + mstate.pending_eval_steps,
            teacher_reward=r,
            num_new_levels=jnp.int32(n),
            extras={
                "ppo": mean_metrics(ppo),
                "teacher_state": s_next,
                "real_size": real.count,
                "syn_size": mstate.syn.count if self.use_diffusion else jnp.int32(0),
                "ddpg_branch": branch,  # 0 none, 1 real-only, 2 mixed
                "diffusion_loss": diff_loss,
            },
        )
        mstate = mstate.replace(ddpg=ddpg_state, s=s_next, t=mstate.t + 1, pending_eval_steps=jnp.int32(0))
        return mstate, sstate, info, test_rets


def make_method(name: str, env, student, config: Any = None):
    """``shed`` or ``hmdp`` (called by ``shed_jax.methods.registry.make_method``)."""
    if name not in ("shed", "hmdp"):
        raise ValueError(f"shed_jax.methods.shed builds 'shed' or 'hmdp', not {name!r}")
    if config is None:
        config = SHEDConfig()
    elif isinstance(config, dict):
        fields = {f.name for f in dataclasses.fields(SHEDConfig)}
        unknown = sorted(set(config) - fields)
        if unknown:
            nested = [k for k in unknown if k in {f.name for f in dataclasses.fields(RewardConfig)}]
            hint = (f"; {nested} are fields of the teacher reward, given inside it: reward={{\"{nested[0]}\": <value>}} "
                    f"(on the command line: --set 'reward={{\"{nested[0]}\": <value>}}')" if nested else "")
            raise ValueError(f"method {name!r}: unknown config field(s) {unknown}{hint}; known: {sorted(fields)}")
        config = SHEDConfig(**config)
    elif not isinstance(config, SHEDConfig):
        raise TypeError(f"method {name!r}: config must be None, a dict or a SHEDConfig, got {type(config).__name__}")
    return SHED(env, student, config, use_diffusion=name == "shed", name=name)
