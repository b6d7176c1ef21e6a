"""Orthogonal weight initialisation that does not call LAPACK on a CPU.

``jax.nn.initializers.orthogonal`` takes the Q factor of a QR decomposition of a Gaussian matrix.
On a CPU the QR is a LAPACK custom call, and under ``vmap`` (a student per seed) it is a *batched*
one, which jaxlib 0.10.2 splits over XLA:CPU's intra-op pool and then waits for from inside that
pool. The six independent QRs of a student init (actor and critic, three layers each) then
deadlock a machine whose pool has fewer threads than that, such as the 2-core CI machine
(shed_jax/xla_cpu.py has the native stack and the measurements).

So on a CPU this module computes the same Q with a Householder QR written in ``jax.numpy`` (one
``fori_loop`` over the columns; a Dense kernel is at most a few hundred wide, so it costs
nothing next to a run), and on every other platform it calls ``jax.nn.initializers.orthogonal``
itself, so GPU runs draw exactly the weights they drew before. Both take the same Gaussian draw
and fix the signs so that R has a positive diagonal, which makes Q unique: the two differ only by
rounding (tests/test_xla_cpu.py checks it against the library to 2e-6).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def householder_q(a: jax.Array) -> jax.Array:
    """Q (``m x n``, orthonormal columns) of ``a = Q R`` for ``m >= n``, with ``diag(R) >= 0``."""
    m, n = a.shape
    rows = jnp.arange(m)

    def reflect(k, carry):
        r, q = carry
        x = jnp.where(rows >= k, r[:, k], 0.0)  # the column below the diagonal
        alpha = -jnp.where(x[k] >= 0, 1.0, -1.0) * jnp.linalg.norm(x)  # R[k, k]; sign avoids cancellation
        v = x.at[k].add(-alpha)
        vv = v @ v
        beta = jnp.where(vv > 0, 2.0 / jnp.where(vv > 0, vv, 1.0), 0.0)  # H = I - beta v v^T
        r = r - beta * jnp.outer(v, v @ r)
        q = q - beta * jnp.outer(q @ v, v)  # Q = H_0 H_1 ... H_k
        return r, q

    r, q = jax.lax.fori_loop(0, n, reflect, (a, jnp.eye(m, dtype=a.dtype)))
    signs = jnp.where(jnp.diagonal(r[:n, :n]) < 0, -1.0, 1.0).astype(a.dtype)
    return q[:, :n] * signs


def orthogonal(scale: float = 1.0):
    """A 2-D (Dense kernel) initializer equal to ``jax.nn.initializers.orthogonal(scale)``, without
    LAPACK on a CPU (module docstring)."""
    library = jax.nn.initializers.orthogonal(scale)

    def init(key, shape, dtype=jnp.float32):
        if len(shape) != 2:
            raise ValueError(f"orthogonal: expected a 2-D kernel shape, got {tuple(shape)}")
        n_rows, n_cols = shape

        def on_cpu(k):
            z = jax.random.normal(k, (max(n_rows, n_cols), min(n_rows, n_cols)), dtype)
            q = householder_q(z)
            return jnp.asarray(scale, dtype) * (q.T if n_rows < n_cols else q)

        return jax.lax.platform_dependent(key, cpu=on_cpu, default=lambda k: library(k, shape, dtype))

    return init
