"""Analytic sensing against the terrain profile: the 10-ray lidar and the hull-ground test.

``mjx.ray`` ignores heightfields (returns -1), so the lidar intersects each ray with the profile's
segments directly: the profile is piecewise linear on the grid, a ray of length 5.33 m spans at most
``window`` cells ahead of the hull, and one ``dynamic_slice`` plus a [rays x window] segment-ray
test gives all fractions. Because the physics heightfield is built from the same profile, the lidar
sees exactly what the feet collide with (stump sides and pit walls as one-cell-wide faces).
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from envs.walker import constants as C
from envs.walker.terrain import Grid, height_at

RAY_ANGLES = C.LIDAR_ANGLE_STEP * np.arange(C.LIDAR_N, dtype=np.float32)
RAY_DIRS = np.stack([np.sin(RAY_ANGLES), -np.cos(RAY_ANGLES)], axis=-1).astype(np.float32)  # [10, 2]


def window_cells(grid: Grid) -> int:
    """Profile segments a ray can cross: from the hull's cell up to LIDAR_RANGE ahead."""
    return int(math.ceil(C.LIDAR_RANGE / grid.dx)) + 2


def lidar(profile: jax.Array, grid: Grid, origin: jax.Array) -> jax.Array:
    """Fractions in (0, 1] along each ray to the first terrain hit (1 if none); shape [10]."""
    w = window_cells(grid)
    j0 = jnp.clip(jnp.floor((origin[0] - grid.x_min) / grid.dx).astype(jnp.int32), 0, grid.n - 1 - w)
    hs = jax.lax.dynamic_slice(profile, (j0,), (w + 1,))
    xs = grid.x_min + grid.dx * (j0 + jnp.arange(w + 1, dtype=jnp.float32))
    a = jnp.stack([xs[:-1], hs[:-1]], -1)  # [w, 2] segment starts
    e = jnp.stack([xs[1:] - xs[:-1], hs[1:] - hs[:-1]], -1)  # [w, 2] segment vectors
    d = jnp.asarray(RAY_DIRS) * C.LIDAR_RANGE  # [10, 2] full ray vectors

    cross = lambda u, v: u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]  # noqa: E731
    ap = a[None, :, :] - origin[None, None, :]  # [1, w, 2]
    denom = cross(d[:, None, :], e[None, :, :])  # [10, w]
    safe = jnp.where(jnp.abs(denom) > 1e-9, denom, 1.0)
    t = cross(ap, e[None]) / safe  # fraction along the ray
    s = cross(ap, d[:, None, :]) / safe  # fraction along the segment
    hit = (jnp.abs(denom) > 1e-9) & (t >= 0.0) & (t <= 1.0) & (s >= 0.0) & (s <= 1.0)
    return jnp.min(jnp.where(hit, t, 1.0), axis=1)


def _hull_samples(per_edge: int = 6) -> np.ndarray:
    """Points along the hull polygon's perimeter (hull frame, metres)."""
    p = np.asarray(C.HULL_POLY, np.float32) / C.SCALE
    q = np.roll(p, -1, axis=0)
    t = np.arange(per_edge, dtype=np.float32) / per_edge
    return (p[:, None, :] + t[None, :, None] * (q - p)[:, None, :]).reshape(-1, 2)


HULL_SAMPLES = _hull_samples()


def hull_points(x: jax.Array, z: jax.Array, angle: jax.Array, pts: np.ndarray = HULL_SAMPLES) -> jax.Array:
    """Hull-frame points -> world (CCW angle), [n, 2]."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    px, py = pts[:, 0], pts[:, 1]
    return jnp.stack([x + c * px - s * py, z + s * px + c * py], -1)


def hull_touches_ground(profile: jax.Array, grid: Grid, x, z, angle) -> jax.Array:
    """True if any hull perimeter sample lies on or below the terrain profile.

    Samples are <= 0.21 m apart; every obstacle is at least one TERRAIN_STEP (0.47 m) wide, so no
    terrain feature can poke into the hull between two samples unnoticed.
    """
    p = hull_points(x, z, angle)
    return jnp.any(p[:, 1] <= height_at(profile, grid, p[:, 0]))
