"""DCD's parametric BipedalWalker terrain generator as one ``lax.scan`` over the 200 columns.

``generate(key, level)`` reproduces DCD's GRASS/STUMP/STAIRS/PIT state machine (docs/walker.md "Terrain") from the
8 level parameters and a key, returning the ground polyline (199 edges through ``x, y``) and the
obstacle boxes (stumps, stair steps, pit walls). ``rasterise`` turns that into the height profile
``max(polyline, box tops)`` sampled every ``TERRAIN_STEP / resolution`` metres, which is what the
MJX heightfield, the analytic lidar, the hull-contact test and the renderer all use (one profile,
so physics, sensing and drawing agree).

Everything is pure jnp on scalars and fixed-size arrays, so a batch of different levels is one
``vmap``. Any parameter vector is valid: pairs are sorted and thresholds applied here.

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
    y: jax.Array
    velocity: jax.Array
    counter: jax.Array  # int32
    state: jax.Array  # int32
    oneshot: jax.Array  # bool
    y_orig: jax.Array
    pit_diff: jax.Array
    stair_h: jax.Array
    stair_slope: jax.Array
    stair_n: jax.Array  # int32


def generate(key: jax.Array, level: Any, max_boxes: int = 64, unroll: int = 1) -> Terrain:
    """Run the column state machine. ``level`` has the 8 DCD fields (e.g. ``WalkerParams``)."""
    return generate_from_uniforms(column_uniforms(key), level, max_boxes, unroll)


def level_terrain(key: jax.Array, level: Any, max_boxes: int = 64, unroll: int = 1) -> Terrain:
    """The level's terrain: from its ``terrain_seed`` if ``fixed_terrain`` (exact replay), else from
    ``key`` (a new terrain of the same parameters). Shared by every walker environment. ``unroll``:
    columns per iteration of the generator's loop (speed only: the same terrain up to float32 rounding)."""
    seed = jnp.asarray(level.terrain_seed, jnp.int32)
    typed = jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key)
    seeded = jax.random.key(seed) if typed else jax.random.PRNGKey(seed)
    k = jnp.where(jnp.asarray(level.fixed_terrain), seeded, key)
    return generate(k, level, max_boxes, unroll)


def column_uniforms(key: jax.Array) -> jax.Array:
    """The generator's random numbers: 8 uniforms per column, drawn up front in one call (threefry
    inside the scan body would dominate its cost). Column i uses row i: [0] grass walk, [1] pit gap,
    [2] stump size, [3] stair height, [4] stair direction, [5] stair count, [6] grass counter,
    [7] next obstacle type."""
    return jax.random.uniform(key, (C.TERRAIN_LENGTH, 8), jnp.float32)


def _randint(u: jax.Array, low: int, high: int) -> jax.Array:
    """numpy's ``integers(low, high)`` (high exclusive) from one uniform in [0, 1), as a float."""
    return low + jnp.minimum(jnp.floor(u * (high - low)), high - low - 1.0)


def generate_from_uniforms(uniforms: jax.Array, level: Any, max_boxes: int = 64, unroll: int = 1) -> Terrain:
    """``generate`` with its random numbers given (``[200, 8]``, see ``column_uniforms``)."""
    lv = process(level)
    S = C.TERRAIN_STEP
    gym = jnp.asarray(getattr(level, "gym_hardcore", False), bool)
    hardcore = gym | lv.has_stump | lv.has_stairs | lv.has_pit
    present = jnp.stack([lv.has_stump, lv.has_stairs, lv.has_pit]) | gym
    roughness = jnp.where(gym, 1.0, lv.roughness)
    w = C.STAIR_WIDTH

    n_present = jnp.sum(present)

    def column(carry: _Carry, inp):
        i, u = inp  # u: this column's 8 uniforms
        x = i.astype(jnp.float32) * S
        st, one = carry.state, carry.oneshot
        y, vel, counter = carry.y, carry.velocity, carry.counter
        y_orig, pit_diff = carry.y_orig, carry.pit_diff
        s_h, s_slope, s_n = carry.stair_h, carry.stair_slope, carry.stair_n

        # GRASS (not oneshot): smoothed random walk towards y0, scaled by roughness.
        grass = (st == C.GRASS) & ~one
        v_new = 0.8 * vel + 0.01 * jnp.sign(C.TERRAIN_HEIGHT - y)
        v_new = v_new + jnp.where(i > C.TERRAIN_STARTPAD, (2.0 * u[0] - 1.0) / C.SCALE, 0.0)
        vel = jnp.where(grass, v_new, vel)
        y = jnp.where(grass, y + roughness * v_new, y)

        cand = jnp.zeros((BOX_SLOTS_PER_COLUMN, 4), jnp.float32)
        cand_ok = jnp.zeros((BOX_SLOTS_PER_COLUMN,), bool)

        # PIT oneshot: two walls, gap 1 + U(lo, hi) steps apart.
        pit_one = (st == C.PIT) & one
        gap = 1.0 + lv.pit[0] + u[1] * (lv.pit[1] - lv.pit[0])
        gap = jnp.where(gym, _randint(u[1], 3, 5), gap)
        c_gap = jnp.ceil(gap)
        wall1 = jnp.stack([x, x + S, y - C.PIT_DEPTH * S, y])
        wall2 = wall1 + jnp.stack([gap * S, gap * S, 0.0, 0.0])
        counter = jnp.where(pit_one, c_gap.astype(jnp.int32) + 2, counter)
        pit_diff = jnp.where(pit_one, c_gap - gap, pit_diff)
        y_orig = jnp.where(pit_one, y, y_orig)
        cand = jnp.where(pit_one, cand.at[0].set(wall1).at[1].set(wall2), cand)
        cand_ok = jnp.where(pit_one, cand_ok.at[:2].set(True), cand_ok)

        # PIT later columns: floor 4 steps down; the closing column is moved back by pit_diff.
        pit_walk = (st == C.PIT) & ~one
        y = jnp.where(pit_walk, jnp.where(counter > 1, y_orig - C.PIT_DEPTH * S, y_orig), y)
        closing = pit_walk & (counter == 1)
        x_out = jnp.where(closing, x - pit_diff * S, x)
        pit_diff = jnp.where(closing, 0.0, pit_diff)

        # STUMP oneshot: width 1, float 0, height U(lo, hi) steps; the counter is not reset.
        # Gymnasium: a square of randint(1, 3) steps, and the counter restarts at that size.
        stump_one = (st == C.STUMP) & one
        h_stump = lv.stump[0] + u[2] * (lv.stump[1] - lv.stump[0])
        size_gym = _randint(u[2], 1, 3)
        h_stump = jnp.where(gym, size_gym, h_stump)
        w_stump = jnp.where(gym, size_gym, 1.0)
        cand = jnp.where(stump_one, cand.at[0].set(jnp.stack([x, x + w_stump * S, y, y + h_stump * S])), cand)
        cand_ok = jnp.where(stump_one, cand_ok.at[0].set(True), cand_ok)
        counter = jnp.where(stump_one & gym, size_gym.astype(jnp.int32), counter)

        # STAIRS oneshot: N = randint(steps) boxes of width 4, height h, slope +-1 (if h > 0.01).
        stairs_one = (st == C.STAIRS) & one
        h_new = lv.stair[0] + u[3] * (lv.stair[1] - lv.stair[0])
        slope_new = jnp.where(u[4] > 0.5, 1.0, -1.0)
        n_new = jnp.minimum(jnp.floor(u[5] * lv.steps).astype(jnp.int32), lv.steps - 1)  # randint(steps)
        # Gymnasium: height 1, randint(3, 5) steps
        h_new = jnp.where(gym, 1.0, h_new)
        n_new = jnp.where(gym, _randint(u[5], 3, 5).astype(jnp.int32), n_new)
        s_idx = jnp.arange(BOX_SLOTS_PER_COLUMN, dtype=jnp.float32)
        stair_boxes = jnp.stack(
            [
                x + s_idx * w * S,
                x + (s_idx + 1) * w * S,
                y + (-h_new + s_idx * h_new * slope_new) * S,
                y + s_idx * h_new * slope_new * S,
            ],
            axis=-1,
        )
        build = stairs_one & (h_new > 0.01)
        cand = jnp.where(build, stair_boxes, cand)
        cand_ok = jnp.where(build, s_idx < n_new, cand_ok)
        counter = jnp.where(build, n_new * w + jnp.where(gym, 0, 1), counter)
        y_orig = jnp.where(stairs_one, y, y_orig)
        s_h = jnp.where(stairs_one, h_new, s_h)
        s_slope = jnp.where(stairs_one, slope_new, s_slope)
        s_n = jnp.where(stairs_one, n_new, s_n)

        # STAIRS later columns: follow the step tops (descending: one step lower).
        stairs_walk = (st == C.STAIRS) & ~one
        s_pos = s_n * w - counter
        n_done = jnp.floor_divide(s_pos, w).astype(jnp.float32)
        y_stairs = y_orig + (n_done * s_h * s_slope - jnp.where(s_slope < 0, s_h, 0.0)) * S
        y_ramp = y_orig + (s_pos.astype(jnp.float32) - s_slope) / w * s_slope * S  # Gymnasium's rule
        y_stairs = jnp.where(gym, y_ramp, y_stairs)
        y = jnp.where(stairs_walk, y_stairs, y)

        # This column's boxes are an output of the scan, appended in order after it (a (max_boxes, 4)
        # carry scattered into at every column was a GPU reset's largest kernel).

        # Counter and state transition.
        kind = st
        counter = counter - 1
        switch = counter == 0
        n_grass = C.TERRAIN_GRASS - C.TERRAIN_GRASS // 2
        counter = jnp.where(switch, C.TERRAIN_GRASS // 2 + jnp.minimum(jnp.floor(u[6] * n_grass).astype(jnp.int32), n_grass - 1), counter)
        # Uniform over the present obstacle types: the r-th present one, r = randint(n_present).
        r = jnp.minimum(jnp.floor(u[7] * n_present).astype(jnp.int32), jnp.maximum(n_present - 1, 0))
        obstacle = 1 + jnp.argmax((jnp.cumsum(present) - 1 == r) & present)
        nxt = jnp.where((st == C.GRASS) & hardcore, obstacle, C.GRASS).astype(jnp.int32)
        st = jnp.where(switch, nxt, st)
        one = switch

        carry = _Carry(y, vel, counter, st, one, y_orig, pit_diff, s_h, s_slope, s_n)
        return carry, (x_out, y, kind, cand, cand_ok)

    init = _Carry(
        y=jnp.float32(C.TERRAIN_HEIGHT),
        velocity=jnp.float32(0.0),
        counter=jnp.int32(C.TERRAIN_STARTPAD),
        state=jnp.int32(C.GRASS),
        oneshot=jnp.bool_(False),
        y_orig=jnp.float32(0.0),
        pit_diff=jnp.float32(0.0),
        stair_h=jnp.float32(0.0),
        stair_slope=jnp.float32(1.0),
        stair_n=jnp.int32(0),
    )
    idx = jnp.arange(C.TERRAIN_LENGTH, dtype=jnp.int32)
    _, (xs, ys, kinds, cand, cand_ok) = jax.lax.scan(column, init, (idx, uniforms), unroll=unroll)
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
    xs = grid.x_min + grid.dx * jnp.arange(grid.n, dtype=jnp.float32)
    h = jnp.interp(xs, terrain.x, terrain.y)  # constant beyond the ends
    b = terrain.boxes
    x0 = jnp.where(terrain.box_valid, b[:, 0] - 1e-4, jnp.inf)
    k = jnp.clip(jnp.searchsorted(x0, xs, side="right") - 1, 0, b.shape[0] - 1)
    inside = (xs >= x0[k]) & (xs <= b[k, 1] + 1e-4) & terrain.box_valid[k]
    return jnp.where(inside, jnp.maximum(h, b[k, 3]), h)


def height_at(profile: jax.Array, grid: Grid, x: jax.Array) -> jax.Array:
    """Linear interpolation of the profile at world x (clamped at the ends), any shape of x."""
    u = (x - grid.x_min) / grid.dx
    j = jnp.clip(jnp.floor(u), 0, grid.n - 2).astype(jnp.int32)
    t = jnp.clip(u - j, 0.0, 1.0)
    return profile[j] * (1.0 - t) + profile[j + 1] * t
