"""Tiny 2-D vector helpers shared by the solver: on (..., 2) arrays, ``V2`` (two per-world scalars), and
the one ``sincos`` every rotation of the solver uses."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# sincos: Cody-Waite reduction by pi/4 in three parts whose products with the octant count are exact
# for |x| <= 8192, then minimax polynomials on [-pi/4, pi/4] (the constants of Cephes' sinf / cosf).
_FOUR_OVER_PI = np.float32(1.27323954473516)
_PI4 = tuple(np.float32(x) for x in (0.78515625, 2.4187564849853515625e-4, 3.77489497744594108e-8))
_SIN = tuple(np.float32(x) for x in (-1.9515295891e-4, 8.3321608736e-3, -1.6666654611e-1))
_COS = tuple(np.float32(x) for x in (2.443315711809948e-5, -1.388731625493765e-3, 4.166664568298827e-2))
LARGEST_ANGLE = np.float32(65536.0)  # radians: sincos's argument is clamped to this magnitude


def sincos(angle):
    """(sin, cos) of float32 ``angle``, elementwise, without branches or tables.

    Why not ``jnp.sin`` / ``jnp.cos``: on a GPU each is a library call with a slow path for huge
    arguments (a branch and a local-memory table), which splits a fused solver kernel's straight-line
    body into many blocks; here both share one reduction and the body stays one block. Absolute error
    below 1e-7 for |angle| <= 8192 (tests/test_vec.py), against about 6e-8 for ``jnp.sin`` (so near a
    zero of sin the relative error is larger); odd (sin) and even (cos) but for the sign of a zero.
    Beyond 8192 the error grows, and from ``LARGEST_ANGLE`` on the result is that of
    ``±LARGEST_ANGLE``: bounded, and meaningless, as a body turned ten thousand times has diverged.
    Backends round the polynomials as they contract multiply-adds (XLA:CPU and, with
    ``shed_jax/xla_gpu.py``, GPUs fuse them), so results differ between backends in the last bits.
    """
    x = jnp.asarray(angle, jnp.float32)
    ax = jnp.minimum(jnp.abs(x), LARGEST_ANGLE)  # keeps the octant count an int32 and the result in [-1, 1]
    j = (ax * _FOUR_OVER_PI).astype(jnp.int32)
    j = j + (j & 1)  # the nearest even octant: the reduced argument lies in [-pi/4, pi/4]
    y = j.astype(jnp.float32)
    z = ((ax - y * _PI4[0]) - y * _PI4[1]) - y * _PI4[2]
    zz = z * z
    s = ((_SIN[0] * zz + _SIN[1]) * zz + _SIN[2]) * zz * z + z
    c = ((_COS[0] * zz + _COS[1]) * zz + _COS[2]) * zz * zz - np.float32(0.5) * zz + np.float32(1.0)
    q = j & 7  # 0, 2, 4 or 6: quarter turns of 0, 1, 2 or 3
    swap = (q == 2) | (q == 6)
    sin_ = jnp.where(swap, c, s) * jnp.where((q >= 4) != (x < 0), np.float32(-1.0), np.float32(1.0))
    cos_ = jnp.where(swap, s, c) * jnp.where((q == 2) | (q == 4), np.float32(-1.0), np.float32(1.0))
    return sin_, cos_


def cross(a, b):
    """z-component of a x b for 2-vectors."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def cross_sv(s, v):
    """s x v for a scalar (angular velocity) and a 2-vector: (-s v_y, s v_x)."""
    return jnp.stack([-s * v[..., 1], s * v[..., 0]], -1)


def rotate(angle, v):
    """R(angle) @ v."""
    s, c = sincos(angle)
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
    s, c = sincos(angle)
    return rotate_cs(c, s, v)


def rotate_cs(c, s, v: V2) -> V2:
    """R @ v for a V2, R given by its cosine and sine (to rotate several vectors by one angle)."""
    return V2(c * v.x - s * v.y, s * v.x + c * v.y)
