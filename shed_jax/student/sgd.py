"""Minibatch SGD over a fixed batch: the update loop of PPO and of PAIRED's adversary.

``minibatch_sgd`` runs ``epochs`` passes; each pass draws a permutation of the batch's n samples and
takes one optimiser step per minibatch of ``n // num_minibatches`` of them, in permutation order
(the last ``n % num_minibatches`` permuted samples sit out that pass). A pure function: two
``lax.scan``s, jittable and vmappable.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax


def minibatch_sgd(loss_fn: Callable, tx: optax.GradientTransformation, params: Any, opt_state: Any, batch: Any,
                  key: jax.Array, epochs: int, num_minibatches: int, grad_norm: bool = False):
    """``epochs`` x ``num_minibatches`` optimiser steps of ``loss_fn`` on shuffled minibatches of ``batch``.

    ``batch``: a pytree of arrays sharing a leading axis n >= ``num_minibatches``. ``loss_fn(params,
    minibatch) -> (loss, aux)`` with ``aux`` a dict of scalars. Epoch e shuffles with the e-th key of
    ``jax.random.split(key, epochs)``. ``grad_norm`` adds each step's global gradient norm (before
    ``tx``) to ``aux`` as ``"grad_norm"``.

    Returns ``((params, opt_state), aux)`` with every ``aux`` leaf of shape ``[epochs, num_minibatches]``.
    """
    n = jax.tree_util.tree_leaves(batch)[0].shape[0]
    size = n // num_minibatches
    if size < 1:
        raise ValueError(f"minibatch_sgd: {n} samples cannot fill {num_minibatches} minibatches")
    used = size * num_minibatches

    # a batch of float32 leaves travels as one (n, fields) array: one shuffle and one minibatch read
    # per step instead of one per leaf (on a GPU each is a kernel launch); the loss sees the leaves
    b_leaves, b_tree = jax.tree_util.tree_flatten(batch)
    packed = len(b_leaves) > 1 and all(jnp.ndim(x) >= 1 and jnp.result_type(x) == jnp.float32 for x in b_leaves)
    if packed:
        shapes = [jnp.shape(x)[1:] for x in b_leaves]
        widths = [int(np.prod(sh, dtype=np.int64)) for sh in shapes]
        starts = np.concatenate([[0], np.cumsum(widths)]).tolist()
        batch = jnp.concatenate([jnp.reshape(x, (n, w)) for x, w in zip(b_leaves, widths)], axis=1)

    def unpack(mb):
        if not packed:
            return mb
        return jax.tree_util.tree_unflatten(b_tree, [mb[:, a:a + w].reshape((mb.shape[0],) + sh)
                                                     for a, w, sh in zip(starts, widths, shapes)])

    def grads_and_aux(params, mb):
        grads, aux = jax.grad(loss_fn, has_aux=True)(params, unpack(mb))
        if grad_norm:
            aux = dict(aux, grad_norm=optax.tree.norm(grads))
        return grads, aux

    # float32 scalar aux leave the scan as one vector: one write per step into the stacked output
    # instead of one per scalar (on a GPU each write is a kernel launch)
    _, aux_shape = jax.eval_shape(grads_and_aux, params, jax.tree_util.tree_map(lambda x: x[:size], batch))
    aux_leaves, aux_tree = jax.tree_util.tree_flatten(aux_shape)
    stacked = bool(aux_leaves) and all(x.shape == () and x.dtype == jnp.float32 for x in aux_leaves)

    def step(carry, mb):
        params, opt_state = carry
        grads, aux = grads_and_aux(params, mb)
        updates, opt_state = tx.update(grads, opt_state, params)
        if stacked:
            aux = jnp.stack(jax.tree_util.tree_leaves(aux))
        return (optax.apply_updates(params, updates), opt_state), aux

    def epoch(carry, k):
        perm = jax.random.permutation(k, n)
        if used < n:
            perm = perm[:used]
        mbs = jax.tree_util.tree_map(lambda x: x[perm].reshape((num_minibatches, size) + x.shape[1:]), batch)
        return jax.lax.scan(step, carry, mbs)

    carry, aux = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, epochs))
    if stacked:
        aux = jax.tree_util.tree_unflatten(aux_tree, [aux[..., i] for i in range(aux.shape[-1])])
    return carry, aux
