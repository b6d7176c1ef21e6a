"""Narrow phase: Box2D 2.3's edge-vs-polygon manifold for lone edges (no ghost vertices).

``b2CollideEdgeAndPolygon`` (Box2D/Collision/b2CollideEdge.cpp, class ``b2EPCollider``) for an edge
without neighbours (``m_hasVertex0`` / ``m_hasVertex3`` false, as every separate ``b2EdgeShape``
fixture), written branch-free and fixed-size:

1. the edge normal ``n`` is the edge's right-hand normal, flipped towards the polygon's centroid;
2. edge separation: ``min_i n . (v_i - e1)`` over the polygon's vertices;
3. polygon separation: per polygon face ``i`` the deeper edge end below that face,
   ``min(-N_i . (e1 - v_i), -N_i . (e2 - v_i))`` with the sign of a distance outside the face, and its
   maximum over faces (the first one on ties). Without neighbours Box2D's adjacency test never skips a
   face, so every face counts;
4. no contact if either separation exceeds the radius (2 ``b2_polygonRadius`` = 0.02 m);
5. the polygon face is the reference face ("face B") when its separation exceeds
   ``0.98 * edge separation + 0.001`` (Box2D's hysteresis), otherwise the edge is ("face A");
6. the incident segment (the polygon face most anti-parallel to ``n`` for face A, the edge for face B)
   is clipped to the reference face's side planes (``b2ClipSegmentToLine`` twice; fewer than two
   points after either clip means no contact), and clipped points deeper than the radius are kept,
   compacted to the front (Box2D's ``pointCount``).

Everything is in the world frame (the edge belongs to a static body). Contact ids follow Box2D's
``b2ContactFeature`` (index/type of A's and B's feature, swapped back for face B), packed into one
int per point so a solver can warm start a point only when its feature is unchanged.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs.physics2d.vec import dot

RELATIVE_TOL = 0.98  # Box2D's k_relativeTol / k_absoluteTol (reference-face hysteresis)
ABSOLUTE_TOL = 0.001
VERTEX, FACE = 0, 1  # b2ContactFeature::e_vertex, e_face


def polygon_normals(vertices) -> np.ndarray:
    """Outward unit normals (N, 2) of a convex CCW polygon's faces v_i -> v_{i+1} (Box2D's m_normals)."""
    v = np.asarray(vertices, np.float64)
    e = np.roll(v, -1, axis=0) - v
    n = np.stack([e[:, 1], -e[:, 0]], -1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def pack_id(index_a, index_b, type_a, type_b):
    """One int32 per contact feature, Box2D's ``b2ContactID.key`` (the four bytes of ``b2ContactFeature``)."""
    return (index_a + 256 * index_b + 65536 * type_a + 16777216 * type_b).astype(jnp.int32)


def _right_normal(d):
    return jnp.stack([d[..., 1], -d[..., 0]], -1)


def clip_segment_to_line(p0, p1, id0, id1, normal, offset, vertex_index_a):
    """``b2ClipSegmentToLine`` for exactly two outputs.

    Keeps the points of segment (p0, p1) with ``normal . p - offset <= 0``; a crossing adds the
    intersection (id: A's vertex ``vertex_index_a`` against B's face ``id0``'s B index). Returns
    (q0, q1, id0', id1', ok) where ``ok`` says Box2D got two points (otherwise it stops: no contact).
    ids are (4,) int arrays (index_a, index_b, type_a, type_b).
    """
    d0 = dot(normal, p0) - offset
    d1 = dot(normal, p1) - offset
    both = (d0 <= 0.0) & (d1 <= 0.0)
    cross_ = d0 * d1 < 0.0
    t = d0 / jnp.where(cross_, d0 - d1, 1.0)
    pi = p0 + t * (p1 - p0)
    idi = jnp.stack([jnp.asarray(vertex_index_a, jnp.int32), id0[1], jnp.int32(VERTEX), jnp.int32(FACE)])
    q0 = jnp.where(d0 <= 0.0, p0, p1)
    i0 = jnp.where(d0 <= 0.0, id0, id1)
    q1 = jnp.where(both, p1, pi)
    i1 = jnp.where(both, id1, idi)
    return q0, q1, i0, i1, both | cross_


def edge_polygon_manifold(e1, e2, vertices, normals, centroid, radius):
    """Box2D's manifold of one lone edge (e1 -> e2, world) and a convex polygon (world vertices (N, 2)
    CCW, outward normals (N, 2), area centroid (2,)); ``radius`` is the summed skin (0.02 in Box2D).

    Returns a dict (all fixed-size):
      ``on`` (2,) bool: manifold points present (compacted: point 1 only if point 0);
      ``face_b`` () bool: the polygon's face is the reference face;
      ``ref_normal`` (2,), ``ref_point`` (2,): the reference face's outward normal and first vertex
      (the edge's for face A, the polygon face's for face B);
      ``ref_index`` () int: the polygon face (face B) or the polygon's incident face (face A);
      ``clip`` (2, 2): the clip points (on the polygon for face A, on the edge for face B);
      ``separation`` (2,): ``ref_normal . (clip - ref_point) - radius`` (Box2D's contact separation);
      ``normal`` (2,): the contact normal from the edge to the polygon (``ref_normal``, or its negation
      for face B), ``point`` (2, 2): Box2D's world point (midway between the two skins);
      ``id`` (2,) int32: packed contact features.
    """
    nv = vertices.shape[0]
    idx = jnp.arange(nv)
    d = e2 - e1
    d = d / jnp.sqrt(dot(d, d))
    normal1 = _right_normal(d)
    front = dot(normal1, centroid - e1) >= 0.0
    n = jnp.where(front, normal1, -normal1)

    edge_sep = jnp.min(dot(vertices - e1, n[None]))
    s1 = dot(-normals, vertices - e1[None])
    s2 = dot(-normals, vertices - e2[None])
    poly_s = jnp.minimum(s1, s2)
    poly_index = jnp.argmax(poly_s)
    poly_sep = jnp.max(poly_s)
    touching = (edge_sep <= radius) & (poly_sep <= radius)
    face_b = poly_sep > RELATIVE_TOL * edge_sep + ABSOLUTE_TOL

    # face A: the polygon's incident face (most anti-parallel normal) against the edge
    inc = jnp.argmin(dot(normals, n[None]))
    inc2 = (inc + 1) % nv
    sel = lambda i: jnp.sum(jnp.where((idx == i)[:, None], vertices, 0.0), 0)  # exact one-hot pick
    seln = lambda i: jnp.sum(jnp.where((idx == i)[:, None], normals, 0.0), 0)
    a_p0, a_p1 = sel(inc), sel(inc2)
    a_id0 = jnp.stack([jnp.int32(0), inc.astype(jnp.int32), jnp.int32(FACE), jnp.int32(VERTEX)])
    a_id1 = jnp.stack([jnp.int32(0), inc2.astype(jnp.int32), jnp.int32(FACE), jnp.int32(VERTEX)])
    a_rv1, a_rv2 = jnp.where(front, e1, e2), jnp.where(front, e2, e1)
    a_i1, a_i2 = jnp.where(front, 0, 1), jnp.where(front, 1, 0)

    # face B: the edge against the polygon's face ``poly_index``
    b_i2 = (poly_index + 1) % nv
    b_id = jnp.stack([jnp.int32(0), poly_index.astype(jnp.int32), jnp.int32(VERTEX), jnp.int32(FACE)])

    p0 = jnp.where(face_b, e1, a_p0)
    p1 = jnp.where(face_b, e2, a_p1)
    id0 = jnp.where(face_b, b_id, a_id0)
    id1 = jnp.where(face_b, b_id, a_id1)
    rv1 = jnp.where(face_b, sel(poly_index), a_rv1)
    rv2 = jnp.where(face_b, sel(b_i2), a_rv2)
    rn = jnp.where(face_b, seln(poly_index), n)
    ri1 = jnp.where(face_b, poly_index, a_i1)
    ri2 = jnp.where(face_b, b_i2, a_i2)

    side1 = jnp.stack([rn[1], -rn[0]])
    q0, q1, i0, i1, ok1 = clip_segment_to_line(p0, p1, id0, id1, side1, dot(side1, rv1), ri1)
    q0, q1, i0, i1, ok2 = clip_segment_to_line(q0, q1, i0, i1, -side1, dot(-side1, rv2), ri2)
    sep0 = dot(rn, q0 - rv1)
    sep1 = dot(rn, q1 - rv1)
    ok = touching & ok1 & ok2
    keep0, keep1 = ok & (sep0 <= radius), ok & (sep1 <= radius)
    clip = jnp.stack([jnp.where(keep0, q0, q1), q1])
    sep = jnp.stack([jnp.where(keep0, sep0, sep1), sep1])
    ids = jnp.stack([jnp.where(keep0, i0, i1), i1])
    # face B: Box2D swaps the features back to (A = edge, B = polygon)
    ids = jnp.where(face_b, ids[:, jnp.asarray([1, 0, 3, 2])], ids)
    on = jnp.stack([keep0 | keep1, keep0 & keep1])
    contact_normal = jnp.where(face_b, -rn, rn)
    point = clip - 0.5 * sep[:, None] * rn[None]
    return dict(on=on, face_b=face_b, ref_normal=rn, ref_point=rv1, ref_index=jnp.where(face_b, poly_index, inc),
                clip=clip, separation=sep - radius, normal=contact_normal, point=point,
                id=pack_id(ids[:, 0], ids[:, 1], ids[:, 2], ids[:, 3]))


def polygon_edges_manifolds(edges, valid, vertices, normals, centroid, radius):
    """``edge_polygon_manifold`` of one polygon against every edge (S, 2, 2); ``valid`` (S,) masks edges
    that do not exist (their manifolds have no points). Leaves get a leading (S,) axis."""
    m = jax.vmap(lambda e: edge_polygon_manifold(e[0], e[1], vertices, normals, centroid, radius))(edges)
    m["on"] = m["on"] & valid[:, None]
    return m


def first_true(has, count: int):
    """Where ``has`` (S,) bool's first ``count`` True entries are, in order: ``(found (count,) bool,
    index (count,) int32)``, slot k holding the k-th True entry's index (0 and not found past the last).
    Compares, an ``any`` and an ``argmax``, not a scatter: on a GPU a scatter is a kernel plus its
    buffer's fill and copy."""
    rank = jnp.cumsum(has.astype(jnp.int32)) - 1
    pick = has[None, :] & (rank[None, :] == jnp.arange(count)[:, None])  # (count, S), rows one-hot or empty
    return jnp.any(pick, 1), jnp.argmax(pick, 1).astype(jnp.int32)


def select_edges(m, count: int):
    """The first ``count`` edges (in edge order) whose manifolds have points, as (count, ...) leaves plus
    ``edge`` (count,) int32 (their indices; -1 for an empty slot, whose leaves are zero / False). Edges
    past ``count`` are dropped. Each leaf is read at its slot's edge (one gather per leaf), not summed
    over a one-hot mask: on a GPU a mask's sums are a reduce kernel per leaf shape and slot."""
    found, at = first_true(m["on"][:, 0], count)
    edge = jnp.where(found, at, -1)
    out = {}
    for name, leaf in m.items():
        mask = found.reshape((count,) + (1,) * (leaf.ndim - 1))
        out[name] = jnp.where(mask, leaf[at], jnp.zeros((), leaf.dtype))
    out["edge"] = edge
    return out
