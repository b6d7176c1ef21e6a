"""Narrow phase: polygon vertices against a static height-field polyline (the ground).

The ground is a polyline with strictly increasing x (a height field), given as points (P, 2). Each
polygon vertex is tested against the segment directly below/above it; its separation is measured
along that segment's upward normal. This replaces Box2D's edge-vs-polygon manifold (which yields the
same vertex points on a face contact) with something branch-free and fixed-size. Vertices outside
the polyline's x-range never touch. For sensors we also test the polyline's points against the
polygon, so a terrain peak poking into a face without any vertex below the ground still counts.
"""
from __future__ import annotations

import jax.numpy as jnp

from envs.physics2d.vec import dot


def segment_frames(ground):
    """Per segment: start point (S, 2), unit upward normal (S, 2), x-range (S,), (S,)."""
    p0, p1 = ground[:-1], ground[1:]
    d = p1 - p0
    length = jnp.sqrt(dot(d, d))
    normal = jnp.stack([-d[:, 1], d[:, 0]], -1) / length[:, None]
    return p0, normal, p0[:, 0], p1[:, 0]


def vertex_vs_polyline(points, ground):
    """For world points (V, 2): separation (V,), normal (V, 2), plane point (V, 2), inside (V,) bool.

    ``inside`` is False for points outside the polyline's x-range (no contact possible there).
    The segment is selected with a one-hot mask over the (few) segments instead of a gather, which
    keeps the batched program a pure elementwise fusion. The selection is a masked sum, not a matrix
    product: on GPUs a float32 dot may run in TF32 (JAX's default precision), which would round the
    selected normal and plane point to 10 mantissa bits; the sum of one selected term and zeros is
    exact on every backend.
    """
    p0, normal, x0, x1 = segment_frames(ground)
    x = points[:, 0:1]
    last = jnp.arange(x0.shape[0]) == x0.shape[0] - 1
    sel = (x >= x0[None]) & ((x < x1[None]) | (last[None] & (x <= x1[None])))  # (V, S)
    self_ = sel.astype(points.dtype)
    n = jnp.sum(self_[:, :, None] * normal[None], axis=1)
    q = jnp.sum(self_[:, :, None] * p0[None], axis=1)
    inside = jnp.any(sel, axis=1)
    sep = jnp.where(inside, dot(points - q, n), jnp.inf)
    return sep, n, q, inside


def polyline_points_in_polygon(ground, vertices, radius):
    """Whether any polyline point lies within ``radius`` of the inside of a convex CCW polygon."""
    v0 = vertices
    v1 = jnp.roll(vertices, -1, axis=0)
    e = v1 - v0
    out = jnp.stack([e[:, 1], -e[:, 0]], -1)
    out = out / jnp.sqrt(dot(out, out))[:, None]  # outward face normals (F, 2)
    # elementwise, not a dot: full float32 products on every backend (no TF32 on GPUs)
    s = ground[:, None, 0] * out[None, :, 0] + ground[:, None, 1] * out[None, :, 1] - dot(v0, out)[None]  # (P, F)
    return jnp.any(jnp.max(s, axis=1) <= radius)


def vertex_segment_touching(points, ground, radius):
    """(V, S) bool: vertex within ``radius`` of segment s (finite segment, from its upper side).

    This is the per (shape, ground edge) view of contact that Box2D's contact listener reports
    (one contact per fixture pair), used by environments that react to begin/end events.
    """
    p0, normal, _, _ = segment_frames(ground)
    d = ground[1:] - ground[:-1]  # (S, 2)
    rel = points[:, None, :] - p0[None]  # (V, S, 2)
    t_raw = jnp.sum(rel * d[None], -1) / jnp.sum(d * d, -1)[None]
    t = jnp.clip(t_raw, 0.0, 1.0)
    closest = p0[None] + t[..., None] * d[None]
    diff = points[:, None, :] - closest
    dist = jnp.sqrt(jnp.sum(diff * diff, -1))
    # below the segment itself (not merely below its infinite line, which steep far-away segments
    # would report for any point in the sky) means penetrating
    below = (jnp.sum(rel * normal[None], -1) < 0.0) & (t_raw > 0.0) & (t_raw < 1.0)
    return below | (dist <= radius)
