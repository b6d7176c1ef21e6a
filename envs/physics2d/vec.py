"""Tiny 2-D vector helpers on (..., 2) arrays (cross products, rotations) shared by the solver."""
from __future__ import annotations

import jax.numpy as jnp


def cross(a, b):
    """z-component of a x b for 2-vectors."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def cross_sv(s, v):
    """s x v for a scalar (angular velocity) and a 2-vector: (-s v_y, s v_x)."""
    return jnp.stack([-s * v[..., 1], s * v[..., 0]], -1)


def rotate(angle, v):
    """R(angle) @ v."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]
