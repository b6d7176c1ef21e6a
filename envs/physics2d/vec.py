"""Tiny 2-D vector helpers shared by the solver: on (..., 2) arrays, and ``V2`` (two per-world scalars)."""
from __future__ import annotations

import jax
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


@jax.tree_util.register_pytree_node_class
class V2:
    """A 2-vector held as two per-world scalars (``x``, ``y``) rather than one (..., 2) array.

    The solver's iteration loops use it: their bodies are then purely elementwise over worlds, which
    is what a fused kernel (``envs.physics2d.fused``) needs, and XLA sees no stack/slice ops there.
    """

    __slots__ = ("x", "y")

    def __init__(self, x, y):
        self.x, self.y = x, y

    @classmethod
    def of(cls, a) -> "V2":
        """From a (..., 2) array."""
        return cls(a[..., 0], a[..., 1])

    def array(self):
        """Back to a (..., 2) array."""
        return jnp.stack([jnp.asarray(self.x), jnp.asarray(self.y)], -1)

    def tree_flatten(self):
        return (self.x, self.y), None

    @classmethod
    def tree_unflatten(cls, _, children):
        return cls(*children)

    def __add__(self, o):
        return V2(self.x + o.x, self.y + o.y)

    def __sub__(self, o):
        return V2(self.x - o.x, self.y - o.y)

    def __mul__(self, s):
        return V2(self.x * s, self.y * s)

    def __rmul__(self, s):
        return V2(s * self.x, s * self.y)

    def dot(self, o):
        return self.x * o.x + self.y * o.y

    def cross(self, o):
        """z-component of self x o."""
        return self.x * o.y - self.y * o.x

    def where(self, cond, other) -> "V2":
        """Componentwise ``jnp.where(cond, self, other)``."""
        return V2(jnp.where(cond, self.x, other.x), jnp.where(cond, self.y, other.y))


def cross_sv2(s, v: V2) -> V2:
    """s x v for a scalar and a V2: (-s v_y, s v_x)."""
    return V2(-s * v.y, s * v.x)


def rotate2(angle, v: V2) -> V2:
    """R(angle) @ v for a V2."""
    return rotate_cs(jnp.cos(angle), jnp.sin(angle), v)


def rotate_cs(c, s, v: V2) -> V2:
    """R @ v for a V2, R given by its cosine and sine (to rotate several vectors by one angle)."""
    return V2(c * v.x - s * v.y, s * v.x + c * v.y)
