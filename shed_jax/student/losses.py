"""GAE and the PPO loss terms, as small pure functions on arrays.

Time-major conventions: arrays are ``[T, ...]`` with step t holding the transition
``(s_t, a_t, r_t, s'_t)``. ``next_values[t]`` is the value to bootstrap from after step t, already
masked by the caller: ``V(s'_t)`` if the episode continued or was truncated by the time limit
(``s'_t`` is the pre-reset observation ``info["final_obs"]``), and 0 if it terminated. ``dones[t]``
cuts the GAE recursion at any episode end (termination or truncation), since the next step
belongs to a new episode.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def gae(rewards, values, next_values, dones, gamma, gae_lambda):
    """Generalised advantage estimates and value targets (returns = advantages + values).

    delta_t = r_t + gamma * next_values_t - values_t
    A_t     = delta_t + gamma * lambda * (1 - done_t) * A_{t+1},   A_T = 0
    """
    deltas = rewards + gamma * next_values - values
    cont = 1.0 - dones.astype(jnp.float32)

    def back(carry, x):
        delta, c = x
        adv = delta + gamma * gae_lambda * c * carry
        return adv, adv

    _, adv = jax.lax.scan(back, jnp.zeros_like(deltas[0]), (deltas, cont), reverse=True)
    return adv, adv + values


def bootstrap_values(final_values, terminated):
    """Value to bootstrap from after each step: V(final_obs), or 0 on a true termination."""
    return jnp.where(terminated, 0.0, final_values)


def mean(x, weights=None):
    """``jnp.mean(x)``; with ``weights`` (0/1 or non-negative, the shape of ``x``) the weighted mean,
    0 when every weight is 0. The masked PPO update (a level played without gradients) uses it."""
    if weights is None:
        return jnp.mean(x)
    return jnp.sum(x * weights) / jnp.maximum(jnp.sum(weights), 1e-8)


def normalize_advantages(adv, eps: float = 1e-8, weights=None):
    if weights is None:
        return (adv - adv.mean()) / (adv.std() + eps)
    mu = mean(adv, weights)
    return (adv - mu) / (jnp.sqrt(mean((adv - mu) ** 2, weights)) + eps)


def clipped_surrogate(log_prob, old_log_prob, advantages, clip_eps, weights=None):
    """PPO clipped policy loss (to minimise): -mean(min(rho*A, clip(rho, 1-eps, 1+eps)*A))."""
    ratio = jnp.exp(log_prob - old_log_prob)
    unclipped = ratio * advantages
    clipped = jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages
    return -mean(jnp.minimum(unclipped, clipped), weights)


def value_loss(values, old_values, targets, clip_eps, clip: bool, weights=None):
    """0.5 * mean squared error; with `clip`, the max of the clipped and unclipped errors (PPO2)."""
    err = (values - targets) ** 2
    if clip:
        v_clipped = old_values + jnp.clip(values - old_values, -clip_eps, clip_eps)
        err = jnp.maximum(err, (v_clipped - targets) ** 2)
    return 0.5 * mean(err, weights)


def ppo_loss(log_prob, old_log_prob, advantages, values, old_values, targets, entropy, hparams, clip_value: bool,
             weights=None):
    """Total loss = policy + vf_coef * value - ent_coef * entropy, with the terms for logging.
    ``weights``: per-sample weights of every mean (None: all samples count alike)."""
    pg = clipped_surrogate(log_prob, old_log_prob, advantages, hparams.clip_eps, weights)
    vl = value_loss(values, old_values, targets, hparams.clip_eps, clip_value, weights)
    ent = mean(entropy, weights)
    total = pg + hparams.vf_coef * vl - hparams.ent_coef * ent
    ratio = jnp.exp(log_prob - old_log_prob)
    aux = {
        "loss": total,
        "policy_loss": pg,
        "value_loss": vl,
        "entropy": ent,
        "approx_kl": mean((ratio - 1.0) - (log_prob - old_log_prob), weights),
        "clip_frac": mean((jnp.abs(ratio - 1.0) > hparams.clip_eps).astype(jnp.float32), weights),
    }
    return total, aux
