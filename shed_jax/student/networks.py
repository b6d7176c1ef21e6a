"""Actor and critic networks and the two action distributions the student uses.

Separate actor and critic MLPs (docs/design.md §10.1: 64-64 tanh, orthogonal init). Hidden layers use
orthogonal(sqrt 2) weights; the policy head uses orthogonal(0.01) so the initial policy is close
to uniform / zero-mean, and the value head orthogonal(1), as in PureJaxRL/CleanRL. The orthogonal
initializer is ``jax.nn.initializers.orthogonal`` except on a CPU, where a LAPACK-free QR avoids
an XLA:CPU deadlock (shed_jax/student/orthogonal.py).

The distributions are hand-written (a few lines each) because distrax is not a dependency and
we only need log-prob, entropy, sampling and the mode for a categorical and a diagonal Gaussian.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from shed_jax.student.orthogonal import orthogonal

_ACT: dict[str, Callable] = {"tanh": jnp.tanh, "relu": nn.relu, "elu": nn.elu, "gelu": nn.gelu, "silu": nn.silu}


class MLP(nn.Module):
    """Dense layers with orthogonal init; the last layer is linear with gain `out_scale`."""

    hidden: Sequence[int]
    out_dim: int
    activation: str = "tanh"
    out_scale: float = 1.0

    @nn.compact
    def __call__(self, x):
        act = _ACT[self.activation]
        for h in self.hidden:
            x = act(nn.Dense(h, kernel_init=orthogonal(math.sqrt(2.0)), bias_init=nn.initializers.zeros)(x))
        return nn.Dense(self.out_dim, kernel_init=orthogonal(self.out_scale), bias_init=nn.initializers.zeros)(x)


def bounded_log_std(raw, lo: float = -math.inf, hi: float = math.inf):
    """The log-std a raw parameter stands for under soft bounds ``lo < log_std < hi`` (infinite: none).

    No bounds: ``raw`` itself. Both: ``lo + (hi - lo) * sigmoid(raw)``. Only a lower bound:
    ``lo + softplus(raw)``; only an upper: ``hi - softplus(raw)``. Smooth and strictly monotone, so a
    bound is approached but never reached and the gradient never vanishes exactly, unlike a clip.
    """
    if math.isinf(lo) and math.isinf(hi):
        return raw
    if math.isinf(hi):
        return lo + jax.nn.softplus(raw)
    if math.isinf(lo):
        return hi - jax.nn.softplus(raw)
    return lo + (hi - lo) * jax.nn.sigmoid(raw)


def raw_log_std(log_std: float, lo: float = -math.inf, hi: float = math.inf) -> float:
    """The inverse of :func:`bounded_log_std`: the raw value whose log-std is ``log_std`` (inside the bounds)."""
    if not lo < log_std < hi:
        raise ValueError(f"log-std {log_std:g} is not inside the bounds ({lo:g}, {hi:g})")
    inv_softplus = lambda y: y + math.log(-math.expm1(-y))  # noqa: E731
    if math.isinf(lo) and math.isinf(hi):
        return float(log_std)
    if math.isinf(hi):
        return inv_softplus(log_std - lo)
    if math.isinf(lo):
        return inv_softplus(hi - log_std)
    u = (log_std - lo) / (hi - lo)
    return math.log(u) - math.log1p(-u)


class Actor(nn.Module):
    """Policy network: logits (discrete) or (mean, log_std) with state-independent log-std.

    With ``log_std_min`` or ``log_std_max`` finite the parameter is ``log_std_raw`` and the log-std
    is :func:`bounded_log_std` of it (initially ``init_log_std``); without bounds it is ``log_std``.
    """

    hidden: Sequence[int]
    action_dim: int
    discrete: bool
    activation: str = "tanh"
    init_log_std: float = 0.0
    log_std_min: float = -math.inf
    log_std_max: float = math.inf

    @nn.compact
    def __call__(self, obs):
        out = MLP(self.hidden, self.action_dim, self.activation, out_scale=0.01)(obs)
        if self.discrete:
            return out
        lo, hi = self.log_std_min, self.log_std_max
        if math.isinf(lo) and math.isinf(hi):
            log_std = self.param("log_std", nn.initializers.constant(self.init_log_std), (self.action_dim,))
        else:
            raw = self.param("log_std_raw", nn.initializers.constant(raw_log_std(self.init_log_std, lo, hi)),
                             (self.action_dim,))
            log_std = bounded_log_std(raw, lo, hi)
        return out, jnp.broadcast_to(log_std, out.shape)


class Critic(nn.Module):
    """State-value network V(s) -> scalar."""

    hidden: Sequence[int]
    activation: str = "tanh"

    @nn.compact
    def __call__(self, obs):
        return MLP(self.hidden, 1, self.activation, out_scale=1.0)(obs)[..., 0]


# --------------------------------------------------------------------------------------------
# Distributions (pure functions on the actor's output)
# --------------------------------------------------------------------------------------------

_LOG_2PI = math.log(2.0 * math.pi)


def categorical_log_prob(logits, action):
    logp = jax.nn.log_softmax(logits)
    return jnp.take_along_axis(logp, action[..., None].astype(jnp.int32), axis=-1)[..., 0]


def categorical_entropy(logits):
    logp = jax.nn.log_softmax(logits)
    return -jnp.sum(jnp.exp(logp) * logp, axis=-1)


def gaussian_log_prob(mean, log_std, action):
    z = (action - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z**2 - log_std - 0.5 * _LOG_2PI, axis=-1)


def gaussian_entropy(log_std):
    return jnp.sum(log_std + 0.5 * (1.0 + _LOG_2PI), axis=-1)


def dist_log_prob(out, action, discrete: bool):
    return categorical_log_prob(out, action) if discrete else gaussian_log_prob(out[0], out[1], action)


def dist_entropy(out, discrete: bool):
    return categorical_entropy(out) if discrete else gaussian_entropy(out[1])


def dist_sample(key, out, discrete: bool):
    if discrete:
        return jax.random.categorical(key, out).astype(jnp.int32)
    mean, log_std = out
    return mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)


def dist_mode(out, discrete: bool):
    return jnp.argmax(out, axis=-1).astype(jnp.int32) if discrete else out[0]
