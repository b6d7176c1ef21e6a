"""Minibatch SGD over a fixed batch: the update loop of PPO and of PAIRED's adversary.

``minibatch_sgd`` runs ``epochs`` passes; each pass draws a permutation of the batch's n samples and
takes one optimiser step per minibatch of ``n // num_minibatches`` of them, in permutation order
(the last ``n % num_minibatches`` permuted samples sit out that pass). A pure function: two
``lax.scan``s, jittable and vmappable.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
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

    def step(carry, mb):
        params, opt_state = carry
        grads, aux = jax.grad(loss_fn, has_aux=True)(params, mb)
        updates, opt_state = tx.update(grads, opt_state, params)
        if grad_norm:
            aux = dict(aux, grad_norm=optax.tree.norm(grads))
        return (optax.apply_updates(params, updates), opt_state), aux

    def epoch(carry, k):
        perm = jax.random.permutation(k, n)
        if used < n:
            perm = perm[:used]
        mbs = jax.tree_util.tree_map(lambda x: x[perm].reshape((num_minibatches, size) + x.shape[1:]), batch)
        return jax.lax.scan(step, carry, mbs)

    return jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, epochs))
