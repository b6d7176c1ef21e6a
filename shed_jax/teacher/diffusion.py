"""Conditional DDPM over the teacher's next state s' given (s, a) (docs/design.md §6, §7).

* Schedule: the VP schedule of Diffusion-QL, beta_k = 1 - exp(-beta_min/K - (beta_max - beta_min)
  (2k - 1) / (2 K^2)), with the **minus** sign (the paper's "+beta_min/K" is a typo; the code and
  docs/design.md §6.1 use minus). K = 5, beta_min 0.1, beta_max 10 give ln(alpha_bar_K) = -5.05.
* Forward: s'_k = sqrt(abar_k) s'_0 + sqrt(1 - abar_k) eps; loss E||eps - eps_phi(s'_k, s, a, k)||^2
  (mean over elements) with k ~ U{1..K}.
* Samplers: ``ancestral`` (paper appendix): s'_{k-1} = s'_k/sqrt(alpha_k) - beta_k/sqrt(alpha_k(1 -
  abar_k)) eps_phi + sqrt(beta_k) z, z = 0 at k = 1. ``code_posterior`` (official code): predict x0,
  clamp it, take the DDPM posterior mean with variance beta~_k, clamp the output.
* Network (official code): sinusoidal 16-d time embedding -> Dense 32 -> Mish -> Dense 16, shared by
  the next-state head [s, a, t_emb, s'_k] -> 3 x (256, Mish) -> m and the behaviour-cloning action
  head [a_k, t_emb, s] -> 3 x (256, Mish) -> d_a. The time input is the code's index t = k - 1.
  The action head is trained only when ``train_bc`` is set (``syn_action='bc'``).
* Synthetic actions (``synthesize``): uniform on [-1, 1]^{d_a} (the paper's), from the BC head
  ('bc'), or from the teacher's current policy with noise ('policy', an ``action_fn`` the caller gives).
* Normalisation of s and s' (performance vectors are returns in the hundreds): ``normalizer``
  'buffer' (default) standardises each dimension with the mean/std of the valid entries of the real
  buffer (s and s' pooled), refreshed at every ``train_steps`` call and kept in the state so sampling
  uses exactly the statistics the network was trained with. Because the buffer is a FIFO window,
  these are running statistics over the most recent ``capacity`` transitions; a floor ``min_std``
  keeps a constant dimension finite. 'scale' divides by ``scale`` = 100 (docs/design.md §6.5); 'none' uses raw
  values (official code). Actions live in u-space [-1, 1] and are not normalised.

Everything is a pure function over a ``DiffusionState`` pytree; ``make_diffusion(config)`` returns a
frozen object of such functions (jittable, vmappable over seeds, usable inside ``lax.scan``).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable, Literal, get_args

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from shed_jax.configs import check_modes
from shed_jax.teacher.buffers import RingBuffer, Transition, buffer_sample

Sampler = Literal["ancestral", "code_posterior"]
Normalizer = Literal["buffer", "scale", "none"]
SynAction = Literal["uniform", "bc", "policy"]
SynReward = Literal["recompute", "copy"]
SYN_ACTIONS, SYN_REWARDS = get_args(SynAction), get_args(SynReward)


@dataclasses.dataclass(frozen=True)
class DiffusionConfig:
    """Static settings of the conditional diffusion model.

    state_dim / action_dim: m and d_a.  num_steps: K.  state_clip: the code sampler's clamp of x0 and
    of the output, in raw state units (S_max; None disables).  ema_decay: if > 0, sampling uses an
    exponential moving average of the parameters (updated every training step), as Diffusion-QL
    does; 0 (default) samples with the trained parameters, as the official SHED code does.
    """

    state_dim: int
    action_dim: int
    num_steps: int = 5
    beta_min: float = 0.1
    beta_max: float = 10.0
    hidden: int = 256
    num_layers: int = 3
    time_dim: int = 16
    lr: float = 1e-3
    batch_size: int = 64
    sampler: Sampler = "ancestral"
    state_clip: float | None = 300.0
    normalizer: Normalizer = "buffer"
    scale: float = 100.0
    min_std: float = 1e-2
    train_bc: bool = False
    ema_decay: float = 0.0

    def __post_init__(self):
        for name in ("state_dim", "action_dim", "num_steps", "hidden", "num_layers", "batch_size"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"DiffusionConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.time_dim < 4 or self.time_dim % 2:
            raise ValueError(f"DiffusionConfig.time_dim must be an even number >= 4, got {self.time_dim}")
        if not 0 < self.beta_min < self.beta_max:
            raise ValueError(f"DiffusionConfig needs 0 < beta_min < beta_max, got {self.beta_min}, {self.beta_max}")
        check_modes(self)
        if not self.lr > 0:
            raise ValueError(f"DiffusionConfig.lr must be > 0, got {self.lr}")
        if not self.scale > 0 or not self.min_std > 0:
            raise ValueError(f"DiffusionConfig.scale and min_std must be > 0, got {self.scale}, {self.min_std}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"DiffusionConfig.ema_decay must lie in [0, 1), got {self.ema_decay}")
        if self.state_clip is not None and not self.state_clip > 0:
            raise ValueError(f"DiffusionConfig.state_clip must be > 0 or None, got {self.state_clip}")


# --------------------------------------------------------------------------------------------
# Schedule and forward process
# --------------------------------------------------------------------------------------------


@struct.dataclass
class Schedule:
    """Per-step constants, index k - 1 for diffusion step k = 1..K."""

    betas: jax.Array
    alphas: jax.Array
    alpha_bars: jax.Array
    alpha_bars_prev: jax.Array  # abar_{k-1}, with abar_0 = 1
    posterior_var: jax.Array  # beta~_k = beta_k (1 - abar_{k-1}) / (1 - abar_k)


def vp_schedule(num_steps: int, beta_min: float = 0.1, beta_max: float = 10.0) -> Schedule:
    """The VP schedule (computed in float64 on the host: it is a constant of the model)."""
    K = int(num_steps)
    k = np.arange(1, K + 1, dtype=np.float64)
    betas = 1.0 - np.exp(-beta_min / K - 0.5 * (beta_max - beta_min) * (2 * k - 1) / K**2)
    alphas = 1.0 - betas
    alpha_bars = np.cumprod(alphas)
    prev = np.concatenate([[1.0], alpha_bars[:-1]])
    post = betas * (1.0 - prev) / (1.0 - alpha_bars)
    f = lambda x: jnp.asarray(x, jnp.float32)
    return Schedule(f(betas), f(alphas), f(alpha_bars), f(prev), f(post))


def q_sample(schedule: Schedule, x0, k, eps) -> jax.Array:
    """Forward closed form x_k = sqrt(abar_k) x0 + sqrt(1 - abar_k) eps; k in 1..K, shape x0.shape[:-1]."""
    ab = schedule.alpha_bars[jnp.asarray(k) - 1][..., None]
    return jnp.sqrt(ab) * x0 + jnp.sqrt(1.0 - ab) * eps


def ancestral_step(schedule: Schedule, x_k, eps_pred, k, z) -> jax.Array:
    """Paper appendix: x_{k-1} = x_k/sqrt(a_k) - b_k/sqrt(a_k (1 - abar_k)) eps + sqrt(b_k) z (no z at k=1)."""
    i = jnp.asarray(k) - 1
    a, b, ab = schedule.alphas[i], schedule.betas[i], schedule.alpha_bars[i]
    mean = x_k / jnp.sqrt(a) - b / jnp.sqrt(a * (1.0 - ab)) * eps_pred
    return mean + jnp.where(k > 1, jnp.sqrt(b), 0.0) * z


def posterior_step(schedule: Schedule, x_k, eps_pred, k, z, lo=None, hi=None) -> jax.Array:
    """Official-code step: x0_hat clamped to [lo, hi], DDPM posterior mean, variance beta~_k, output clamped."""
    i = jnp.asarray(k) - 1
    a, b = schedule.alphas[i], schedule.betas[i]
    ab, ab_prev = schedule.alpha_bars[i], schedule.alpha_bars_prev[i]
    x0 = (x_k - jnp.sqrt(1.0 - ab) * eps_pred) / jnp.sqrt(ab)
    if lo is not None:
        x0 = jnp.clip(x0, lo, hi)
    mean = b * jnp.sqrt(ab_prev) / (1.0 - ab) * x0 + (1.0 - ab_prev) * jnp.sqrt(a) / (1.0 - ab) * x_k
    x = mean + jnp.where(k > 1, jnp.sqrt(schedule.posterior_var[i]), 0.0) * z
    if lo is not None:
        x = jnp.clip(x, lo, hi)
    return x


# --------------------------------------------------------------------------------------------
# Network
# --------------------------------------------------------------------------------------------


def sinusoidal_embedding(t, dim: int) -> jax.Array:
    """Transformer-style embedding [sin(t f_i), cos(t f_i)], f_i = 10000^(-i/(dim/2 - 1))."""
    half = dim // 2
    freqs = jnp.exp(-math.log(10000.0) * jnp.arange(half) / (half - 1))
    args = jnp.asarray(t, jnp.float32)[..., None] * freqs
    return jnp.concatenate([jnp.sin(args), jnp.cos(args)], axis=-1)


class _MishMLP(nn.Module):
    out_dim: int
    hidden: int
    num_layers: int

    @nn.compact
    def __call__(self, x):
        for _ in range(self.num_layers):
            x = jax.nn.mish(nn.Dense(self.hidden)(x))
        return nn.Dense(self.out_dim)(x)


class Denoiser(nn.Module):
    """eps-networks for the next state (``__call__``) and, for BC, the action (``eps_action``)."""

    state_dim: int
    action_dim: int
    hidden: int = 256
    num_layers: int = 3
    time_dim: int = 16

    def setup(self):
        self.time_in = nn.Dense(2 * self.time_dim)
        self.time_out = nn.Dense(self.time_dim)
        self.state_head = _MishMLP(self.state_dim, self.hidden, self.num_layers)
        self.action_head = _MishMLP(self.action_dim, self.hidden, self.num_layers)

    def time_embedding(self, t):
        return self.time_out(jax.nn.mish(self.time_in(sinusoidal_embedding(t, self.time_dim))))

    def __call__(self, x_k, s, a, t):
        return self.state_head(jnp.concatenate([s, a, self.time_embedding(t), x_k], axis=-1))

    def eps_action(self, a_k, s, t):
        return self.action_head(jnp.concatenate([a_k, self.time_embedding(t), s], axis=-1))

    def init_both(self, x_k, s, a, t):
        return self(x_k, s, a, t), self.eps_action(a, s, t)


# --------------------------------------------------------------------------------------------
# State, normalisation
# --------------------------------------------------------------------------------------------


@struct.dataclass
class NormStats:
    mean: jax.Array  # [m]
    std: jax.Array  # [m]


@struct.dataclass
class DiffusionState:
    params: dict
    ema_params: dict  # sampling parameters: EMA of params if ema_decay > 0, else equal to params
    opt_state: optax.OptState
    norm: NormStats
    num_updates: jax.Array  # int32


def buffer_state_stats(buffer: RingBuffer, min_std: float) -> NormStats:
    """Per-dimension mean/std of s and s' pooled over the buffer's valid entries (std >= min_std)."""
    data: Transition = buffer.data
    valid = (jnp.arange(buffer.capacity) < buffer.count).astype(jnp.float32)[:, None]
    n = 2.0 * jnp.maximum(buffer.count, 1).astype(jnp.float32)
    mean = (jnp.sum(valid * data.s, 0) + jnp.sum(valid * data.s_next, 0)) / n
    var = (jnp.sum(valid * (data.s - mean) ** 2, 0) + jnp.sum(valid * (data.s_next - mean) ** 2, 0)) / n
    return NormStats(mean=mean, std=jnp.maximum(jnp.sqrt(var), min_std))


def normalize(norm: NormStats, x) -> jax.Array:
    return (x - norm.mean) / norm.std


def denormalize(norm: NormStats, x) -> jax.Array:
    return x * norm.std + norm.mean


# --------------------------------------------------------------------------------------------
# The model: init, loss, training, sampling, synthesis
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class DiffusionModel:
    """Pure functions of one ``DiffusionConfig`` (build with ``make_diffusion``)."""

    config: DiffusionConfig

    @property
    def net(self) -> Denoiser:
        c = self.config
        return Denoiser(c.state_dim, c.action_dim, c.hidden, c.num_layers, c.time_dim)

    @property
    def schedule(self) -> Schedule:
        c = self.config
        return vp_schedule(c.num_steps, c.beta_min, c.beta_max)

    @property
    def optimizer(self):
        return optax.adam(self.config.lr)

    def init(self, key: jax.Array) -> DiffusionState:
        c = self.config
        s = jnp.zeros((1, c.state_dim))
        a = jnp.zeros((1, c.action_dim))
        params = self.net.init(key, s, s, a, jnp.zeros((1,)), method=Denoiser.init_both)
        m = c.state_dim
        std = jnp.full((m,), c.scale if c.normalizer == "scale" else 1.0, jnp.float32)
        return DiffusionState(params, params, self.optimizer.init(params), NormStats(jnp.zeros((m,)), std), jnp.int32(0))

    def loss(self, params, key: jax.Array, s, a, s_next) -> jax.Array:
        """Noise-prediction loss on a normalised batch (s, a, s' each [B, .]); + BC loss if train_bc."""
        c, sched = self.config, self.schedule
        B = s.shape[0]
        k_k, k_e, k_ka, k_ea = jax.random.split(key, 4)
        k = jax.random.randint(k_k, (B,), 1, c.num_steps + 1)
        eps = jax.random.normal(k_e, s_next.shape)
        pred = self.net.apply(params, q_sample(sched, s_next, k, eps), s, a, k - 1)
        loss = jnp.mean((eps - pred) ** 2)
        if c.train_bc:
            ka = jax.random.randint(k_ka, (B,), 1, c.num_steps + 1)
            eps_a = jax.random.normal(k_ea, a.shape)
            pred_a = self.net.apply(params, q_sample(sched, a, ka, eps_a), s, ka - 1, method=Denoiser.eps_action)
            loss = loss + jnp.mean((eps_a - pred_a) ** 2)
        return loss

    def refresh_norm(self, state: DiffusionState, buffer: RingBuffer) -> DiffusionState:
        if self.config.normalizer != "buffer":
            return state
        return state.replace(norm=buffer_state_stats(buffer, self.config.min_std))

    @jax.named_scope("diffusion_train")  # names its kernels in a profile
    def train_steps(self, state: DiffusionState, key: jax.Array, buffer: RingBuffer, num_steps: int):
        """``num_steps`` (static) Adam steps on uniform batches from ``buffer`` (a lax.scan).

        Refreshes the normaliser from the buffer first (``normalizer='buffer'``). Returns (state,
        per-step losses [num_steps]). The buffer must be non-empty.
        """
        state = self.refresh_norm(state, buffer)
        norm, opt = state.norm, self.optimizer

        decay = self.config.ema_decay

        def one(carry, k):
            params, ema, opt_state = carry
            k_b, k_l = jax.random.split(k)
            b: Transition = buffer_sample(buffer, k_b, self.config.batch_size)
            s, sn = normalize(norm, b.s), normalize(norm, b.s_next)
            loss, grads = jax.value_and_grad(self.loss)(params, k_l, s, b.u, sn)
            updates, opt_state = opt.update(grads, opt_state, params)
            params = optax.apply_updates(params, updates)
            ema = optax.incremental_update(params, ema, 1.0 - decay) if decay > 0 else params
            return (params, ema, opt_state), loss

        carry = (state.params, state.ema_params, state.opt_state)
        (params, ema, opt_state), losses = jax.lax.scan(one, carry, jax.random.split(key, num_steps))
        new = state.replace(params=params, ema_params=ema, opt_state=opt_state, num_updates=state.num_updates + num_steps)
        return new, losses

    def _reverse(self, key, shape, eps_fn, lo, hi):
        c, sched = self.config, self.schedule
        k0, kz = jax.random.split(key)
        x = jax.random.normal(k0, shape)

        def one(x, inp):
            k, kk = inp
            eps = eps_fn(x, k)
            z = jax.random.normal(kk, shape)
            if c.sampler == "ancestral":
                return ancestral_step(sched, x, eps, k, z), None
            return posterior_step(sched, x, eps, k, z, lo, hi), None

        ks = jnp.arange(c.num_steps, 0, -1)
        x, _ = jax.lax.scan(one, x, (ks, jax.random.split(kz, c.num_steps)))
        return x

    def sample_next_state(self, state: DiffusionState, key: jax.Array, s, a) -> jax.Array:
        """s' ~ p_phi(s' | s, a) via the reverse chain; s [B, m], a [B, d_a] -> [B, m] in raw units."""
        c, norm = self.config, state.norm
        s_n = normalize(norm, s)
        lo = hi = None
        if c.state_clip is not None:
            lo, hi = normalize(norm, -c.state_clip), normalize(norm, c.state_clip)
        eps_fn = lambda x, k: self.net.apply(state.ema_params, x, s_n, a, jnp.full(x.shape[:-1], k - 1))
        return denormalize(norm, self._reverse(key, s.shape[:-1] + (c.state_dim,), eps_fn, lo, hi))

    def sample_action(self, state: DiffusionState, key: jax.Array, s) -> jax.Array:
        """a ~ p_phi(a | s) from the behaviour-cloning head (meaningful only if trained), clipped to [-1, 1]."""
        c = self.config
        s_n = normalize(state.norm, s)
        eps_fn = lambda x, k: self.net.apply(
            state.ema_params, x, s_n, jnp.full(x.shape[:-1], k - 1), method=Denoiser.eps_action
        )
        return jnp.clip(self._reverse(key, s.shape[:-1] + (c.action_dim,), eps_fn, -1.0, 1.0), -1.0, 1.0)

    def heldout_loss(self, state: DiffusionState, key: jax.Array, s, a, s_next, draws: int = 16) -> jax.Array:
        """The training loss of the current parameters on transitions (s, a, s' each [B, .]) it has not
        been trained on, normalised as training normalises, averaged over ``draws`` noise draws."""
        s_n, sn_n = normalize(state.norm, s), normalize(state.norm, s_next)
        losses = jax.vmap(lambda k: self.loss(state.params, k, s_n, a, sn_n))(jax.random.split(key, draws))
        return jnp.mean(losses)

    def synthesize(
        self,
        state: DiffusionState,
        key: jax.Array,
        real_buffer: RingBuffer,
        n: int,
        reward_fn: Callable,
        syn_action: str = "uniform",
        syn_reward: str = "recompute",
        action_fn: Callable | None = None,
    ) -> Transition:
        """``n`` synthetic transitions (docs/design.md §7) as a Transition batch with leading axis n.

        s from uniformly drawn real transitions; a ~ U[-1,1]^{d_a} ('uniform'), from the BC head
        ('bc') or ``action_fn(key, s)`` ('policy': the teacher's current policy, [n, m] -> [n, d_a]);
        s' from the reverse chain; r = reward_fn(s, a, s') ('recompute', vmapped over the batch) or
        the source's r ('copy'); done copied from the source.
        """
        if syn_action not in SYN_ACTIONS:
            raise ValueError(f"syn_action must be one of {SYN_ACTIONS}, got {syn_action!r}")
        if syn_reward not in SYN_REWARDS:
            raise ValueError(f"syn_reward must be one of {SYN_REWARDS}, got {syn_reward!r}")
        if syn_action == "bc" and not self.config.train_bc:
            raise ValueError("syn_action='bc' needs a model built with DiffusionConfig(train_bc=True)")
        if syn_action == "policy" and action_fn is None:
            raise ValueError("syn_action='policy' needs action_fn, the teacher's policy (key, s) -> a")
        k_src, k_a, k_s = jax.random.split(key, 3)
        src: Transition = buffer_sample(real_buffer, k_src, n)
        if syn_action == "uniform":
            a = jax.random.uniform(k_a, (n, self.config.action_dim), jnp.float32, -1.0, 1.0)
        elif syn_action == "policy":
            a = jnp.asarray(action_fn(k_a, src.s), jnp.float32)
        else:
            a = self.sample_action(state, k_a, src.s)
        s_next = self.sample_next_state(state, k_s, src.s, a)
        r = jax.vmap(reward_fn)(src.s, a, s_next) if syn_reward == "recompute" else src.r
        return Transition(s=src.s, u=a, r=jnp.asarray(r, jnp.float32), s_next=s_next, done=src.done)


def make_diffusion(config: DiffusionConfig) -> DiffusionModel:
    return DiffusionModel(config)
