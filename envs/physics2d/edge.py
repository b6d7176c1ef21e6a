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

import jax.numpy as jnp
import numpy as np

from envs.physics2d.vec import V2, argmax_of, argmin_of, max_of, min_of, pick_of

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


def clip_segment_to_line(p0: V2, p1: V2, id0, id1, normal: V2, offset, vertex_index_a):
    """``b2ClipSegmentToLine`` for exactly two outputs, elementwise over per-pair arrays.

    Keeps the points of segment (p0, p1) with ``normal . p - offset <= 0``; a crossing adds the
    intersection (id: A's vertex ``vertex_index_a`` against B's face ``id0``'s B index). Returns
    (q0, q1, id0', id1', ok) where ``ok`` says Box2D got two points (otherwise it stops: no contact).
    ids are 4-tuples of int32 arrays (index_a, index_b, type_a, type_b).
    """
    d0 = normal.dot(p0) - offset
    d1 = normal.dot(p1) - offset
    both = (d0 <= 0.0) & (d1 <= 0.0)
    cross_ = d0 * d1 < 0.0
    t = d0 / jnp.where(cross_, d0 - d1, 1.0)
    pi = p0 + t * (p1 - p0)
    idi = (vertex_index_a, id0[1], VERTEX, FACE)
    first = d0 <= 0.0
    q0 = p0.where(first, p1)
    q1 = p1.where(both, pi)
    i0 = tuple(jnp.where(first, a, b) for a, b in zip(id0, id1))
    i1 = tuple(jnp.where(both, a, b) for a, b in zip(id1, idi))
    return q0, q1, i0, i1, both | cross_


def finish_manifold(touching, face_b, rn: V2, rv1: V2, ref_index, q0: V2, q1: V2, i0, i1, ok_clip, radius,
                    offset=None):
    """The end of a manifold, shared by edges and polygons: the clipped points within ``radius`` of the
    reference face (plane ``rn`` through ``rv1``: separation ``rn . (q - rv1)``, or ``rn . q - offset``
    as Box2D's polygon collider measures it) kept and compacted to the front, the features swapped
    back to (A, B) for face B, Box2D's world points midway between the skins. Returns the manifold as
    a flat dict of per-pair arrays (``stack_manifold`` gives the array layout)."""
    if offset is None:
        sep0, sep1 = rn.dot(q0 - rv1), rn.dot(q1 - rv1)
    else:
        sep0, sep1 = rn.dot(q0) - offset, rn.dot(q1) - offset
    ok = touching & ok_clip
    keep0, keep1 = ok & (sep0 <= radius), ok & (sep1 <= radius)
    c0 = q0.where(keep0, q1)
    s0 = jnp.where(keep0, sep0, sep1)
    j0 = tuple(jnp.where(keep0, a, b) for a, b in zip(i0, i1))
    ids = []
    for j in (j0, i1):  # face B: Box2D swaps the features back to (A = edge, B = polygon)
        ia, ib, ta, tb = (jnp.where(face_b, j[k], j[m]) for k, m in ((1, 0), (0, 1), (3, 2), (2, 3)))
        ids.append(pack_id(jnp.asarray(ia, jnp.int32), jnp.asarray(ib, jnp.int32), ta, tb))
    normal = (-rn).where(face_b, rn)
    p0 = c0 - (0.5 * s0) * rn
    p1 = q1 - (0.5 * sep1) * rn
    return dict(on0=keep0 | keep1, on1=keep0 & keep1, face_b=face_b, ref_nx=rn.x, ref_ny=rn.y, ref_px=rv1.x,
                ref_py=rv1.y, ref_index=ref_index, clip0x=c0.x, clip0y=c0.y, clip1x=q1.x, clip1y=q1.y,
                sep0=s0 - radius, sep1=sep1 - radius, nx=normal.x, ny=normal.y, point0x=p0.x, point0y=p0.y,
                point1x=p1.x, point1y=p1.y, id0=ids[0], id1=ids[1])


def stack_manifold(m):
    """A flat manifold (``finish_manifold``) in the array layout of ``edge_polygon_manifold``'s result."""
    v = lambda a, b: jnp.stack([m[a], m[b]], -1)  # noqa: E731
    return dict(on=v("on0", "on1"), face_b=m["face_b"], ref_normal=v("ref_nx", "ref_ny"),
                ref_point=v("ref_px", "ref_py"), ref_index=m["ref_index"],
                clip=jnp.stack([v("clip0x", "clip0y"), v("clip1x", "clip1y")], -2), separation=v("sep0", "sep1"),
                normal=v("nx", "ny"), point=jnp.stack([v("point0x", "point0y"), v("point1x", "point1y")], -2),
                id=v("id0", "id1"))


def edge_manifold(e1: V2, e2: V2, vertices, normals, centroid: V2, radius):
    """Box2D's manifold of lone edges (e1 -> e2, world) and convex polygons (world vertices and
    outward normals: lists of ``V2``, CCW; area centroid ``V2``), elementwise over any broadcast shape
    of (polygon, edge) pairs; ``radius`` is the summed skin (0.02 in Box2D). A flat manifold
    (``finish_manifold``); ``edge_polygon_manifold`` says what it holds."""
    nv = len(vertices)
    d = e2 - e1
    length = jnp.sqrt(d.dot(d))
    d = V2(d.x / length, d.y / length)
    normal1 = V2(d.y, -d.x)  # the right-hand normal
    front = normal1.dot(centroid - e1) >= 0.0
    n = normal1.where(front, -normal1)

    edge_sep = min_of([(v - e1).dot(n) for v in vertices])
    poly_s = [jnp.minimum((-nn).dot(v - e1), (-nn).dot(v - e2)) for v, nn in zip(vertices, normals)]
    poly_index = argmax_of(poly_s)
    poly_sep = max_of(poly_s)
    touching = (edge_sep <= radius) & (poly_sep <= radius)
    face_b = poly_sep > RELATIVE_TOL * edge_sep + ABSOLUTE_TOL

    # face A: the polygon's incident face (most anti-parallel normal) against the edge
    inc = argmin_of([nn.dot(n) for nn in normals])
    inc2 = (inc + 1) % nv
    a_id0 = (0, inc, FACE, VERTEX)
    a_id1 = (0, inc2, FACE, VERTEX)
    a_rv1, a_rv2 = e1.where(front, e2), e2.where(front, e1)
    a_i1, a_i2 = jnp.where(front, 0, 1), jnp.where(front, 1, 0)

    # face B: the edge against the polygon's face ``poly_index``
    b_i2 = (poly_index + 1) % nv
    b_id = (0, poly_index, VERTEX, FACE)

    p0 = e1.where(face_b, pick_of(vertices, inc))
    p1 = e2.where(face_b, pick_of(vertices, inc2))
    id0 = tuple(jnp.where(face_b, b, a) for a, b in zip(a_id0, b_id))
    id1 = tuple(jnp.where(face_b, b, a) for a, b in zip(a_id1, b_id))
    rv1 = pick_of(vertices, poly_index).where(face_b, a_rv1)
    rv2 = pick_of(vertices, b_i2).where(face_b, a_rv2)
    rn = pick_of(normals, poly_index).where(face_b, n)
    ri1 = jnp.where(face_b, poly_index, a_i1)
    ri2 = jnp.where(face_b, b_i2, a_i2)

    side1 = V2(rn.y, -rn.x)
    q0, q1, i0, i1, ok1 = clip_segment_to_line(p0, p1, id0, id1, side1, side1.dot(rv1), ri1)
    q0, q1, i0, i1, ok2 = clip_segment_to_line(q0, q1, i0, i1, -side1, (-side1).dot(rv2), ri2)
    return finish_manifold(touching, face_b, rn, rv1, jnp.where(face_b, poly_index, inc), q0, q1, i0, i1,
                           ok1 & ok2, radius)


def points(a):
    """A (N, 2) array as a list of ``V2``."""
    return [V2.of(a[i]) for i in range(a.shape[0])]


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
    return stack_manifold(edge_manifold(V2.of(e1), V2.of(e2), points(vertices), points(normals), V2.of(centroid),
                                        radius))


def polygon_edges_manifolds(edges, valid, vertices, normals, centroid, radius):
    """``edge_polygon_manifold`` of one polygon against every edge (S, 2, 2); ``valid`` (S,) masks edges
    that do not exist (their manifolds have no points). Leaves get a leading (S,) axis."""
    m = edge_manifold(V2.of(edges[:, 0]), V2.of(edges[:, 1]), points(vertices), points(normals), V2.of(centroid),
                      radius)
    m = stack_manifold(m)
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


def first_manifolds(candidates, count: int):
    """The first ``count`` candidates (in order) whose manifolds have points. ``candidates``: a list of
    (flat manifold of per-world leaves, fixture key); returns ``count`` flat manifolds with ``key``
    added, zero / False (key 0) in slots left empty; candidates past ``count`` are dropped. An
    unrolled loop of selects (each candidate's rank among those with points), so it stays inside one
    elementwise GPU kernel (``select_edges`` is the same for stacked leaves)."""
    leaves = dict(candidates[0][0], key=candidates[0][1])
    out = [{name: jnp.zeros(jnp.shape(leaf), jnp.result_type(leaf)) for name, leaf in leaves.items()}
           for _ in range(count)]
    rank = jnp.zeros(jnp.shape(leaves["on0"]), jnp.int32)  # candidates with points so far
    for m, key in candidates:
        on = m["on0"]
        m = dict(m, key=key)
        for k in range(count):
            take = on & (rank == k)
            out[k] = {name: jnp.where(take, m[name], leaf) for name, leaf in out[k].items()}
        rank = rank + on.astype(jnp.int32)
    return out


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
