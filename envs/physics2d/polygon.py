"""Narrow phase: Box2D 2.3's polygon-vs-polygon manifold (``b2CollidePolygons``) for a static convex
obstacle A against a moving convex polygon B, branch-free and fixed-size.

1. max separation of B from A's faces and of A from B's (``b2FindMaxSeparation`` of Box2D 2.3.0, the
   version pybox2d and so Gymnasium build: a local search over faces from the face that points most
   towards the other centroid); no contact if either exceeds the radius (2 ``b2_polygonRadius`` =
   0.02 m);
2. B's face is the reference face ("face B") when its separation exceeds ``0.98 A's + 0.001``
   (Box2D 2.3.0's hysteresis; later versions compare against ``A's + 0.1 b2_linearSlop``), otherwise
   A's is ("face A");
3. the incident face (``b2FindIncidentEdge``: the other polygon's face most anti-parallel to the
   reference normal) is clipped to the reference face's side planes, each pushed out by the radius
   (``b2ClipSegmentToLine`` twice; fewer than two points means no contact), and the clipped points
   within the radius of the reference face are kept, compacted to the front.

The result has the layout of ``edge.edge_polygon_manifold`` (A in the edge's place), so the solver
treats a (polygon, obstacle) manifold as it treats a (polygon, edge) one: for face A the obstacle's
plane is fixed and the polygon's clip points move with it; for face B the obstacle's clip points are
fixed and the polygon's face moves. Everything is in the world frame; ids are Box2D's
``b2ContactFeature`` packed as in ``edge.pack_id``, swapped back to (A, B) for face B.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

# Box2D 2.3.0 uses the same reference-face hysteresis (k_relativeTol, k_absoluteTol) for polygons as for edges
from envs.physics2d.edge import ABSOLUTE_TOL, FACE, RELATIVE_TOL, VERTEX, clip_segment_to_line, pack_id
from envs.physics2d.vec import dot


def box_polygon(box):
    """An axis-aligned box (x0, x1, y0, y1) as Box2D's ``b2PolygonShape::Set`` orders its corners:
    the convex hull from the rightmost (then lowest) point, counter-clockwise, so vertex 0 is
    (x1, y0) and face 0 the +x side. Returns (vertices (4, 2), outward normals (4, 2), centroid (2,))."""
    x0, x1, y0, y1 = box[..., 0], box[..., 1], box[..., 2], box[..., 3]
    v = jnp.stack([jnp.stack([x1, y0], -1), jnp.stack([x1, y1], -1),
                   jnp.stack([x0, y1], -1), jnp.stack([x0, y0], -1)], -2)
    one, zero = jnp.ones_like(x0), jnp.zeros_like(x0)
    n = jnp.stack([jnp.stack([one, zero], -1), jnp.stack([zero, one], -1),
                   jnp.stack([-one, zero], -1), jnp.stack([zero, -one], -1)], -2)
    c = jnp.stack([0.5 * (x0 + x1), 0.5 * (y0 + y1)], -1)
    return v, n, c


def _pick(rows, i):
    """rows[i] by an exact one-hot sum (a gather-free pick that keeps the kernel's ops elementwise)."""
    idx = jnp.arange(rows.shape[0])
    return jnp.sum(jnp.where((idx == i)[:, None], rows, 0.0), 0)


def max_separation(v1, n1, c1, v2, c2):
    """Box2D 2.3.0's ``b2FindMaxSeparation`` of polygon 2 from polygon 1's faces (vertices, normals,
    centroids): per face i the deepest vertex of polygon 2 below it, ``min_j n1_i . (v2_j - v1_i)``,
    searched from the face whose normal points most towards c2 - c1 (the first on ties), stepping
    towards its better neighbour while that improves. Returns (face index, its separation)."""
    n = v1.shape[0]
    s = jnp.min(jnp.sum(n1[:, None] * (v2[None] - v1[:, None]), -1), 1)  # (N,) every face's separation
    sel = lambda i: jnp.sum(jnp.where(jnp.arange(n) == i, s, 0.0))
    edge = jnp.argmax(dot(n1, (c2 - c1)[None]))
    s0, prev, nxt = sel(edge), (edge - 1) % n, (edge + 1) % n
    sp, sn = sel(prev), sel(nxt)
    go_prev = (sp > s0) & (sp > sn)
    go_next = ~go_prev & (sn > s0)
    inc = jnp.where(go_prev, n - 1, 1)
    best = jnp.where(go_prev, prev, jnp.where(go_next, nxt, edge))
    best_s = jnp.where(go_prev, sp, jnp.where(go_next, sn, s0))
    moving = go_prev | go_next
    for _ in range(n - 2):  # the local search, at most once round the polygon
        cand = (best + inc) % n
        sc = sel(cand)
        step = moving & (sc > best_s)
        best, best_s = jnp.where(step, cand, best), jnp.where(step, sc, best_s)
        moving = step
    return best, best_s


def polygon_polygon_manifold(a_vertices, a_normals, a_centroid, b_vertices, b_normals, b_centroid, radius):
    """Box2D's manifold of a static convex polygon A and a convex polygon B (world vertices (N, 2) CCW,
    outward normals (N, 2), area centroids (2,)); ``radius`` is the summed skin (0.02 in Box2D).

    Returns the dict of ``edge.edge_polygon_manifold``: ``on`` (2,), ``face_b`` (), ``ref_normal`` (2,),
    ``ref_point`` (2,) (the reference face's first vertex), ``ref_index`` (), ``clip`` (2, 2) (on B for
    face A, on A for face B), ``separation`` (2,) (minus the radius), ``normal`` (2,) (A to B),
    ``point`` (2, 2) (midway between the skins), ``id`` (2,) int32.
    """
    na, nb = a_vertices.shape[0], b_vertices.shape[0]
    edge_a, sep_a = max_separation(a_vertices, a_normals, a_centroid, b_vertices, b_centroid)
    edge_b, sep_b = max_separation(b_vertices, b_normals, b_centroid, a_vertices, a_centroid)
    touching = (sep_a <= radius) & (sep_b <= radius)
    face_b = sep_b > RELATIVE_TOL * sep_a + ABSOLUTE_TOL

    # reference polygon 1, incident polygon 2 (swapped for face B)
    edge1 = jnp.where(face_b, edge_b, edge_a)
    iv2 = jnp.where(face_b, (edge_b + 1) % nb, (edge_a + 1) % na)
    ref_v1 = jnp.where(face_b, _pick(b_vertices, edge_b), _pick(a_vertices, edge_a))
    ref_v2 = jnp.where(face_b, _pick(b_vertices, (edge_b + 1) % nb), _pick(a_vertices, (edge_a + 1) % na))
    rn = jnp.where(face_b, _pick(b_normals, edge_b), _pick(a_normals, edge_a))

    # b2FindIncidentEdge: the incident polygon's face most anti-parallel to the reference normal
    inc_a = jnp.argmin(dot(a_normals, rn[None]))  # A incident (face B)
    inc_b = jnp.argmin(dot(b_normals, rn[None]))  # B incident (face A)
    p0 = jnp.where(face_b, _pick(a_vertices, inc_a), _pick(b_vertices, inc_b))
    i1 = jnp.where(face_b, inc_a, inc_b).astype(jnp.int32)
    i2 = jnp.where(face_b, (inc_a + 1) % na, (inc_b + 1) % nb).astype(jnp.int32)
    p1 = jnp.where(face_b, _pick(a_vertices, (inc_a + 1) % na), _pick(b_vertices, (inc_b + 1) % nb))
    e1 = edge1.astype(jnp.int32)
    id0 = jnp.stack([e1, i1, jnp.int32(FACE), jnp.int32(VERTEX)])
    id1 = jnp.stack([e1, i2, jnp.int32(FACE), jnp.int32(VERTEX)])

    d = ref_v2 - ref_v1
    tangent = d / jnp.sqrt(dot(d, d))
    normal = jnp.stack([tangent[1], -tangent[0]])  # b2Cross(tangent, 1)
    front = dot(normal, ref_v1)
    side1 = -dot(tangent, ref_v1) + radius
    side2 = dot(tangent, ref_v2) + radius
    q0, q1, c0, c1, ok1 = clip_segment_to_line(p0, p1, id0, id1, -tangent, side1, e1)
    q0, q1, c0, c1, ok2 = clip_segment_to_line(q0, q1, c0, c1, tangent, side2, iv2.astype(jnp.int32))
    sep0 = dot(normal, q0) - front
    sep1 = dot(normal, q1) - front
    ok = touching & ok1 & ok2
    keep0, keep1 = ok & (sep0 <= radius), ok & (sep1 <= radius)
    clip = jnp.stack([jnp.where(keep0, q0, q1), q1])
    sep = jnp.stack([jnp.where(keep0, sep0, sep1), sep1])
    ids = jnp.stack([jnp.where(keep0, c0, c1), c1])
    ids = jnp.where(face_b, ids[:, jnp.asarray([1, 0, 3, 2])], ids)  # swap features back to (A, B)
    on = jnp.stack([keep0 | keep1, keep0 & keep1])
    point = clip - 0.5 * sep[:, None] * normal[None]
    return dict(on=on, face_b=face_b, ref_normal=normal, ref_point=ref_v1, ref_index=edge1,
                clip=clip, separation=sep - radius, normal=jnp.where(face_b, -normal, normal), point=point,
                id=pack_id(ids[:, 0], ids[:, 1], ids[:, 2], ids[:, 3]))


def polygon_obstacles_manifolds(boxes, valid, vertices, normals, centroid, radius):
    """``polygon_polygon_manifold`` of one polygon (B) against every box obstacle (K, 4) as (x0, x1,
    y0, y1); ``valid`` (K,) masks obstacles that do not exist. Leaves get a leading (K,) axis."""
    bv, bn, bc = box_polygon(boxes)
    m = jax.vmap(lambda v, n, c: polygon_polygon_manifold(v, n, c, vertices, normals, centroid, radius))(bv, bn, bc)
    m["on"] = m["on"] & valid[:, None]
    return m
