"""DCD's parametric BipedalWalker terrain generator: one sequential loop over the 200 columns.

``generate(key, level)`` reproduces DCD's GRASS/STUMP/STAIRS/PIT state machine (docs/walker.md "Terrain") from the
8 level parameters and a key, returning the ground polyline (199 edges through ``x, y``) and the
obstacle boxes (stumps, stair steps, pit walls). ``rasterise`` turns that into the height profile
``max(polyline, box tops)`` sampled every ``TERRAIN_STEP / resolution`` metres, which is what the
MJX heightfield, the analytic lidar, the hull-contact test and the renderer all use (one profile,
so physics, sensing and drawing agree).

Everything is pure jnp on scalars and fixed-size arrays, so a batch of different levels is one
``vmap``. Any parameter vector is valid: pairs are sorted and thresholds applied here. The loop
carries only per-world scalars (the state machine); every column's boxes are built after it, all at
once. So the loop can run as one GPU kernel (``envs.physics2d.fused.per_world_scan``): as an XLA
loop its 200 dependent iterations launch about 8 small kernels each, most of a GPU reset's time.

A level with ``gym_hardcore`` set runs Gymnasium's BipedalWalkerHardcore rules instead (docs/walker.md "Terrain"),
in the same scan, selected per level so that one batch can mix both: every obstacle type present,
roughness 1, square stumps of 1 or 2 steps (the counter restarts at the stump's size), pits 3 or 4
steps between walls with no fractional part, staircases of 3 or 4 steps of height 1 and width 4
(counter = steps x 4), and Gymnasium's stair polyline: the column height ramps linearly,
``y_o + (steps*4 - counter - slope) / 4 * slope`` steps, so in the second half of each step the
polyline rises above the step's box (and, being ground, is walked on there).
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.walker import constants as C

BOX_SLOTS_PER_COLUMN = C.MAX_STAIR_STEPS - 1  # a staircase writes at most 8 boxes in one column


@struct.dataclass
class Terrain:
    """One generated level: polyline vertices and obstacle boxes (all in metres)."""

    x: jax.Array  # [200] column x (the column closing a pit is moved back by pit_diff steps)
    y: jax.Array  # [200] column height
    boxes: jax.Array  # [K, 4] (x0, x1, y0, y1); unused slots are all zero
    box_valid: jax.Array  # [K] bool
    n_boxes: jax.Array  # int32, boxes generated (may exceed K: the rest are dropped, see overflow)
    kinds: jax.Array  # [200] int32 state of each column (GRASS/STUMP/STAIRS/PIT), for tests


@struct.dataclass
class ProcessedLevel:
    """The level after DCD's processing: sorted pairs, integer steps, presence flags."""

    roughness: jax.Array
    pit: jax.Array  # (low, high)
    stump: jax.Array
    stair: jax.Array
    steps: jax.Array  # int32 >= 1: a staircase has randint(steps) in {0..steps-1} steps
    has_stump: jax.Array
    has_stairs: jax.Array
    has_pit: jax.Array


def process(level: Any) -> ProcessedLevel:
    """Sort each (low, high) pair, round the step count and apply the presence thresholds."""
    f = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731

    def pair(a, b):
        a, b = f(a), f(b)
        return jnp.stack([jnp.minimum(a, b), jnp.maximum(a, b)])

    pit = pair(level.pit_gap_low, level.pit_gap_high)
    stump = pair(level.stump_height_low, level.stump_height_high)
    stair = pair(level.stair_height_low, level.stair_height_high)
    steps = jnp.clip(jnp.round(f(level.stair_steps)), 1, C.MAX_STAIR_STEPS).astype(jnp.int32)
    return ProcessedLevel(
        roughness=f(level.roughness),
        pit=pit,
        stump=stump,
        stair=stair,
        steps=steps,
        has_stump=stump[1] >= C.STUMP_THRESHOLD,
        has_stairs=stair[1] >= C.STAIR_THRESHOLD,
        has_pit=pit[1] >= C.PIT_THRESHOLD,
    )


@struct.dataclass
class _Carry:
    """The column state machine's state, every field a float32 scalar (integers held exactly)."""

    y: jax.Array
    velocity: jax.Array
    counter: jax.Array
    state: jax.Array
    oneshot: jax.Array  # 0 / 1
    y_orig: jax.Array
    pit_diff: jax.Array
    stair_h: jax.Array
    stair_slope: jax.Array
    stair_n: jax.Array


@struct.dataclass
class _Consts:
    """The level's values the state machine reads, as float32 scalars (flags 0 / 1)."""

    roughness: jax.Array  # 1 on Gymnasium-hardcore levels
    pit_lo: jax.Array
    pit_hi: jax.Array
    stair_lo: jax.Array
    stair_hi: jax.Array
    steps: jax.Array
    gym: jax.Array
    hardcore: jax.Array
    present: tuple  # (stump, stairs, pit) flags


def generate(key: jax.Array, level: Any, max_boxes: int = 64, unroll: int = 1, kernel: str = "xla") -> Terrain:
    """Run the column state machine. ``level`` has the 8 DCD fields (e.g. ``WalkerParams``)."""
    return generate_from_uniforms(column_uniforms(key), level, max_boxes, unroll, kernel)


def level_terrain(key: jax.Array, level: Any, max_boxes: int = 64, unroll: int = 1, kernel: str = "xla") -> Terrain:
    """The level's terrain: from its ``terrain_seed`` if ``fixed_terrain`` (exact replay), else from
    ``key`` (a new terrain of the same parameters). Shared by every walker environment. ``unroll``:
    columns per iteration of the generator's XLA loop; ``kernel``: ``envs.physics2d.fused`` mode of
    the loop ("auto": one GPU kernel on GPUs). Both are speed only: the same terrain up to float32
    rounding."""
    seed = jnp.asarray(level.terrain_seed, jnp.int32)
    typed = jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key)
    seeded = jax.random.key(seed) if typed else jax.random.PRNGKey(seed)
    k = jnp.where(jnp.asarray(level.fixed_terrain), seeded, key)
    return generate(k, level, max_boxes, unroll, kernel)


def column_uniforms(key: jax.Array) -> jax.Array:
    """The generator's random numbers: 8 uniforms per column, drawn up front in one call (threefry
    inside the scan body would dominate its cost). Column i uses row i: [0] grass walk, [1] pit gap,
    [2] stump size, [3] stair height, [4] stair direction, [5] stair count, [6] grass counter,
    [7] next obstacle type."""
    return jax.random.uniform(key, (C.TERRAIN_LENGTH, 8), jnp.float32)


def _randint(u: jax.Array, low: int, high: int) -> jax.Array:
    """numpy's ``integers(low, high)`` (high exclusive) from one uniform in [0, 1), as a float."""
    return low + jnp.minimum(jnp.floor(u * (high - low)), high - low - 1.0)


def _pit_gap(u1, lo, hi, gym):
    """A pit's gap in steps: 1 + U(lo, hi) (DCD), randint(3, 5) (Gymnasium)."""
    return jnp.where(gym, _randint(u1, 3, 5), 1.0 + lo + u1 * (hi - lo))


def _stairs(u3, u4, u5, lo, hi, steps, gym):
    """A staircase's (step height, slope +-1, step count): DCD's U(lo, hi) and randint(steps),
    Gymnasium's 1 and randint(3, 5)."""
    h = jnp.where(gym, 1.0, lo + u3 * (hi - lo))
    n = jnp.where(gym, _randint(u5, 3, 5), jnp.minimum(jnp.floor(u5 * steps), steps - 1.0))
    return h, jnp.where(u4 > 0.5, 1.0, -1.0), n


def _column(k: _Consts, carry: _Carry, inp):
    """One column of the state machine on per-world scalars (``fused.per_world_scan``'s contract).
    Returns (carry, (x of the column's vertex, its height, its state, whether it is a oneshot
    column)). Only a oneshot column writes boxes, and its height is the one it entered with."""
    i, u = inp
    S, w = C.TERRAIN_STEP, float(C.STAIR_WIDTH)
    x = i * S
    st, one = carry.state, carry.oneshot > 0.5
    y, vel, counter = carry.y, carry.velocity, carry.counter
    y_orig, pit_diff = carry.y_orig, carry.pit_diff
    s_h, s_slope, s_n = carry.stair_h, carry.stair_slope, carry.stair_n
    gym = k.gym > 0.5

    # GRASS (not oneshot): smoothed random walk towards y0, scaled by roughness.
    grass = (st == C.GRASS) & ~one
    v_new = 0.8 * vel + 0.01 * jnp.sign(C.TERRAIN_HEIGHT - y)
    v_new = v_new + jnp.where(i > C.TERRAIN_STARTPAD, (2.0 * u[0] - 1.0) / C.SCALE, 0.0)
    vel = jnp.where(grass, v_new, vel)
    y = jnp.where(grass, y + k.roughness * v_new, y)

    # PIT oneshot: the counter spans the gap (its walls are boxes, built after the loop).
    pit_one = (st == C.PIT) & one
    gap = _pit_gap(u[1], k.pit_lo, k.pit_hi, gym)
    c_gap = jnp.ceil(gap)
    counter = jnp.where(pit_one, c_gap + 2.0, counter)
    pit_diff = jnp.where(pit_one, c_gap - gap, pit_diff)
    y_orig = jnp.where(pit_one, y, y_orig)

    # PIT later columns: floor 4 steps down; the closing column is moved back by pit_diff.
    pit_walk = (st == C.PIT) & ~one
    y = jnp.where(pit_walk, jnp.where(counter > 1.0, y_orig - C.PIT_DEPTH * S, y_orig), y)
    closing = pit_walk & (counter == 1.0)
    x_out = jnp.where(closing, x - pit_diff * S, x)
    pit_diff = jnp.where(closing, 0.0, pit_diff)

    # STUMP oneshot: DCD's counter is not reset; Gymnasium's restarts at the square's size.
    counter = jnp.where((st == C.STUMP) & one & gym, _randint(u[2], 1, 3), counter)

    # STAIRS oneshot: N steps of width 4 (built only if the height exceeds 0.01).
    stairs_one = (st == C.STAIRS) & one
    h_new, slope_new, n_new = _stairs(u[3], u[4], u[5], k.stair_lo, k.stair_hi, k.steps, gym)
    build = stairs_one & (h_new > 0.01)
    counter = jnp.where(build, n_new * w + jnp.where(gym, 0.0, 1.0), counter)
    y_orig = jnp.where(stairs_one, y, y_orig)
    s_h = jnp.where(stairs_one, h_new, s_h)
    s_slope = jnp.where(stairs_one, slope_new, s_slope)
    s_n = jnp.where(stairs_one, n_new, s_n)

    # STAIRS later columns: follow the step tops (descending: one step lower).
    stairs_walk = (st == C.STAIRS) & ~one
    s_pos = s_n * w - counter
    n_done = jnp.floor(s_pos / w)
    y_stairs = y_orig + (n_done * s_h * s_slope - jnp.where(s_slope < 0, s_h, 0.0)) * S
    y_ramp = y_orig + (s_pos - s_slope) / w * s_slope * S  # Gymnasium's rule
    y_stairs = jnp.where(gym, y_ramp, y_stairs)
    y = jnp.where(stairs_walk, y_stairs, y)

    # Counter and state transition: after a grass stretch, the r-th present obstacle type,
    # r = randint(number present); after an obstacle, grass.
    counter = counter - 1.0
    switch = counter == 0.0
    n_grass = C.TERRAIN_GRASS - C.TERRAIN_GRASS // 2
    counter = jnp.where(switch, C.TERRAIN_GRASS // 2 + jnp.minimum(jnp.floor(u[6] * n_grass), n_grass - 1.0), counter)
    p = [f > 0.5 for f in k.present]
    n_present = sum(k.present)
    r = jnp.minimum(jnp.floor(u[7] * n_present), jnp.maximum(n_present - 1.0, 0.0))
    before = [0.0, k.present[0], k.present[0] + k.present[1]]  # present types before each type
    obstacle = jnp.float32(C.STUMP)  # argmax's answer when none matches (unused: then not hardcore)
    for kind, ok, b in reversed(list(zip((C.STUMP, C.STAIRS, C.PIT), p, before))):
        obstacle = jnp.where(ok & (b == r), float(kind), obstacle)
    nxt = jnp.where((st == C.GRASS) & (k.hardcore > 0.5), obstacle, float(C.GRASS))
    new = _Carry(y, vel, counter, jnp.where(switch, nxt, st), jnp.where(switch, 1.0, 0.0),
                 y_orig, pit_diff, s_h, s_slope, s_n)
    return new, (x_out, y, st, carry.oneshot)


def generate_from_uniforms(uniforms: jax.Array, level: Any, max_boxes: int = 64, unroll: int = 1,
                           kernel: str = "xla") -> Terrain:
    """``generate`` with its random numbers given (``[200, 8]``, see ``column_uniforms``).

    Two parts: the state machine's sequential loop over columns on per-world scalars (one GPU kernel
    with ``kernel="pallas"``/``"auto"``, through ``fused.per_world_scan``), then every column's
    boxes at once from its state, height and uniforms (no box passes through the loop)."""
    from envs.physics2d import fused

    lv = process(level)
    S, w = C.TERRAIN_STEP, C.STAIR_WIDTH
    f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
    gym = jnp.asarray(getattr(level, "gym_hardcore", False), bool)
    hardcore = gym | lv.has_stump | lv.has_stairs | lv.has_pit
    present = tuple(f32(flag | gym) for flag in (lv.has_stump, lv.has_stairs, lv.has_pit))
    consts = _Consts(roughness=f32(jnp.where(gym, 1.0, lv.roughness)), pit_lo=lv.pit[0], pit_hi=lv.pit[1],
                     stair_lo=lv.stair[0], stair_hi=lv.stair[1], steps=f32(lv.steps), gym=f32(gym),
                     hardcore=f32(hardcore), present=present)
    init = _Carry(y=f32(C.TERRAIN_HEIGHT), velocity=f32(0.0), counter=f32(C.TERRAIN_STARTPAD),
                  state=f32(C.GRASS), oneshot=f32(0.0), y_orig=f32(0.0), pit_diff=f32(0.0),
                  stair_h=f32(0.0), stair_slope=f32(1.0), stair_n=f32(0.0))
    idx = jnp.arange(C.TERRAIN_LENGTH, dtype=jnp.float32)
    us = tuple(uniforms[:, j] for j in range(8))
    if fused.resolve_mode(kernel) == "xla":
        _, (xs, ys, st, one) = jax.lax.scan(lambda c, x: _column(consts, c, x), init, (idx, us), unroll=unroll)
    else:
        _, (xs, ys, st, one) = fused.per_world_scan(_column, consts, init, (idx, us), mode=kernel)
    kinds = st.astype(jnp.int32)
    one = one > 0.5

    # each oneshot column's boxes (at most BOX_SLOTS_PER_COLUMN), at its entry height ``ys``
    x, u = idx * S, uniforms
    slot = jnp.arange(BOX_SLOTS_PER_COLUMN, dtype=jnp.float32)
    pit_one = (kinds == C.PIT) & one
    gap = _pit_gap(u[:, 1], lv.pit[0], lv.pit[1], gym)
    wall1 = jnp.stack([x, x + S, ys - C.PIT_DEPTH * S, ys], -1)  # (200, 4)
    wall2 = wall1 + jnp.stack([gap * S, gap * S, jnp.zeros_like(gap), jnp.zeros_like(gap)], -1)
    walls = jnp.zeros((C.TERRAIN_LENGTH, BOX_SLOTS_PER_COLUMN, 4), jnp.float32).at[:, 0].set(wall1).at[:, 1].set(wall2)
    # STUMP: width 1, height U(lo, hi) steps on the ground (Gymnasium: a square of randint(1, 3) steps)
    stump_one = (kinds == C.STUMP) & one
    size_gym = _randint(u[:, 2], 1, 3)
    h_stump = jnp.where(gym, size_gym, lv.stump[0] + u[:, 2] * (lv.stump[1] - lv.stump[0]))
    w_stump = jnp.where(gym, size_gym, 1.0)
    stump = jnp.zeros_like(walls).at[:, 0].set(jnp.stack([x, x + w_stump * S, ys, ys + h_stump * S], -1))
    # STAIRS: step s spans [x + s w, x + (s + 1) w) steps, top at y + s h slope
    h, slope, n = _stairs(u[:, 3], u[:, 4], u[:, 5], lv.stair[0], lv.stair[1], f32(lv.steps), gym)
    h, slope, n = h[:, None], slope[:, None], n[:, None]
    xs_, ys_ = x[:, None], ys[:, None]
    stair_boxes = jnp.stack([xs_ + slot * w * S, xs_ + (slot + 1) * w * S,
                             ys_ + (-h + slot * h * slope) * S, ys_ + slot * h * slope * S], -1)
    build = (kinds == C.STAIRS) & one & (h[:, 0] > 0.01)
    cand = jnp.where(pit_one[:, None, None], walls, 0.0)
    cand = jnp.where(stump_one[:, None, None], stump, cand)
    cand = jnp.where(build[:, None, None], stair_boxes, cand)
    cand_ok = ((pit_one[:, None] & (slot < 2)) | (stump_one[:, None] & (slot < 1))
               | (build[:, None] & (slot < n)))
    # the boxes in column order, compacted; those beyond max_boxes are dropped
    cand, cand_ok = cand.reshape(-1, 4), cand_ok.reshape(-1)
    pos = jnp.where(cand_ok, jnp.cumsum(cand_ok) - 1, max_boxes)  # out of range -> dropped
    boxes = jnp.zeros((max_boxes, 4), jnp.float32).at[pos].set(cand, mode="drop")
    n_boxes = jnp.sum(cand_ok, dtype=jnp.int32)
    valid = jnp.arange(max_boxes) < n_boxes
    return Terrain(x=xs, y=ys, boxes=boxes, box_valid=valid, n_boxes=n_boxes, kinds=kinds)


@struct.dataclass
class Grid:
    """Static description of the sampled profile: x_j = x_min + j * dx, j < n."""

    x_min: float = struct.field(pytree_node=False)
    dx: float = struct.field(pytree_node=False)
    n: int = struct.field(pytree_node=False)

    @property
    def x_max(self) -> float:
        return self.x_min + (self.n - 1) * self.dx


def make_grid(resolution: int = 4, pad_left: int = 4, pad_right: int = 4) -> Grid:
    """Samples every TERRAIN_STEP/resolution over [-pad_left, 200 + pad_right] columns."""
    if resolution < 1 or pad_left < 1 or pad_right < 1:
        raise ValueError(f"terrain grid: resolution and pads must be >= 1, got {resolution}, {pad_left}, {pad_right}")
    dx = C.TERRAIN_STEP / resolution
    n = (C.TERRAIN_LENGTH + pad_left + pad_right) * resolution + 1
    return Grid(x_min=-pad_left * C.TERRAIN_STEP, dx=dx, n=n)


def rasterise(terrain: Terrain, grid: Grid) -> jax.Array:
    """Heights ``max(polyline, box tops)`` at the grid samples (``[grid.n]``).

    A box covers the samples in its closed x-interval (with a 1e-4 m tolerance, so boxes aligned
    with columns keep their full top width); each vertical face becomes one grid cell wide.
    The generator emits boxes in increasing x without overlaps, so each sample finds its only
    candidate box by binary search (O(n log K) instead of an O(n K) all-pairs test).
    """
    # The sample positions are a constant of the program, not computed in it: XLA may recompute a
    # computed xs inside each fused step of the unrolled searches, rounding it differently in each,
    # and a search whose comparisons disagree about a sample one ulp from a vertex ends up to two
    # segments off (seen in the MJX walker's step and reset programs on XLA:CPU, 2026-12-05).
    xs = jnp.asarray(grid.x_min + grid.dx * np.arange(grid.n, dtype=np.float32))
    h = _interp(xs, terrain.x, terrain.y)  # constant beyond the ends
    b = terrain.boxes
    x0 = jnp.where(terrain.box_valid, b[:, 0] - 1e-4, jnp.inf)
    k = jnp.clip(jnp.searchsorted(x0, xs, side="right", method="scan_unrolled") - 1, 0, b.shape[0] - 1)
    inside = (xs >= x0[k]) & (xs <= b[k, 1] + 1e-4) & terrain.box_valid[k]
    return jnp.where(inside, jnp.maximum(h, b[k, 3]), h)


def _interp(x, xp, fp):
    """``jnp.interp(x, xp, fp)`` (its formula, bit for bit) with its binary search unrolled
    (``searchsorted(method="scan_unrolled")``): jnp's own runs it as a ``while`` loop of about ten
    steps, some 30 small kernels per call on a GPU; unrolled, XLA fuses it into a few. Comparing every
    x with every xp (``"compare_all"``) launches as few but does O(len(x) len(xp)) work, too much at
    tens of thousands of walkers."""
    i = jnp.clip(jnp.searchsorted(xp, x, side="right", method="scan_unrolled"), 1, xp.shape[0] - 1)
    df = fp[i] - fp[i - 1]
    dx = xp[i] - xp[i - 1]
    delta = x - xp[i - 1]
    dx0 = jnp.abs(dx) <= np.spacing(np.finfo(np.float32).eps)
    f = jnp.where(dx0, fp[i - 1], fp[i - 1] + (delta / jnp.where(dx0, 1, dx)) * df)
    f = jnp.where(x < xp[0], fp[0], f)
    return jnp.where(x > xp[-1], fp[-1], f)


def height_at(profile: jax.Array, grid: Grid, x: jax.Array) -> jax.Array:
    """Linear interpolation of the profile at world x (clamped at the ends), any shape of x."""
    u = (x - grid.x_min) / grid.dx
    j = jnp.clip(jnp.floor(u), 0, grid.n - 2).astype(jnp.int32)
    t = jnp.clip(u - j, 0.0, 1.0)
    return profile[j] * (1.0 - t) + profile[j + 1] * t
