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

Lanes (experimental, ``lanes=4``): a const or carry leaf may also be a *lane vector*, shape (4,)
per world, e.g. one entry per leg body for constraints that touch one body each and so commute. The
kernel then gives each world 4 threads, one per lane: lane vectors are (worlds, 4) tiles, per-world
scalars (worlds, 1) columns that every lane holds alike, so elementwise ops between them broadcast as
() and (4,) do on the XLA paths. :func:`lane` takes one entry of a lane vector as a per-world scalar,
:func:`lanes_of` makes a lane vector of per-world scalars, :func:`lane_min` the smallest entry; none
moves data between worlds. ``BlockAny`` flags may be lane vectors (reduced over the block's lanes too).

Skipping work no world needs: a const leaf wrapped in ``BlockAny`` (a per-world 0/1 flag, e.g. "this
contact touches") and ``when(flag, fn, operand)`` in the body. On the XLA paths ``when`` is plain
``fn(operand)``; in the kernel the flag is reduced once over the block's worlds before the loop and
``fn`` runs only in blocks where some world has it set. The caller guarantees that ``fn`` leaves the
operand of a world whose flag is 0 unchanged (up to the sign of zero), so the paths agree.
"""
from __future__ import annotations

import contextlib
import threading

import jax
import jax.numpy as jnp
from jax import lax

MODES = ("auto", "xla", "pallas", "interpret")
_TRACING = threading.local()  # .in_kernel: True while this thread traces a kernel body (``when`` branches)
BLOCK = 128  # worlds per kernel instance (one per thread with 4 warps)
NUM_WARPS = 4  # Triton warps per kernel instance (32 threads each)
TILE = 4  # per-world fields per memory access of the kernel's inputs and outputs (a power of two)
# Compiled kernels pad their worlds to at least MIN_WORLDS, so that loops run at different batches (a
# teacher's evaluation, a test set, the training rollout) are one kernel to XLA, which compiles a
# Triton call once per grid: a kernel of 8 or 40 blocks takes the same time on a GPU with more
# multiprocessors than that. The interpreter (CPU tests) pads to whole blocks only. ``pad_worlds_to``
# raises it for a program whose largest batch is larger (the driver: a run's training batch).
DEFAULT_MIN_WORLDS = 1024
MIN_WORLDS = DEFAULT_MIN_WORLDS


def pad_worlds_to(worlds: int) -> int:
    """From now on compiled kernels cover at least ``max(worlds, DEFAULT_MIN_WORLDS)`` worlds; returns
    that number. Process-wide, not per thread: programs compile in worker threads, and every program of
    a run must lower with the same padding (so its kernels are one set to XLA, and a resumed run's
    program is the fresh run's). Kernels traced before the call keep their padding."""
    global MIN_WORLDS
    if not (isinstance(worlds, int) and worlds >= 1):
        raise ValueError(f"pad_worlds_to needs a whole number of worlds >= 1, got {worlds!r}")
    MIN_WORLDS = max(int(worlds), DEFAULT_MIN_WORLDS)
    return MIN_WORLDS


_AUTO = threading.local()  # .mode: what "auto" resolves to inside ``auto_as`` (None: by the backend)


def resolve_mode(mode: str) -> str:
    """``"auto"`` means the Pallas kernel on GPU and plain XLA elsewhere (or ``auto_as``'s mode)."""
    if mode not in MODES:
        raise ValueError(f"solver kernel must be one of {MODES}, got {mode!r}")
    if mode == "auto":
        forced = getattr(_AUTO, "mode", None)
        return forced or ("pallas" if jax.default_backend() == "gpu" else "xla")
    return mode


@contextlib.contextmanager
def auto_as(mode: str):
    """Within the block (this thread), ``"auto"`` resolves to ``mode``: e.g. ``"pallas"`` to lower on
    any host the kernels a GPU run would compile (``lowering_platforms=("cuda",)``, nothing compiled)."""
    if mode not in MODES or mode == "auto":
        raise ValueError(f"auto_as needs one of {MODES[1:]}, got {mode!r}")
    before = getattr(_AUTO, "mode", None)
    _AUTO.mode = mode
    try:
        yield
    finally:
        _AUTO.mode = before


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


@jax.custom_batching.custom_vmap
def batch_any(flag):
    """A per-world bool scalar as it is outside ``vmap``; under ``vmap`` (nested ones too), whether it is
    set for any world of the batch, unbatched. A ``lax.cond`` on it then stays one branch for the whole
    batch (skipped where no world needs it) instead of both branches and a select; the caller
    guarantees the branch leaves a world whose own flag is False unchanged, so the results agree."""
    return flag


@batch_any.def_vmap
def _batch_any_rule(axis_size, in_batched, flag):
    # reduce this batch axis, then again through batch_any for any enclosing vmap's axis
    return batch_any(jnp.any(flag, axis=0) if in_batched[0] else flag), False


def lane(x, j: int):
    """Entry ``j`` of a lane vector ``x`` as a per-world scalar: a sum in which the other entries are
    -0.0, so exact but for the sign of zero (the sum starts from +0.0, so a -0.0 entry comes back 0.0)."""
    in_kernel = getattr(_TRACING, "in_kernel", False)
    idx = lax.broadcasted_iota(jnp.int32, jnp.shape(x), jnp.ndim(x) - 1)
    return jnp.sum(jnp.where(idx == j, x, -0.0), axis=-1, keepdims=in_kernel)


def lane_min(x):
    """The smallest entry of a lane vector ``x``, as a per-world scalar (exact)."""
    return jnp.min(x, axis=-1, keepdims=getattr(_TRACING, "in_kernel", False))


def lanes_of(*scalars):
    """The lane vector whose entry j is per-world scalar ``scalars[j]``."""
    in_kernel = getattr(_TRACING, "in_kernel", False)
    k = len(scalars)
    shape = (1, k) if in_kernel else (k,)
    idx = lax.broadcasted_iota(jnp.int32, shape, len(shape) - 1)
    out = jnp.asarray(scalars[-1], jnp.float32)
    for j in range(k - 2, -1, -1):
        out = jnp.where(idx == j, scalars[j], out)
    return jnp.broadcast_to(out, jnp.broadcast_shapes(jnp.shape(out), shape))


def _is_flag(x) -> bool:
    return isinstance(x, BlockAny)


def per_world_fori_loop(n: int, body, consts, carry, *, mode: str = "auto", unroll: int = 1, done=None,
                        lanes: int = 1):
    """``carry = body(consts, carry)`` ``n`` times, for one world; see the module docstring.

    ``done(carry)``, optional: a per-world 0/1 flag (e.g. Box2D's "position solved"). The caller
    guarantees that once it is 1, ``body`` returns the carry unchanged and it stays 1; the loop may then
    stop early with the same result. The XLA paths stop a batch when every world is done (a vmapped
    ``while_loop``), the kernel a block of ``BLOCK`` worlds (``BLOCK // lanes`` with lanes) when all of its
    worlds are. ``unroll``
    applies only without ``done``. ``lanes=4``: leaves may be lane vectors (module docstring); ``done``
    then returns a per-world scalar."""
    if lanes not in (1, TILE):
        raise ValueError(f"per_world_fori_loop: lanes must be 1 or {TILE} (the kernel's tile), got {lanes!r}")
    if done is None:
        xla = lambda c, s, _: (lax.fori_loop(0, n, lambda _, x: body(c, x), s, unroll=unroll), ())  # noqa: E731
    else:
        def xla(c, s, _):
            cond = lambda x: (x[0] < n) & (done(x[1]) < 0.5)  # noqa: E731
            return lax.while_loop(cond, lambda x: (x[0] + 1, body(c, x[1])), (jnp.int32(0), s))[1], ()
    step = lambda c, s, _: (body(c, s), ())  # noqa: E731
    return _per_world(n, step, xla, consts, carry, (), mode, done, lanes)[0]


def per_world_scan(body, consts, carry, xs, *, mode: str = "auto"):
    """``lax.scan`` for one world: ``(carry, y_i) = body(consts, carry, x_i)`` over the leading axis of
    ``xs``; returns ``(carry, ys)``. ``xs`` leaves are float32 ``(n,)`` per world, ``y_i`` leaves
    float32 per-world scalars (stacked to ``(n,)``); the body's contract is the module docstring's. In
    the kernel each iteration loads its row of ``xs`` and stores its row of ``ys`` (global memory), so
    per-iteration outputs cost no registers."""
    x_leaves = jax.tree_util.tree_leaves(xs)
    if not x_leaves:
        raise ValueError("per_world_scan needs at least one xs leaf (its length is the scan's)")
    n = jnp.shape(x_leaves[0])[0] if jnp.ndim(x_leaves[0]) else -1
    for x in x_leaves:
        if jnp.shape(x) != (n,) or jnp.result_type(x) != jnp.float32:
            raise TypeError(f"per_world_scan needs float32 xs of one shape (n,), got {jnp.shape(x)} {jnp.result_type(x)}")
    xla = lambda c, s, x: lax.scan(lambda s_, x_: body(c, s_, x_), s, x)  # noqa: E731
    return _per_world(n, body, xla, consts, carry, xs, mode)


def _per_world(n, step, xla, consts, carry, xs, mode, done=None, lanes=1):
    """Shared by the loop and the scan: ``xla(consts, carry, xs)`` is the reference, ``step`` one
    iteration ``(consts, carry, x_i) -> (carry, y_i)`` for the kernel, ``done`` the loop's early stop."""
    mode = resolve_mode(mode)
    if mode == "xla" or n == 0:
        return xla(consts, carry, xs)
    c_leaves, c_tree = jax.tree_util.tree_flatten(consts)
    s_leaves, s_tree = jax.tree_util.tree_flatten(carry)
    x_leaves, x_tree = jax.tree_util.tree_flatten(xs)
    shapes = ((), (lanes,)) if lanes > 1 else ((),)
    for x in c_leaves + s_leaves:
        if jnp.shape(x) not in shapes or jnp.result_type(x) != jnp.float32:
            raise TypeError(f"per_world_fori_loop needs float32 per-world scalars{' or lane vectors' * (lanes > 1)}, "
                            f"got {jnp.shape(x)} {jnp.result_type(x)}")
    lane_mask = tuple(jnp.shape(x) != () for x in c_leaves + s_leaves)
    nc, ns = len(c_leaves), len(s_leaves)
    # the per-iteration outputs' structure, from an abstract evaluation of one step
    y_shape = jax.eval_shape(lambda c, s, x: step(c, s, x)[1], consts, carry,
                             jax.tree_util.tree_map(lambda v: v[0], xs))
    y_tree = jax.tree_util.tree_structure(y_shape)

    def run_one(*leaves):
        c = jax.tree_util.tree_unflatten(c_tree, leaves[:nc])
        s = jax.tree_util.tree_unflatten(s_tree, leaves[nc:nc + ns])
        x = jax.tree_util.tree_unflatten(x_tree, leaves[nc + ns:])
        s, y = xla(c, s, x)
        return tuple(jax.tree_util.tree_leaves(s)) + tuple(jax.tree_util.tree_leaves(y))

    def run_many(*leaves):  # per-world leaves (W,) or (W, lanes), per-iteration leaves (W, n)
        if any(lane_mask):
            return tuple(_lane_kernel(n, step, c_tree, s_tree, nc, ns, leaves, lane_mask, mode == "interpret", lanes,
                                      done))
        return tuple(_kernel(n, step, c_tree, s_tree, x_tree, y_tree, nc, ns, leaves, mode == "interpret", done))

    many = _flattening(run_many)
    one = jax.custom_batching.custom_vmap(run_one)

    @one.def_vmap
    def _rule(axis_size, in_batched, *leaves):
        leaves = [x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)) for x, b in zip(leaves, in_batched)]
        out = many(*leaves)
        return out, (True,) * len(out)

    leaves = [jnp.asarray(x, jnp.float32) for x in c_leaves + s_leaves + x_leaves]
    out = one(*leaves)
    ny = y_tree.num_leaves
    s = jax.tree_util.tree_unflatten(s_tree, out[:len(out) - ny])
    return s, jax.tree_util.tree_unflatten(y_tree, out[len(out) - ny:])


def _flattening(run_many):
    """``run_many`` over (W, ...) leaves, made vmappable by folding a new batch axis into W."""
    many = jax.custom_batching.custom_vmap(run_many)

    @many.def_vmap
    def _rule(axis_size, in_batched, *leaves):
        full = [x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)) for x, b in zip(leaves, in_batched)]
        w = full[0].shape[1]
        out = many(*[x.reshape((axis_size * w,) + x.shape[2:]) for x in full])
        return tuple(y.reshape((axis_size, w) + y.shape[1:]) for y in out), (True,) * len(out)

    return many


def _pow2(k: int) -> int:
    return 1 << max(0, (k - 1).bit_length())


def _tiles(fields: int, tile: int) -> int:
    """Columns for ``fields`` per-world fields: whole tiles, a power of two in all (Triton's block shapes)."""
    return _pow2(-(-fields // tile) * tile)


def _blocks(w: int, interpret: bool, block: int | None = None) -> int:
    """Kernel instances for ``w`` worlds: whole blocks of ``block`` worlds (``BLOCK``), covering at least
    ``MIN_WORLDS`` when compiled."""
    block = block or BLOCK
    return -(-w // block) if interpret else -(-max(w, MIN_WORLDS) // block)


def _tile_split(tile, width: int):
    """The ``width`` columns of a (BLOCK, width) tile as (BLOCK,) rows (``width`` a power of two)."""
    if width == 1:
        return [tile.reshape(tile.shape[0])]
    return [p.reshape(tile.shape[0]) for p in jnp.split(tile, width, axis=1)]


def _tile_join(rows):
    """(BLOCK,) rows (a power of two of them) as one (BLOCK, len(rows)) tile, column j = ``rows[j]``: joined
    pairwise (Triton's join makes a new last axis of two), evens and odds first so the columns interleave
    back into order."""
    if len(rows) == 1:
        return rows[0].reshape(rows[0].shape[0], 1)
    if len(rows) == 2:
        return jnp.stack(rows, axis=-1)
    a, b = _tile_join(rows[0::2]), _tile_join(rows[1::2])
    return jnp.stack([a, b], axis=-1).reshape(a.shape[0], 2 * a.shape[1])


def _compiler_kwargs(interpret: bool) -> dict:
    """``pallas_call``'s Triton options for a compiled kernel (``NUM_WARPS`` warps); none for the interpreter."""
    if interpret:
        return {}
    from jax.experimental.pallas import triton as plt

    return {"compiler_params": plt.CompilerParams(num_warps=NUM_WARPS)}


def _kernel(n, step, c_tree, s_tree, x_tree, y_tree, nc, ns, leaves, interpret, done=None):
    """All ``n`` iterations for W worlds in one ``pallas_call`` over blocks of ``BLOCK`` worlds:
    per-world inputs and outputs as (worlds, fields) arrays, read and written ``TILE`` fields per memory
    access; per-iteration ones as (fields, n, worlds) rows. With ``done``, a block stops once every
    world in it is done (padding worlds count as done)."""
    from jax.experimental import pallas as pl

    w = leaves[0].shape[0]
    f_in, f_out = nc + ns, ns
    f_x, f_y = x_tree.num_leaves, y_tree.num_leaves
    # with ``done``, one more input field says which worlds are real (1) or padding (0): as data, not as
    # a constant ``w``, so calls at different batches of one grid are the same kernel
    f_real = f_in + (done is not None)
    # Triton wants power-of-two block shapes: pad fields, iterations and worlds (padding worlds are
    # zeros, computed and dropped; the solver's divisions are guarded, so they stay finite).
    tile = min(TILE, _pow2(max(f_real, f_out)))
    cols_in, cols_out, wp = _tiles(f_real, tile), _tiles(f_out, tile), _blocks(w, interpret) * BLOCK
    per_world = list(leaves[:f_in]) + ([jnp.ones((w,), jnp.float32)] if done is not None else [])
    # stacked as rows, then one transpose (XLA's tiled transpose, not a strided gather per field)
    x = jnp.pad(jnp.stack(per_world, 0), ((0, cols_in - f_real), (0, wp - w))).T
    in_specs = [pl.BlockSpec((BLOCK, cols_in), lambda i: (i, 0))]
    out_shape = [jax.ShapeDtypeStruct((wp, cols_out), jnp.float32)]
    out_specs = [pl.BlockSpec((BLOCK, cols_out), lambda i: (i, 0))]
    inputs = [x]
    if f_x:
        n_p = _pow2(n)
        seq = jnp.stack([v.T for v in leaves[f_in:]], 0)  # (f_x, n, W)
        inputs.append(jnp.pad(seq, ((0, _pow2(f_x) - f_x), (0, n_p - n), (0, wp - w))))
        in_specs.append(pl.BlockSpec((_pow2(f_x), n_p, BLOCK), lambda i: (0, 0, i)))
    if f_y:
        out_shape.append(jax.ShapeDtypeStruct((_pow2(f_y), _pow2(n), wp), jnp.float32))
        out_specs.append(pl.BlockSpec((_pow2(f_y), _pow2(n), BLOCK), lambda i: (0, 0, i)))

    def kernel(*refs):
        x_ref, seq_ref = refs[0], refs[1] if f_x else None
        o_ref, ys_ref = refs[len(inputs)], refs[len(inputs) + 1] if f_y else None
        # one memory access per ``tile`` fields: Triton's coalescing pass walks the whole kernel once per
        # access, so a kernel of a few hundred one-field accesses compiled for minutes
        rows = [r for j in range(0, f_real, tile) for r in _tile_split(x_ref[:, j:j + tile], tile)]
        c = jax.tree_util.tree_unflatten(c_tree, rows[:nc])
        # block-uniform flags: reduced once, before the loop
        c = jax.tree_util.tree_map(lambda x: BlockAny(jnp.max(x.flag)) if _is_flag(x) else x, c, is_leaf=_is_flag)
        s = jax.tree_util.tree_unflatten(s_tree, rows[nc:f_in])

        def iteration(i, s):
            xi = jax.tree_util.tree_unflatten(x_tree, [seq_ref[f, i, :] for f in range(f_x)])
            s, y = step(c, s, xi)
            for g, v in enumerate(jax.tree_util.tree_leaves(y)):
                ys_ref[g, i, :] = jnp.broadcast_to(jnp.asarray(v, jnp.float32), (BLOCK,))
            return s

        _TRACING.in_kernel = True
        try:
            if done is None:
                s = lax.fori_loop(0, n, iteration, s)
            else:
                real = rows[f_in] > 0.5
                cond = lambda x: (x[0] < n) & (jnp.min(jnp.where(real, done(x[1]), 1.0)) < 0.5)  # noqa: E731
                s = lax.while_loop(cond, lambda x: (x[0] + 1, iteration(x[0], x[1])), (jnp.int32(0), s))[1]
        finally:
            _TRACING.in_kernel = False
        out = [jnp.broadcast_to(jnp.asarray(v, jnp.float32), (BLOCK,)) for v in jax.tree_util.tree_leaves(s)]
        out += [jnp.zeros((BLOCK,), jnp.float32)] * (-len(out) % tile)  # the last tile's padding fields
        for j in range(0, len(out), tile):
            o_ref[:, j:j + tile] = _tile_join(out[j:j + tile])

    outs = pl.pallas_call(
        kernel,
        out_shape=tuple(out_shape),
        grid=(wp // BLOCK,),
        in_specs=in_specs,
        out_specs=tuple(out_specs),
        interpret=interpret,
        **_compiler_kwargs(interpret),
    )(*inputs)
    fields = outs[0][:w, :f_out].T
    out = [fields[g] for g in range(f_out)]
    if f_y:
        out += [outs[1][g, :n, :w].T for g in range(f_y)]
    return out


def _lane_kernel(n, step, c_tree, s_tree, nc, ns, leaves, lane_mask, interpret, lanes, done=None):
    """``_kernel`` for loops with lane vectors: ``BLOCK // lanes`` worlds per instance, ``lanes``
    threads per world. Inputs and outputs are (worlds, fields) arrays whose first columns hold the
    lane vectors, one tile of ``lanes`` columns each (read and written as (worlds, lanes) tiles), and
    the per-world scalars after them (read as (worlds, 1) columns of their tiles). ``done`` as
    ``_kernel``'s: one more scalar column says which worlds are real."""
    from jax.experimental import pallas as pl

    bw = BLOCK // lanes
    w = leaves[0].shape[0]
    f_in = nc + ns
    in_lane = [i for i in range(f_in) if lane_mask[i]]
    in_scalar = [i for i in range(f_in) if not lane_mask[i]]
    out_lane = [i - nc for i in in_lane if i >= nc]
    out_scalar = [i - nc for i in in_scalar if i >= nc]

    real_col = [jnp.ones((w,), jnp.float32)] if done is not None else []
    cols = [leaves[i][:, j] for i in in_lane for j in range(lanes)] + [leaves[i] for i in in_scalar] + real_col
    n_out = lanes * len(out_lane) + len(out_scalar)
    cols_in, cols_out, wp = _tiles(len(cols), lanes), _tiles(n_out, lanes), _blocks(w, interpret, bw) * bw
    x = jnp.pad(jnp.stack(cols, 0), ((0, cols_in - len(cols)), (0, wp - w))).T

    def kernel(x_ref, o_ref):
        tiles = [x_ref[:, j:j + lanes] for j in range(0, len(cols), lanes)]
        vals = [None] * f_in
        for k, i in enumerate(in_lane):
            vals[i] = tiles[k]
        singles = [p for t_ in tiles[len(in_lane):] for p in jnp.split(t_, lanes, axis=1)]
        for k, i in enumerate(in_scalar):
            vals[i] = singles[k]
        c = jax.tree_util.tree_unflatten(c_tree, vals[:nc])
        # block-uniform flags: reduced once, before the loop (over the block's worlds and lanes)
        c = jax.tree_util.tree_map(lambda x: BlockAny(jnp.max(x.flag)) if _is_flag(x) else x, c, is_leaf=_is_flag)
        s = jax.tree_util.tree_unflatten(s_tree, vals[nc:])
        _TRACING.in_kernel = True
        try:
            if done is None:
                s = lax.fori_loop(0, n, lambda i, s_: step(c, s_, None)[0], s)
            else:
                real = singles[len(in_scalar)] > 0.5
                cond = lambda x: (x[0] < n) & (jnp.min(jnp.where(real, done(x[1]), 1.0)) < 0.5)  # noqa: E731
                s = lax.while_loop(cond, lambda x: (x[0] + 1, step(c, x[1], None)[0]), (jnp.int32(0), s))[1]
        finally:
            _TRACING.in_kernel = False
        out = jax.tree_util.tree_leaves(s)
        for k, i in enumerate(out_lane):
            o_ref[:, lanes * k:lanes * (k + 1)] = jnp.broadcast_to(jnp.asarray(out[i], jnp.float32), (bw, lanes))
        rows = [jnp.broadcast_to(jnp.asarray(out[i], jnp.float32), (bw, 1)).reshape(bw) for i in out_scalar]
        rows += [jnp.zeros((bw,), jnp.float32)] * (-len(rows) % lanes)
        base = lanes * len(out_lane)
        for j in range(0, len(rows), lanes):
            o_ref[:, base + j:base + j + lanes] = _tile_join(rows[j:j + lanes])

    res = pl.pallas_call(
        kernel,
        out_shape=jax.ShapeDtypeStruct((wp, cols_out), jnp.float32),
        grid=(wp // bw,),
        in_specs=[pl.BlockSpec((bw, cols_in), lambda i: (i, 0))],
        out_specs=pl.BlockSpec((bw, cols_out), lambda i: (i, 0)),
        interpret=interpret,
        **_compiler_kwargs(interpret),
    )(x)[:w]
    out = [None] * ns
    for k, i in enumerate(out_lane):
        out[i] = res[:, lanes * k:lanes * (k + 1)]
    base = lanes * len(out_lane)
    for k, i in enumerate(out_scalar):
        out[i] = res[:, base + k]
    return out
