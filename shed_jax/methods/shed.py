"""SHED and h-MDP behind the UED method interface (SPEC 1.2): a DDPG teacher over performance vectors.

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
(the teacher sees s/100, SPEC 1.1) and the diffusion model normalises them itself. Rewards are
computed on raw returns; DDPG z-scores them per batch. The teacher's networks, the diffusion model
and both buffers persist across teacher episodes; ``begin_episode`` only evaluates the fresh student
to get s_0 and resets the step counter.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from shed_jax import eval_sets
from shed_jax.methods.base import StepInfo
from shed_jax.methods.dr import LevelCodec, mean_metrics, teacher_space
from shed_jax.methods.mutations import new_seeds
from shed_jax.teacher.buffers import (
    RingBuffer,
    Transition,
    buffer_add,
    buffer_add_many,
    buffer_init,
    buffer_sample,
    make_transition,
    sample_mixed,
)
from shed_jax.teacher.ddpg import DDPGConfig, DDPGState, make_ddpg
from shed_jax.teacher.diffusion import DiffusionConfig, DiffusionState, make_diffusion
from shed_jax.teacher.reward import RewardConfig, make_reward_fn


@dataclasses.dataclass(frozen=True)
class SHEDConfig:
    """SHED / h-MDP settings; defaults are SPEC 1.2 / 6.2 (official thresholds) and 6.3 (lander)."""

    updates_per_step: int = 10  # C in PPO iterations
    num_levels: int = 5  # n (lander 5, walker 4)
    budget_steps: int = 20  # T: done = 1 on the T-th transition
    num_eval_episodes: int = 8  # E_eval
    eval_set: str = "official"  # lander: 'official' (code's 10) or 'paper' (covering, any m); walker: ladder
    num_eval_levels: int = 10  # m
    eval_max_steps: int | None = None  # override the evaluation episode cap (default: the set's max_steps)
    state_scale: float = 100.0  # the DDPG networks see s / state_scale
    reward: RewardConfig = RewardConfig()
    explore_sigma: float = 0.1
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
        if not self.state_scale > 0:
            raise ValueError(f"SHEDConfig.state_scale must be > 0, got {self.state_scale}")
        if self.real_capacity is not None and self.real_capacity < self.ddpg_batch:
            raise ValueError(f"SHEDConfig.real_capacity must be >= ddpg_batch, got {self.real_capacity}")


@struct.dataclass
class SHEDState:
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
    if env.name.startswith("lander"):
        if config.eval_set == "official":
            ls = eval_sets.official_lander_eval_set(config.num_eval_levels)
        else:
            ls = eval_sets.lander_paper_eval_set(config.num_eval_levels)
        return ls.to_params(env.default_params), int(np.max(ls.fields["max_steps"]))
    if env.name == "walker":
        ls = eval_sets.walker_eval_set(config.num_eval_levels)
        return ls.to_params(env.default_params), None
    raise ValueError(f"SHED has no evaluation set for environment {env.name!r}")


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
        ddpg = make_ddpg(DDPGConfig(m, da, explore_sigma=cfg.explore_sigma))
        diff = make_diffusion(
            DiffusionConfig(m, da, lr=cfg.diffusion_lr, sampler=cfg.sampler, train_bc=cfg.syn_action == "bc", ema_decay=cfg.diffusion_ema)
        )
        for k, v in dict(codec=codec, eval_params=eval_params, eval_max=eval_max, ddpg=ddpg, diff=diff, capacity=cap,
                         reward_fn=make_reward_fn(cfg.reward), state_dim=m, action_dim=da).items():
            object.__setattr__(self, k, v)

    # ---- pieces --------------------------------------------------------------------------

    def performance(self, key, sstate):
        """s = mean return per evaluation level [m], and the env steps it cost."""
        rets, info = self.student.evaluate_with_info(sstate, key, self.eval_params, self.config.num_eval_episodes, self.eval_max)
        return rets.mean(axis=-1), jnp.asarray(info["env_steps"], jnp.int32)

    def _scaled(self, b: Transition) -> Transition:
        k = 1.0 / self.config.state_scale
        return b.replace(s=b.s * k, s_next=b.s_next * k)

    def _ddpg_updates(self, key, mstate: SHEDState) -> tuple[DDPGState, jax.Array]:
        cfg = self.config
        real, syn = mstate.real, mstate.syn

        def real_updates(count):
            def run(st):
                def one(st, k):
                    b = buffer_sample(real, k, cfg.ddpg_batch)
                    return self.ddpg.update(st, self._scaled(b))[0], None

                return jax.lax.scan(one, st, jax.random.split(key, count))[0]

            return run

        def mixed_updates(st):
            def one(st, k):
                b, n_real = sample_mixed(real, syn, k, cfg.ddpg_batch, cfg.psi)
                return self.ddpg.update(st, self._scaled(b), n_real)[0], None

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

    def _diffusion_block(self, key, diff_state: DiffusionState, real: RingBuffer, syn: RingBuffer):
        cfg = self.config
        k_train, k_syn = jax.random.split(key)

        def run(args):
            d, sb = args
            d, losses = self.diff.train_steps(d, k_train, real, cfg.diffusion_steps)
            new = self.diff.synthesize(d, k_syn, real, cfg.num_syn, self.reward_fn, cfg.syn_action, cfg.syn_reward)
            return (d, buffer_add_many(sb, new)), jnp.mean(losses)

        def skip(args):
            return args, jnp.float32(jnp.nan)

        return jax.lax.cond(real.count > cfg.diffusion_threshold, run, skip, (diff_state, syn))

    # ---- interface -------------------------------------------------------------------------

    def init(self, key: jax.Array) -> SHEDState:
        k_ddpg, k_diff = jax.random.split(key)
        example = make_transition(self.state_dim, self.action_dim)
        return SHEDState(
            ddpg=self.ddpg.init(k_ddpg),
            diffusion=self.diff.init(k_diff) if self.use_diffusion else None,
            real=buffer_init(example, self.capacity),
            syn=buffer_init(example, self.config.syn_capacity) if self.use_diffusion else None,
            s=jnp.zeros((self.state_dim,), jnp.float32),
            t=jnp.int32(0),
            pending_eval_steps=jnp.int32(0),
        )

    def begin_episode(self, key: jax.Array, mstate: SHEDState, sstate):
        s0, steps = self.performance(key, sstate)
        return mstate.replace(s=s0, t=jnp.int32(0), pending_eval_steps=steps), sstate

    def step(self, key: jax.Array, mstate: SHEDState, sstate):
        cfg, student = self.config, self.student
        n, d = cfg.num_levels, self.codec.dim
        k_act, k_seed, k_train, k_eval, k_diff, k_ddpg = jax.random.split(key, 6)
        u = self.ddpg.act(mstate.ddpg, mstate.s / cfg.state_scale, k_act)  # [n * d]
        vecs = self.codec.space.from_unit(u.reshape(n, d))
        sstate, ppo = student.train(sstate, k_train, self.codec.to_params(vecs, new_seeds(k_seed, n)), cfg.updates_per_step)
        s_next, eval_steps = self.performance(k_eval, sstate)
        r = self.reward_fn(mstate.s, u, s_next)
        done = (mstate.t == cfg.budget_steps - 1).astype(jnp.float32)
        real = buffer_add(mstate.real, Transition(s=mstate.s, u=u, r=r, s_next=s_next, done=done))
        mstate = mstate.replace(real=real)
        diff_loss = jnp.float32(jnp.nan)
        if self.use_diffusion:
            (diffusion, syn), diff_loss = self._diffusion_block(k_diff, mstate.diffusion, real, mstate.syn)
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
        return mstate, sstate, info


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
            raise ValueError(f"method {name!r}: unknown config field(s) {unknown}; known: {sorted(fields)}")
        config = SHEDConfig(**config)
    elif not isinstance(config, SHEDConfig):
        raise TypeError(f"method {name!r}: config must be None, a dict or a SHEDConfig, got {type(config).__name__}")
    return SHED(env, student, config, use_diffusion=name == "shed", name=name)
