"""A per-world ``fori_loop`` that runs as one GPU kernel when it is vmapped over worlds.

Why this exists: the solver's Gauss-Seidel passes are tiny (a few dozen flops per constraint) and
strictly sequential, so XLA turns each pass into ~37 kernel launches (17 fusions and 20 copies of
the loop carry, docs/log/benchmarks.md "Why an iteration costs 21 µs") and a lander step spends ~1.7 ms of its 2.3 ms launching them.
Here the whole loop (all iterations) is one Pallas kernel: every GPU thread holds one world's carry
in registers for all the iterations. No library offers this (XLA's command buffers and unrolling
were measured and did not help), hence the hand-written kernel.

Contract: ``body(consts, carry) -> carry`` sees pytrees whose leaves are float32 *per-world
scalars* and uses only elementwise jnp ops (no stacking, slicing, gathers or array constants
captured from outside; Python / numpy scalars are fine). The same body then runs three ways:

* ``"xla"``: ``lax.fori_loop`` (the reference; used on CPU and when not vmapped);
* ``"pallas"``: under ``vmap``, one Triton kernel over blocks of worlds (GPU);
* ``"interpret"``: the same kernel through Pallas' interpreter (CPU tests of the kernel path).

Nested vmaps (seeds x environments) are flattened into one world axis by ``custom_vmap`` rules, so
the kernel always sees a flat (fields, worlds) array.

Skipping work no world needs: a const leaf wrapped in ``BlockAny`` (a per-world 0/1 flag, e.g. "this
contact touches") and ``when(flag, fn, operand)`` in the body. On the XLA paths ``when`` is plain
``fn(operand)``; in the kernel the flag is reduced once over the block's worlds before the loop and
``fn`` runs only in blocks where some world has it set. The caller guarantees that ``fn`` leaves the
operand of a world whose flag is 0 unchanged (up to the sign of zero), so the paths agree.
"""
from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
from jax import lax

MODES = ("auto", "xla", "pallas", "interpret")
_TRACING = threading.local()  # .in_kernel: True while this thread traces a kernel body (``when`` branches)
BLOCK = 128  # worlds per kernel instance (one per thread with 4 warps)
NUM_WARPS = 4  # Triton warps per kernel instance (32 threads each)


def resolve_mode(mode: str) -> str:
    """``"auto"`` means the Pallas kernel on GPU and plain XLA elsewhere."""
    if mode not in MODES:
        raise ValueError(f"solver kernel must be one of {MODES}, got {mode!r}")
    if mode == "auto":
        return "pallas" if jax.default_backend() == "gpu" else "xla"
    return mode


@jax.tree_util.register_pytree_node_class
class BlockAny:
    """A per-world 0/1 flag among a loop's consts; in the kernel the body sees its maximum over the block."""

    __slots__ = ("flag",)

    def __init__(self, flag):
        self.flag = flag

    def tree_flatten(self):
        return (self.flag,), None

    @classmethod
    def tree_unflatten(cls, _, children):
        return cls(*children)


def when(flag: BlockAny, fn, operand, enabled: bool = True):
    """``fn(operand)``, skipped in kernel blocks where ``flag`` is 0 for every world (see the module
    docstring: ``fn`` must leave a world whose flag is 0 unchanged). ``enabled=False`` never skips."""
    if not isinstance(flag, BlockAny):
        raise TypeError(f"fused.when needs a BlockAny flag from the loop's consts, got {type(flag).__name__}")
    if not (getattr(_TRACING, "in_kernel", False) and enabled):
        return fn(operand)
    return lax.cond(flag.flag > 0.5, fn, lambda x: x, operand)


def _is_flag(x) -> bool:
    return isinstance(x, BlockAny)


def per_world_fori_loop(n: int, body, consts, carry, *, mode: str = "auto", unroll: int = 1):
    """``carry = body(consts, carry)`` ``n`` times, for one world; see the module docstring."""
    mode = resolve_mode(mode)
    xla = lambda c, s: lax.fori_loop(0, n, lambda _, x: body(c, x), s, unroll=unroll)  # noqa: E731
    if mode == "xla" or n == 0:
        return xla(consts, carry)
    c_leaves, c_tree = jax.tree_util.tree_flatten(consts)
    s_leaves, s_tree = jax.tree_util.tree_flatten(carry)
    for x in c_leaves + s_leaves:
        if jnp.shape(x) != () or jnp.result_type(x) != jnp.float32:
            raise TypeError(f"per_world_fori_loop needs float32 per-world scalars, got {jnp.shape(x)} "
                            f"{jnp.result_type(x)}")
    nc = len(c_leaves)

    def run_one(*leaves):
        c = jax.tree_util.tree_unflatten(c_tree, leaves[:nc])
        s = jax.tree_util.tree_unflatten(s_tree, leaves[nc:])
        return tuple(jax.tree_util.tree_leaves(xla(c, s)))

    def run_many(*leaves):  # every leaf (W,): W worlds
        return tuple(_kernel(n, body, c_tree, s_tree, nc, leaves, mode == "interpret"))

    many = _flattening(run_many)
    one = jax.custom_batching.custom_vmap(run_one)

    @one.def_vmap
    def _rule(axis_size, in_batched, *leaves):
        leaves = [x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)) for x, b in zip(leaves, in_batched)]
        out = many(*leaves)
        return out, (True,) * len(out)

    leaves = [jnp.asarray(x, jnp.float32) for x in c_leaves + s_leaves]
    return jax.tree_util.tree_unflatten(s_tree, one(*leaves))


def _flattening(run_many):
    """``run_many`` over (W,) leaves, made vmappable by folding a new batch axis into W."""
    many = jax.custom_batching.custom_vmap(run_many)

    @many.def_vmap
    def _rule(axis_size, in_batched, *leaves):
        full = [x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)) for x, b in zip(leaves, in_batched)]
        w = full[0].shape[1]
        out = many(*[x.reshape(axis_size * w) for x in full])
        return tuple(y.reshape(axis_size, w) for y in out), (True,) * len(out)

    return many


def _pow2(k: int) -> int:
    return 1 << max(0, (k - 1).bit_length())


def _kernel(n, body, c_tree, s_tree, nc, leaves, interpret):
    """All ``n`` iterations for W worlds in one ``pallas_call`` over blocks of ``BLOCK`` worlds."""
    from jax.experimental import pallas as pl

    w = leaves[0].shape[0]
    f_in, f_out = len(leaves), len(leaves) - nc
    # Triton wants power-of-two block shapes: pad fields and worlds (padding worlds are zeros,
    # computed and dropped; the solver's divisions are guarded, so they stay finite).
    rows_in, rows_out, wp = _pow2(f_in), _pow2(f_out), -(-w // BLOCK) * BLOCK
    x = jnp.stack(leaves, 0)
    x = jnp.pad(x, ((0, rows_in - f_in), (0, wp - w)))

    def kernel(x_ref, o_ref):
        rows = [x_ref[f, :] for f in range(f_in)]
        c = jax.tree_util.tree_unflatten(c_tree, rows[:nc])
        # block-uniform flags: reduced once, before the loop
        c = jax.tree_util.tree_map(lambda x: BlockAny(jnp.max(x.flag)) if _is_flag(x) else x, c, is_leaf=_is_flag)
        s = jax.tree_util.tree_unflatten(s_tree, rows[nc:])
        _TRACING.in_kernel = True
        try:
            s = lax.fori_loop(0, n, lambda _, v: body(c, v), s)
        finally:
            _TRACING.in_kernel = False
        for g, v in enumerate(jax.tree_util.tree_leaves(s)):
            o_ref[g, :] = jnp.broadcast_to(jnp.asarray(v, jnp.float32), (BLOCK,))
        for g in range(f_out, rows_out):
            o_ref[g, :] = jnp.zeros((BLOCK,), jnp.float32)

    kwargs = {}
    if not interpret:
        from jax.experimental.pallas import triton as plt

        kwargs["compiler_params"] = plt.CompilerParams(num_warps=NUM_WARPS)
    out = pl.pallas_call(
        kernel,
        out_shape=jax.ShapeDtypeStruct((rows_out, wp), jnp.float32),
        grid=(wp // BLOCK,),
        in_specs=[pl.BlockSpec((rows_in, BLOCK), lambda i: (0, i))],
        out_specs=pl.BlockSpec((rows_out, BLOCK), lambda i: (0, i)),
        interpret=interpret,
        **kwargs,
    )(x)
    return [out[g, :w] for g in range(f_out)]
