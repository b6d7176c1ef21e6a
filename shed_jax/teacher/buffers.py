"""Fixed-capacity ring buffers as pytrees, for the teacher's real and synthetic transitions.

A buffer is ``(data, pos, count)``: ``data`` is any pytree whose leaves carry a leading capacity
axis, ``pos`` the next write index, ``count`` the number of valid entries (<= capacity). When full,
new entries overwrite the oldest (FIFO), as the official code's replay buffers do.

Written by hand rather than with flashbax because flashbax is not a dependency of this project (not
installed); the handful of operations needed here (add, add-many, uniform sample, mixed sample) are a
few lines of ``dynamic_update``/``randint`` each and stay jittable with static shapes.

Sampling is uniform **with replacement** over the valid entries (``randint`` indices), which is
what a DDPG replay batch needs and keeps shapes static. Sampling an empty buffer returns entry 0 of
the (zero-initialised) storage; callers guard on ``count`` (the SHED thresholds do).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


@struct.dataclass
class Transition:
    """One teacher transition (s, u, r, s', done); batches carry leading axes on every field."""

    s: jax.Array  # [m] performance vector before the step
    u: jax.Array  # [d_a] teacher action in u-space [-1, 1]
    r: jax.Array  # [] teacher reward
    s_next: jax.Array  # [m] performance vector after the step
    done: jax.Array  # [] float 1.0 on the last transition of a teacher episode


def make_transition(state_dim: int, action_dim: int, batch: tuple = ()) -> Transition:
    """A zero transition (or a batch of them) with the given sizes: a template for ``buffer_init``."""
    z = lambda *shape: jnp.zeros(batch + shape, jnp.float32)
    return Transition(s=z(state_dim), u=z(action_dim), r=z(), s_next=z(state_dim), done=z())


@struct.dataclass
class RingBuffer:
    data: object  # pytree, every leaf [capacity, ...]
    pos: jax.Array  # int32 next write index
    count: jax.Array  # int32 number of valid entries

    @property
    def capacity(self) -> int:
        return jax.tree_util.tree_leaves(self.data)[0].shape[0]


def buffer_init(example, capacity: int) -> RingBuffer:
    """An empty buffer holding ``capacity`` items shaped like ``example`` (an unbatched pytree)."""
    if capacity < 1:
        raise ValueError(f"buffer capacity must be >= 1, got {capacity}")
    data = jax.tree_util.tree_map(lambda x: jnp.zeros((capacity,) + jnp.shape(x), jnp.asarray(x).dtype), example)
    return RingBuffer(data=data, pos=jnp.int32(0), count=jnp.int32(0))


def buffer_add(buf: RingBuffer, item) -> RingBuffer:
    """Append one item (unbatched pytree), overwriting the oldest when full."""
    data = jax.tree_util.tree_map(lambda d, x: d.at[buf.pos].set(jnp.asarray(x, d.dtype)), buf.data, item)
    cap = buf.capacity
    return RingBuffer(data=data, pos=(buf.pos + 1) % cap, count=jnp.minimum(buf.count + 1, cap))


def buffer_add_many(buf: RingBuffer, items) -> RingBuffer:
    """Append a batch (leading axis n, static, n <= capacity) in order, as n successive adds."""
    n = jax.tree_util.tree_leaves(items)[0].shape[0]
    cap = buf.capacity
    if n > cap:
        raise ValueError(f"cannot add {n} items at once to a buffer of capacity {cap}")
    idx = (buf.pos + jnp.arange(n)) % cap  # distinct since n <= cap
    data = jax.tree_util.tree_map(lambda d, x: d.at[idx].set(jnp.asarray(x, d.dtype)), buf.data, items)
    return RingBuffer(data=data, pos=(buf.pos + n) % cap, count=jnp.minimum(buf.count + n, cap))


def buffer_sample(buf: RingBuffer, key: jax.Array, batch_size: int):
    """``batch_size`` items drawn uniformly with replacement from the valid entries."""
    idx = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buf.count, 1))
    return jax.tree_util.tree_map(lambda d: d[idx], buf.data)


def num_real_in_batch(batch_size: int, psi) -> jax.Array:
    """floor(psi * batch_size) as an int32 array: the real part of a mixed batch (24 of 32 for psi = 0.75).

    ``psi`` may be traced (a dynamic hyperparameter); a concrete one outside [0, 1] raises. The
    product is float32 with 1e-4 added, so that e.g. 0.75 * 32 and 0.7 * 10 floor to 24 and 7 in
    any rounding.
    """
    try:
        v = np.asarray(psi, dtype=np.float64)
    except Exception:  # a tracer: nothing to check at trace time
        v = None
    if v is not None and not np.all((v >= 0.0) & (v <= 1.0)):
        raise ValueError(f"real-data ratio psi must lie in [0, 1], got {psi}")
    return jnp.floor(jnp.asarray(psi, jnp.float32) * batch_size + 1e-4).astype(jnp.int32)


def sample_mixed(real: RingBuffer, syn: RingBuffer, key: jax.Array, batch_size: int, psi):
    """A mixed batch with a dynamic real share: floor(psi * batch_size) real items first, synthetic ones after.

    Returns ``(batch, real_mask)``. The shapes are static for any psi: ``batch_size`` candidates
    are drawn from each buffer and ``real_mask`` (bool [batch_size], a prefix) picks the real ones,
    so psi can be traced and vmapped (a sweep over psi compiles once). ``reward.zscore_mixed`` takes
    the mask to z-score the two parts separately [official code: 24 real + 8 synthetic of 32].
    """
    k_real, k_syn = jax.random.split(key)
    mask = jnp.arange(batch_size) < num_real_in_batch(batch_size, psi)
    b_real, b_syn = buffer_sample(real, k_real, batch_size), buffer_sample(syn, k_syn, batch_size)
    pick = lambda x, y: jnp.where(mask.reshape((batch_size,) + (1,) * (x.ndim - 1)), x, y)
    return jax.tree_util.tree_map(pick, b_real, b_syn), mask
