"""Spread a vmapped batch of runs (seeds x hyperparameter points) over every visible device.

A run batch is a pytree whose leaves all carry the same leading axis (one entry per run). Runs are
independent, so the batch axis is the one axis worth sharding: a 1-D mesh over all devices with
axis name ``"batch"`` and ``NamedSharding(mesh, P("batch"))`` on every leaf. The same code uses one
device (a mesh of one) or N. Each device runs the vmapped program on its own slice of the batch
(``shard_map``, see ``per_device``), and no run talks to another.

    mesh = batch_mesh()                                  # all devices of all processes
    inputs, n = pad_batch(inputs, mesh.size)             # or pad=False: raise if not divisible
    state = sharded_init(init, mesh)(*put_batch(inputs, mesh))
    run_chunk = sharded_run(run, mesh)                   # jit(vmap(run, in_axes=(0, None, None)))
    state, metrics = run_chunk(state, num_steps, start_step)
    metrics = unpad(to_host(metrics), n)

Batches that do not divide by the device count are **padded** by default (``pad_batch`` repeats the
last run; ``unpad`` drops the copies after the results come back): a sweep's size is seeds x points,
which rarely divides by the GPU count, and the padded runs cost at most ``devices - 1`` extra runs
of compute. ``pad_batch(..., pad=False)`` raises a ValueError instead, naming both sizes.

Multi-host (not tested here; see docs/sweeps.md): call ``jax.distributed.initialize()`` first in
every process, then the mesh spans every process's devices. ``put_batch`` builds global arrays
with ``jax.make_array_from_callback`` from the full host batch that every process computes
identically (keys and hyperparameters are cheap and deterministic), and ``to_host`` gathers
sharded results with ``multihost_utils.process_allgather`` when there is more than one process.
"""
from __future__ import annotations

from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

AXIS = "batch"


def batch_mesh(devices: Sequence[Any] | None = None) -> Mesh:
    """A 1-D mesh named ``"batch"`` over ``devices`` (default: ``jax.devices()``, every process's)."""
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("batch_mesh needs at least one device")
    return Mesh(np.asarray(devices, dtype=object), (AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """Leading axis split over the mesh's devices, other axes whole."""
    return NamedSharding(mesh, P(AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, P())


def batch_size(tree: Any) -> int:
    """The common leading axis of every leaf; ValueError if the leaves disagree or are scalars."""
    sizes = set()
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        shape = np.shape(leaf)
        if not shape:
            raise ValueError(f"batch leaf {jax.tree_util.keystr(path)} is a scalar; every leaf needs a leading batch axis")
        sizes.add(shape[0])
    if len(sizes) != 1:
        raise ValueError(f"batch leaves disagree on the leading axis: sizes {sorted(sizes)}")
    return sizes.pop()


def padded_size(n: int, multiple: int) -> int:
    """The smallest multiple of ``multiple`` that is >= n."""
    if n < 1 or multiple < 1:
        raise ValueError(f"padded_size needs n >= 1 and multiple >= 1, got n={n}, multiple={multiple}")
    return -(-n // multiple) * multiple


def pad_batch(tree: Any, multiple: int, *, pad: bool = True) -> tuple[Any, int]:
    """``(tree padded to a multiple of ``multiple`` along axis 0, original size)``.

    Padding repeats the last entry (a valid run, so no NaNs or invalid configurations appear); drop
    the copies with ``unpad``. With ``pad=False`` a size that does not divide raises a ValueError.
    """
    n = batch_size(tree)
    target = padded_size(n, multiple)
    if target == n:
        return tree, n
    if not pad:
        raise ValueError(
            f"a batch of {n} runs does not divide over {multiple} devices; use a multiple of {multiple} "
            f"(e.g. {target}) or let pad_batch pad it"
        )

    def grow(x):
        xp = jnp if isinstance(x, jax.Array) else np
        x = xp.asarray(x)
        return xp.concatenate([x, xp.repeat(x[-1:], target - n, axis=0)])

    return jax.tree_util.tree_map(grow, tree), n


def unpad(tree: Any, n: int) -> Any:
    """The first ``n`` entries of every leaf (undoes ``pad_batch``)."""
    return jax.tree_util.tree_map(lambda x: x[:n], tree)


def put_batch(tree: Any, mesh: Mesh) -> Any:
    """Place a host batch (every leaf's axis 0 divisible by the mesh size) as global sharded arrays.

    Every process must pass the same full batch; each device receives its slice.
    """
    n = batch_size(tree)
    if n % mesh.size:
        raise ValueError(f"put_batch: {n} runs do not divide over {mesh.size} devices; pad_batch first")
    sharding = batch_sharding(mesh)

    def place(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])

    return jax.tree_util.tree_map(place, tree)


def sharded_init(init: Callable, mesh: Mesh) -> Callable:
    """``jit(vmap(init))`` taking and returning batches sharded over the mesh's ``"batch"`` axis."""
    s = batch_sharding(mesh)
    return jax.jit(per_device(jax.vmap(init), mesh, P(AXIS)), in_shardings=s, out_shardings=s)


def sharded_run(run: Callable, mesh: Mesh) -> Callable:
    """``jit(vmap(run, in_axes=(0, None, None)))`` with ``num_steps`` static, sharded over the batch.

    ``run(state, num_steps, start_step)`` is the loop's per-run function (``shed_jax.loop``); the
    state comes in and goes out split over devices; ``start_step`` is shared by all runs (replicated),
    so the loop's schedule conditions stay unbatched.
    """
    s = batch_sharding(mesh)

    def chunk(state, num_steps, start_step):
        local = lambda st, t: jax.vmap(run, in_axes=(0, None, None))(st, num_steps, t)  # noqa: E731
        return per_device(local, mesh, (P(AXIS), P()))(state, start_step)

    return jax.jit(chunk, static_argnums=1, in_shardings=(s, replicated(mesh)), out_shardings=s)


def per_device(fn: Callable, mesh: Mesh, in_specs) -> Callable:
    """``fn`` run by every device on its own slice of the batch (``shard_map``).

    ``in_specs``: per argument, ``P("batch")`` (split along the leading, run axis) or ``P()`` (the
    same on every device); a single spec applies to all. Every output is split. The runs are
    independent, so this is the same computation as the plain vmap. Writing it per device keeps
    custom kernels (the lander's fused solver, ``envs/physics2d/fused.py``) away from XLA's SPMD
    partitioner, which has no rule to split a Pallas call (an opaque custom call) by worlds.
    """
    return jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=P(AXIS), check_vma=False)


def devices_of(tree: Any) -> set:
    """Every device holding a piece of any leaf of ``tree``."""
    out = set()
    for leaf in jax.tree_util.tree_leaves(tree):
        out |= set(leaf.sharding.device_set)
    return out


def to_host(tree: Any) -> Any:
    """numpy copies of a (possibly sharded) pytree; gathers across processes when there are several."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return jax.tree_util.tree_map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))
    return jax.tree_util.tree_map(np.asarray, jax.device_get(tree))
