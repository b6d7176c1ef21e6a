"""Gymnasium's hand-written Lunar Lander controller (docs/lander.md), as a jittable, vmappable function."""
from __future__ import annotations

import jax.numpy as jnp


def heuristic(obs, continuous: bool):
    """Action for one observation (8,) (vmap for batches): int32 scalar, or float32 (2,) if continuous."""
    obs = jnp.asarray(obs, jnp.float32)
    s0, s1, s2, s3, s4, s5, s6, s7 = (obs[..., i] for i in range(8))
    angle_targ = jnp.clip(0.5 * s0 + s2, -0.4, 0.4)  # point towards the pad, at most 22 degrees
    hover_targ = 0.55 * jnp.abs(s0)  # higher when far from the pad
    angle_todo = 0.5 * (angle_targ - s4) - s5
    hover_todo = 0.5 * (hover_targ - s1) - 0.5 * s3
    legs = (s6 != 0) | (s7 != 0)
    angle_todo = jnp.where(legs, 0.0, angle_todo)  # after touch-down only slow the fall
    hover_todo = jnp.where(legs, -0.5 * s3, hover_todo)
    if continuous:
        return jnp.clip(jnp.stack([20.0 * hover_todo - 1.0, -20.0 * angle_todo], -1), -1.0, 1.0)
    a = jnp.where(angle_todo > 0.05, 1, 0)
    a = jnp.where(angle_todo < -0.05, 3, a)
    a = jnp.where((hover_todo > jnp.abs(angle_todo)) & (hover_todo > 0.05), 2, a)
    return a.astype(jnp.int32)
