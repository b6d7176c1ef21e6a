"""Continuous collision: Box2D 2.3's time of impact (``b2TimeOfImpact``) of a moving convex polygon
against static convex shapes (edges as two-vertex shapes, boxes as four), fixed-size and branch-free.

Box2D advances the two sweeps conservatively until the distance between the shapes' cores (no skin)
falls to ``target = max(linear_slop, radius - 3 linear_slop)`` (0.005 m for two 0.01 m skins), within
``tolerance = 0.25 linear_slop``; its result states are reproduced as:
  * cores overlapping at the start (distance 0): ``e_overlapped``, no impact;
  * closer than ``target + tolerance`` at the start: ``e_touching`` at t = 0;
  * otherwise the first time the distance reaches ``target`` (``e_touching`` at t), or none in the
    step (``e_separated``).
Instead of Box2D's separating-axis root finder (data-dependent loops) the distance is sampled at
``samples`` equal fractions of the step, and the first interval that falls below the target is
resolved to 2^-``bisections`` of its length, keeping the time at which the distance is still at
least the target (Box2D's answer lies within ``tolerance`` of that distance; 4 + 8 resolve a step to
1/1024, under 1 mm at a walker's leg speeds). It is resolved in rounds of up to ``ROUND_PARTS``
equal parts, each round keeping the first part that ends below the target: the earliest crossing at
that resolution, the cell bisection would find wherever the distance falls through the interval
once (the same times, bit for bit, with a power-of-two ``samples``), in two dependent rounds instead
of eight (on a GPU each is a few kernels). Lowered for a CPU the rounds are halvings: bisection,
which evaluates the distance 8 times instead of 30, and where the distance crosses the target twice
may keep the later crossing. A pass that dips under the target between two samples and comes
back out is missed (Box2D's conservative advancement catches it): about 1 in 200 random sweeps
against pybox2d (tests/test_physics2d_toi.py). The distance is the exact Euclidean distance between the convex
cores (0 when the separating-axis test finds no gap), the quantity Box2D's GJK returns. A sweep is
Box2D's ``b2Sweep``: centre of mass and angle interpolated linearly over the step.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from envs.physics2d.vec import V2, dot, rotate, sincos


def point_segment_distance(p, a, b):
    """Distance from points ``p`` to segments ``a``-``b`` (broadcast over leading axes, (..., 2))."""
    d = b - a
    dd = dot(d, d)
    t = jnp.clip(dot(p - a, d) / jnp.where(dd > 0.0, dd, 1.0), 0.0, 1.0)
    r = p - a - t[..., None] * d
    return jnp.sqrt(dot(r, r))


def _faces(v):
    """A convex shape's faces v_i -> v_{i+1} (a two-vertex shape has both orientations of its segment)."""
    return v, jnp.roll(v, -1, axis=-2)


def _max_face_separation(p, q):
    """max over p's faces of the smallest signed distance of q's vertices outside that face (the
    separating-axis test; p counter-clockwise or two-vertex). p (..., n, 2), q (..., m, 2) -> (...)."""
    a, b = _faces(p)
    e = b - a
    n = jnp.stack([e[..., 1], -e[..., 0]], -1)
    n = n / jnp.sqrt(jnp.maximum(dot(n, n), 1e-30))[..., None]
    s = dot(q[..., None, :, :] - a[..., :, None, :], n[..., :, None, :])  # (..., n, m)
    return jnp.max(jnp.min(s, -1), -1)


def convex_distance(p, q):
    """Euclidean distance between two convex shapes' cores (0 when they overlap).
    p (..., n, 2) counter-clockwise (or two vertices), q (..., m, 2) the same; leading axes broadcast."""
    gap = jnp.maximum(_max_face_separation(p, q), _max_face_separation(q, p)) > 0.0
    pa, pb = _faces(p)
    qa, qb = _faces(q)
    d_pq = point_segment_distance(p[..., :, None, :], qa[..., None, :, :], qb[..., None, :, :])  # (..., n, m)
    d_qp = point_segment_distance(q[..., :, None, :], pa[..., None, :, :], pb[..., None, :, :])  # (..., m, n)
    d = jnp.minimum(jnp.min(d_pq, (-2, -1)), jnp.min(d_qp, (-2, -1)))
    return jnp.where(gap, d, 0.0)


def sweep_vertices(local, c0, a0, c1, a1, t):
    """World vertices of a polygon (``local`` (n, 2) from its centre of mass) on the sweep
    (c0, a0) -> (c1, a1) at fractions ``t`` (...) -> (..., n, 2)."""
    t = jnp.asarray(t)
    c = c0 + t[..., None] * (c1 - c0)
    a = a0 + t * (a1 - a0)
    return c[..., None, :] + rotate(a[..., None], local)


def sweep_distance(local, c0, a0, c1, a1, t, shapes):
    """``convex_distance(sweep_vertices(local, c0, a0, c1, a1, t), shapes)``: the distance from the
    polygon at sweep fractions ``t`` (leading axes broadcast against ``shapes``' (S,)) to each of
    ``shapes`` (S, m, 2).

    Lowered for a CPU it is those two functions on (..., n, 2) arrays. Lowered for a GPU it is the
    same arithmetic on every vertex and face as separate arrays (``V2``), all elementwise, which XLA
    fuses with its surroundings: in the array form the vertex stack, the faces' roll and the minima
    over a few vertices are each a kernel, about five per evaluation, and the search's evaluations
    depend on each other. XLA:CPU compiles long elementwise code slowly (minima as elementwise chains
    made the 2-D walker's step compile in 32 s instead of 22 s), and a CPU has no kernel launches to
    save. Where XLA fuses multiply-adds differently the two forms differ in the last bits."""
    return lax.platform_dependent(local, c0, a0, c1, a1, t, shapes,
                                  cpu=_sweep_distance_arrays, default=_sweep_distance_points)


def _sweep_distance_arrays(local, c0, a0, c1, a1, t, shapes):
    return convex_distance(sweep_vertices(local, c0, a0, c1, a1, t), shapes)


def _sweep_distance_points(local, c0, a0, c1, a1, t, shapes):
    t = jnp.asarray(t)
    cx, cy = c0[0] + t * (c1[0] - c0[0]), c0[1] + t * (c1[1] - c0[1])
    a = a0 + t * (a1 - a0)
    sin, cos = sincos(a)
    p = [V2(cx + (cos * local[i, 0] - sin * local[i, 1]), cy + (sin * local[i, 0] + cos * local[i, 1]))
         for i in range(local.shape[0])]
    q = [V2(shapes[:, j, 0], shapes[:, j, 1]) for j in range(shapes.shape[1])]
    gap = jnp.maximum(_max_face_separation_points(p, q), _max_face_separation_points(q, p)) > 0.0
    d = jnp.minimum(_min_vertex_face_distance(p, q), _min_vertex_face_distance(q, p))
    return jnp.where(gap, d, 0.0)


def _faces_points(v: list) -> list:
    """``_faces`` for a vertex list: (v_i, v_{i+1})."""
    return [(v[i], v[(i + 1) % len(v)]) for i in range(len(v))]


def _max_face_separation_points(p: list, q: list):
    """``_max_face_separation`` for vertex lists (``V2`` each)."""
    best = None
    for a, b in _faces_points(p):
        e = b - a
        nx, ny = e.y, -e.x
        norm = jnp.sqrt(jnp.maximum(nx * nx + ny * ny, 1e-30))
        nx, ny = nx / norm, ny / norm
        worst = None
        for v in q:
            s = (v.x - a.x) * nx + (v.y - a.y) * ny
            worst = s if worst is None else jnp.minimum(worst, s)
        best = worst if best is None else jnp.maximum(best, worst)
    return best


def _min_vertex_face_distance(p: list, q: list):
    """The least ``point_segment_distance`` from a vertex of ``p`` to a face of ``q`` (vertex lists)."""
    out = None
    for a, b in _faces_points(q):
        d = b - a
        dd = d.dot(d)
        den = jnp.where(dd > 0.0, dd, 1.0)
        for v in p:
            r = v - a
            t = jnp.clip(r.dot(d) / den, 0.0, 1.0)
            r = r - d * t
            dist = jnp.sqrt(r.dot(r))
            out = dist if out is None else jnp.minimum(out, dist)
    return out


def time_of_impact(local, c0, a0, c1, a1, shapes, valid, target: float, tolerance: float,
                   samples: int = 4, bisections: int = 8, from_touching: bool = True, parts: int | None = None):
    """The time of impact of one moving polygon with each static shape.

    ``local`` (n, 2) the polygon's vertices from its centre of mass (counter-clockwise); the sweep
    (c0 (2,), a0) -> (c1 (2,), a1) over one step; ``shapes`` (S, m, 2) static convex shapes, ``valid``
    (S,) bool. Returns (alpha (S,) in [0, 1], touching (S,) bool): Box2D's ``e_touching`` and its t
    (alpha 1 where not touching). ``from_touching=False`` drops the touching-at-the-start result.
    ``parts``: sub-intervals per refinement round (a power of two); None: ``ROUND_PARTS`` lowered for
    a GPU, where a round is a few kernel launches, and 2 (bisection) lowered for a CPU, where the
    rounds' extra distance evaluations are time (a 2-D walker step took 72 % longer with 16).
    """
    ts = jnp.linspace(0.0, 1.0, samples + 1, dtype=jnp.float32)
    d = sweep_distance(local, c0, a0, c1, a1, ts[:, None], shapes)  # (N + 1, S)
    d0 = d[0]
    start = valid & (d0 > 0.0) & (d0 < target + tolerance)
    below = d[1:] < target
    cross = valid & (d0 >= target + tolerance) & jnp.any(below, 0)
    first = jnp.argmax(below, 0)  # the first sample interval that ends below the target
    lo, hi = ts[first], ts[first + 1]

    def refine(parts):
        def run(lo, hi):
            for k in _rounds(bisections, parts):  # the interval in k equal parts, the first that ends below the target
                w = (hi - lo) / k  # exact when samples is a power of two: every bound is then a dyadic fraction
                t = lo + jnp.arange(1, k, dtype=jnp.float32)[:, None] * w  # (k - 1, S)
                below = sweep_distance(local, c0, a0, c1, a1, t, shapes) < target
                j = jnp.where(jnp.any(below, 0), jnp.argmax(below, 0) + 1, k)  # hi ends the last part
                lo, hi = lo + (j - 1) * w, jnp.where(j == k, hi, lo + j * w)
            return lo, hi
        return run

    if parts is None:
        lo, hi = lax.platform_dependent(lo, hi, cpu=refine(2), default=refine(ROUND_PARTS))
    else:
        lo, hi = refine(parts)(lo, hi)
    if not from_touching:
        start = jnp.zeros_like(start)
    touching = start | cross
    return jnp.where(start, 0.0, jnp.where(cross, lo, 1.0)), touching


#: sub-intervals per refinement round of the time-of-impact search (a power of two)
ROUND_PARTS = 16


def _rounds(bisections: int, parts: int = ROUND_PARTS) -> list[int]:
    """The parts of each refinement round that resolve an interval as ``bisections`` halvings would:
    ``parts`` at a time, the rest in the last round (8, 16 -> [16, 16]; 5, 16 -> [16, 2]; 2 parts: bisection)."""
    if parts < 2 or parts & (parts - 1):
        raise ValueError(f"time of impact: parts per round must be a power of two >= 2, got {parts}")
    step = parts.bit_length() - 1
    return [2 ** min(step, bisections - b) for b in range(0, bisections, step)]


def edge_shapes(edges):
    """Edges (S, 2, 2) as four-vertex shapes (a, b, b, a) (S, 4, 2), so edges and boxes form one
    list: the repeated vertices add zero-length faces, which change neither distance nor overlap."""
    return jnp.concatenate([edges, edges[:, ::-1]], 1)


def swept_gap(local, c0, a0, c1, a1, shapes, valid):
    """How far each shape's bounding box is from the polygon's swept bounding box (negative where
    they overlap; +inf for invalid shapes), with the sweep's box padded by the bulge of its rotation
    (a vertex at radius r turning by da leaves the chord by at most r (1 - cos(da / 2))). -> (S,)"""
    ends = jnp.concatenate([sweep_vertices(local, c0, a0, c1, a1, jnp.float32(0.0)),
                            sweep_vertices(local, c0, a0, c1, a1, jnp.float32(1.0))])
    r = jnp.max(jnp.sqrt(dot(local, local)))
    bulge = r * (1.0 - jnp.cos(jnp.minimum(jnp.abs(a1 - a0), jnp.pi) / 2.0))
    lo, hi = jnp.min(ends, 0) - bulge, jnp.max(ends, 0) + bulge
    s_lo, s_hi = jnp.min(shapes, 1), jnp.max(shapes, 1)
    gap = jnp.max(jnp.maximum(s_lo - hi, lo - s_hi), -1)
    return jnp.where(valid, gap, jnp.inf)


def earliest_impact(local, c0, a0, c1, a1, shapes, valid, target: float, tolerance: float, candidates: int,
                    samples: int = 4, bisections: int = 8, from_touching: bool = True):
    """The earliest time of impact of one moving polygon with any of ``shapes`` (S, 4, 2) (``valid``
    (S,)): ``time_of_impact`` on the ``candidates`` shapes nearest its swept bounding box (a shape
    whose box stays farther than ``target + tolerance`` from the sweep's cannot be touched). Returns
    (alpha (), impact () bool, crowded () bool: more shapes were in reach than ``candidates``)."""
    gap = swept_gap(local, c0, a0, c1, a1, shapes, valid)
    count = min(candidates, shapes.shape[0])
    neg, idx = jax.lax.top_k(-gap, count)
    reach = -neg <= target + tolerance
    alpha, touching = time_of_impact(local, c0, a0, c1, a1, shapes[idx], reach, target, tolerance,
                                     samples=samples, bisections=bisections, from_touching=from_touching)
    crowded = jnp.sum(gap <= target + tolerance) > count
    return jnp.min(jnp.where(touching, alpha, 1.0)), jnp.any(touching), crowded
