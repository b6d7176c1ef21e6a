"""DDPG teacher (docs/design.md §5): a deterministic actor over u-space and a Q critic, with target copies.

Actor  m -> 400 -> 300 -> d_a, ReLU, tanh output (u in [-1, 1]^{d_a}).
Critic [s, u] -> 400 -> 300 -> 1, ReLU.
Target y = r~ + gamma (1 - done) Q'(s', mu'(s')); critic loss MSE; actor loss -mean Q(s, mu(s)) using
the freshly updated critic; then soft target updates theta' <- tau theta + (1 - tau) theta' (optax's
``incremental_update``). Adam 1e-3 for both, no gradient clipping [official code].

r~ is the batch's rewards z-scored per batch (real and synthetic parts separately in a mixed batch,
``real_mask``) when ``reward_norm`` is on [official code], else the raw rewards.

The learning rates live in the optimiser states (``optax.inject_hyperparams``): the config's values
at ``init``, replaced by ``with_learning_rates`` with traced values if wanted, so a ``vmap`` over
learning rates is one compiled program. The exploration noise's std is the config's, or a traced
``sigma`` given to ``act``. This is the project's only DDPG: the hierarchical teachers
(``shed_jax.teacher.ddpg_teacher``) call it.

Everything is a pure function of (config, state, ...); the config is a frozen, hashable dataclass so
it can be a static argument of ``jax.jit``. Teacher actions stay in u-space; mapping u to level
parameters is the caller's job (``env.param_space.from_unit``).

Initialisation uses flax's defaults (LeCun-normal kernels, zero biases), not PyTorch's fan-in
uniform; DDPG is not sensitive to this at these sizes.
"""
from __future__ import annotations

import dataclasses
from typing import Literal, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from shed_jax.configs import check_modes
from shed_jax.teacher.buffers import Transition
from shed_jax.teacher.reward import zscore_mixed


@dataclasses.dataclass(frozen=True)
class DDPGConfig:
    """Static DDPG settings. state_dim = m (or m + 1 with the t/T extension), action_dim = n*d."""

    state_dim: int
    action_dim: int
    hidden: tuple = (400, 300)
    actor_lr: float = 1e-3  # Adam learning rates at init; ``with_learning_rates`` replaces them
    critic_lr: float = 1e-3
    gamma: float = 0.99
    tau: float = 0.001
    explore_sigma: float = 0.1  # Gaussian in u-space [our choice]; 0.0 = official code; ``act(sigma=)`` overrides
    reward_norm: bool = True  # per-batch z-scoring of rewards [official code]
    # Options of the learning teacher (shed_jax.methods.learning_teacher); the defaults are the official code's.
    preact_penalty: float = 0.0  # the actor loss adds preact_penalty * mean(z^2) of its pre-tanh outputs z
    actor_out_init: Literal["lecun", "zeros"] = "lecun"  # 'zeros': the actor's last layer starts at 0, so mu(s) = 0
    # TD3's clipped double Q (Fujimoto et al., 2018): two critics, both fitted to
    # r + gamma min(Q1', Q2'); the actor ascends Q1. Off: one critic, as in DDPG.
    twin_critics: bool = False
    # the actor and both target networks update on every k-th call of ``update`` (TD3: 2); the critic on every call
    actor_delay: int = 1

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        for name in ("state_dim", "action_dim"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"DDPGConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"DDPGConfig.hidden must be non-empty positive widths, got {self.hidden}")
        for name in ("actor_lr", "critic_lr"):
            if not getattr(self, name) > 0:
                raise ValueError(f"DDPGConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.gamma <= 1.0:
            raise ValueError(f"DDPGConfig.gamma must lie in [0, 1], got {self.gamma}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"DDPGConfig.tau must lie in (0, 1], got {self.tau}")
        if not self.explore_sigma >= 0.0:
            raise ValueError(f"DDPGConfig.explore_sigma must be >= 0, got {self.explore_sigma}")
        if not self.preact_penalty >= 0.0:
            raise ValueError(f"DDPGConfig.preact_penalty must be >= 0, got {self.preact_penalty}")
        if not isinstance(self.twin_critics, bool):
            raise ValueError(f"DDPGConfig.twin_critics must be True or False, got {self.twin_critics!r}")
        if isinstance(self.actor_delay, bool) or not isinstance(self.actor_delay, int) or self.actor_delay < 1:
            raise ValueError(f"DDPGConfig.actor_delay must be an int >= 1, got {self.actor_delay!r}")
        check_modes(self)


class Actor(nn.Module):
    action_dim: int
    hidden: Sequence[int] = (400, 300)
    zero_out: bool = False  # the last layer's kernel and bias start at zero

    @nn.compact
    def __call__(self, s, preact: bool = False):
        """tanh(z) of the last layer's output z; (tanh(z), z) with ``preact``."""
        x = s
        for h in self.hidden:
            x = nn.relu(nn.Dense(h)(x))
        z = (nn.Dense(self.action_dim, kernel_init=nn.initializers.zeros) if self.zero_out else nn.Dense(self.action_dim))(x)
        return (jnp.tanh(z), z) if preact else jnp.tanh(z)


class Critic(nn.Module):
    hidden: Sequence[int] = (400, 300)

    @nn.compact
    def __call__(self, s, u):
        x = jnp.concatenate([s, u], axis=-1)
        for h in self.hidden:
            x = nn.relu(nn.Dense(h)(x))
        return nn.Dense(1)(x)[..., 0]


class TwinCritic(nn.Module):
    """Two independent critics; returns [2, ...] (Q1, Q2)."""

    hidden: Sequence[int] = (400, 300)

    @nn.compact
    def __call__(self, s, u):
        return jnp.stack([Critic(self.hidden, name="q1")(s, u), Critic(self.hidden, name="q2")(s, u)])


@struct.dataclass
class DDPGState:
    actor_params: dict
    critic_params: dict
    target_actor_params: dict
    target_critic_params: dict
    actor_opt_state: optax.OptState
    critic_opt_state: optax.OptState
    num_updates: jax.Array  # int32


def _nets(config: DDPGConfig):
    critic = TwinCritic(config.hidden) if config.twin_critics else Critic(config.hidden)
    return Actor(config.action_dim, config.hidden, config.actor_out_init == "zeros"), critic


def _q1(config: DDPGConfig, q):
    """The critic the actor follows (the only one without twin critics)."""
    return q[0] if config.twin_critics else q


def _q_target(config: DDPGConfig, q):
    """The value a target takes: min(Q1', Q2') with twin critics."""
    return jnp.min(q, axis=0) if config.twin_critics else q


def _optims(config: DDPGConfig):
    """Adam for the actor and the critic, each with its learning rate held in the optimiser state."""
    adam = optax.inject_hyperparams(optax.adam)
    return adam(learning_rate=config.actor_lr), adam(learning_rate=config.critic_lr)


def ddpg_init(config: DDPGConfig, key: jax.Array) -> DDPGState:
    """Fresh networks, identical target copies and Adam states (learning rates from the config)."""
    actor, critic = _nets(config)
    k_a, k_c = jax.random.split(key)
    s = jnp.zeros((1, config.state_dim), jnp.float32)
    u = jnp.zeros((1, config.action_dim), jnp.float32)
    actor_params = actor.init(k_a, s)
    critic_params = critic.init(k_c, s, u)
    opt_a, opt_c = _optims(config)
    return DDPGState(
        actor_params=actor_params,
        critic_params=critic_params,
        target_actor_params=actor_params,
        target_critic_params=critic_params,
        actor_opt_state=opt_a.init(actor_params),
        critic_opt_state=opt_c.init(critic_params),
        num_updates=jnp.int32(0),
    )


def with_learning_rates(state: DDPGState, actor_lr, critic_lr) -> DDPGState:
    """``state`` with these (possibly traced) Adam learning rates in its optimiser states."""
    def put(opt_state, lr):
        return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": jnp.asarray(lr, jnp.float32)})

    return state.replace(actor_opt_state=put(state.actor_opt_state, actor_lr), critic_opt_state=put(state.critic_opt_state, critic_lr))


def ddpg_act(config: DDPGConfig, state: DDPGState, s, key: jax.Array | None = None, sigma=None) -> jax.Array:
    """u = clip(mu(s) + N(0, sigma^2), -1, 1); deterministic mu(s) when ``key`` is None or sigma = 0.

    ``sigma``: the noise std, ``config.explore_sigma`` when None; may be traced.
    """
    actor, _ = _nets(config)
    u = actor.apply(state.actor_params, jnp.asarray(s, jnp.float32))
    sigma = config.explore_sigma if sigma is None else sigma
    if key is not None and not (isinstance(sigma, (int, float)) and sigma == 0):
        u = u + sigma * jax.random.normal(key, u.shape)
    return jnp.clip(u, -1.0, 1.0)


def ddpg_q(config: DDPGConfig, state: DDPGState, s, u) -> jax.Array:
    """Q(s, u) of the online critic (Q1 with twin critics)."""
    _, critic = _nets(config)
    return _q1(config, critic.apply(state.critic_params, s, u))


@jax.named_scope("ddpg_update")  # names the teacher update's kernels in a profile
def ddpg_update(config: DDPGConfig, state: DDPGState, batch: Transition, real_mask=None):
    """One critic step, one actor step and one soft target update on ``batch`` (leading axis B).

    ``real_mask`` (bool [B], may be traced): for a mixed batch from ``buffers.sample_mixed``, which
    items are real, so that rewards are z-scored per part; None: all real. The Adam learning rates
    are the ones in ``state``'s optimiser states. Returns (new state, metrics dict).
    """
    actor, critic = _nets(config)
    opt_a, opt_c = _optims(config)
    r = batch.r.astype(jnp.float32)
    if config.reward_norm:
        r = zscore_mixed(r, jnp.ones(r.shape[-1:], bool) if real_mask is None else real_mask)
    next_u = actor.apply(state.target_actor_params, batch.s_next)
    q_next = _q_target(config, critic.apply(state.target_critic_params, batch.s_next, next_u))
    y = jax.lax.stop_gradient(r + config.gamma * (1.0 - batch.done) * q_next)

    def critic_loss(p):
        q = critic.apply(p, batch.s, batch.u)  # [2, B] with twin critics: the loss sums both MSEs
        loss = jnp.sum(jnp.mean((q - y) ** 2, axis=-1)) if config.twin_critics else jnp.mean((q - y) ** 2)
        return loss, _q1(config, q)

    (c_loss, q), c_grads = jax.value_and_grad(critic_loss, has_aux=True)(state.critic_params)
    c_updates, critic_opt_state = opt_c.update(c_grads, state.critic_opt_state, state.critic_params)
    critic_params = optax.apply_updates(state.critic_params, c_updates)

    def actor_loss(p):
        if not config.preact_penalty:
            return -jnp.mean(_q1(config, critic.apply(critic_params, batch.s, actor.apply(p, batch.s))))
        u, z = actor.apply(p, batch.s, preact=True)
        return -jnp.mean(_q1(config, critic.apply(critic_params, batch.s, u))) + config.preact_penalty * jnp.mean(z ** 2)

    a_loss, a_grads = jax.value_and_grad(actor_loss)(state.actor_params)
    a_updates, actor_opt_state = opt_a.update(a_grads, state.actor_opt_state, state.actor_params)
    actor_params = optax.apply_updates(state.actor_params, a_updates)
    slow = dict(
        actor_params=actor_params,
        target_actor_params=optax.incremental_update(actor_params, state.target_actor_params, config.tau),
        target_critic_params=optax.incremental_update(critic_params, state.target_critic_params, config.tau),
        actor_opt_state=actor_opt_state,
    )
    if config.actor_delay > 1:  # the actor's step and the targets' only on every k-th update, else kept
        now = (state.num_updates + 1) % config.actor_delay == 0
        slow = {k: jax.tree_util.tree_map(lambda a, b: jnp.where(now, a, b), v, getattr(state, k)) for k, v in slow.items()}

    new_state = DDPGState(critic_params=critic_params, critic_opt_state=critic_opt_state,
                          num_updates=state.num_updates + 1, **slow)
    metrics = {"critic_loss": c_loss, "actor_loss": a_loss, "q_mean": jnp.mean(q), "target_mean": jnp.mean(y)}
    return new_state, metrics


def ddpg_td_errors(config: DDPGConfig, state: DDPGState, batch: Transition) -> jax.Array:
    """|Q(s, u) - (r + gamma (1 - done) Q'(s', mu'(s')))| per item of ``batch``, its rewards as given.

    A diagnostic: the caller passes the rewards as the critic sees them (normalised or not).
    """
    actor, critic = _nets(config)
    q_next = _q_target(config, critic.apply(state.target_critic_params, batch.s_next,
                                            actor.apply(state.target_actor_params, batch.s_next)))
    y = batch.r + config.gamma * (1.0 - batch.done) * q_next
    return jnp.abs(_q1(config, critic.apply(state.critic_params, batch.s, batch.u)) - y)


@dataclasses.dataclass(frozen=True)
class DDPG:
    """The functions above bound to one config (``make_ddpg``), mirroring ``make_student``."""

    config: DDPGConfig

    def init(self, key):
        return ddpg_init(self.config, key)

    def act(self, state, s, key=None, sigma=None):
        return ddpg_act(self.config, state, s, key, sigma)

    def q(self, state, s, u):
        return ddpg_q(self.config, state, s, u)

    def update(self, state, batch, real_mask=None):
        return ddpg_update(self.config, state, batch, real_mask)

    def with_learning_rates(self, state, actor_lr, critic_lr):
        return with_learning_rates(state, actor_lr, critic_lr)

    def td_errors(self, state, batch):
        return ddpg_td_errors(self.config, state, batch)


def make_ddpg(config: DDPGConfig) -> DDPG:
    return DDPG(config)
