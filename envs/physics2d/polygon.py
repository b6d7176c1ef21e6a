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

import jax.numpy as jnp

# Box2D 2.3.0 uses the same reference-face hysteresis (k_relativeTol, k_absoluteTol) for polygons as for edges
from envs.physics2d.edge import (ABSOLUTE_TOL, FACE, RELATIVE_TOL, VERTEX, clip_segment_to_line, finish_manifold,
                                 points, stack_manifold)
from envs.physics2d.vec import V2, argmax_of, argmin_of, min_of, pick_of


def box_polygon(box):
    """An axis-aligned box (x0, x1, y0, y1) as Box2D's ``b2PolygonShape::Set`` orders its corners:
    the convex hull from the rightmost (then lowest) point, counter-clockwise, so vertex 0 is
    (x1, y0) and face 0 the +x side. Returns (vertices (4, 2), outward normals (4, 2), centroid (2,))."""
    v, n, c = box_corners(box)
    return (jnp.stack([p.array() for p in v], -2), jnp.stack([p.array() for p in n], -2), c.array())


def box_corners(box):
    """``box_polygon`` as lists of ``V2`` (vertices, normals) and the centroid ``V2``, over ``box``'s
    leading shape."""
    x0, x1, y0, y1 = box[..., 0], box[..., 1], box[..., 2], box[..., 3]
    one, zero = jnp.ones_like(x0), jnp.zeros_like(x0)
    v = [V2(x1, y0), V2(x1, y1), V2(x0, y1), V2(x0, y0)]
    n = [V2(one, zero), V2(zero, one), V2(-one, zero), V2(zero, -one)]
    return v, n, V2(0.5 * (x0 + x1), 0.5 * (y0 + y1))


def max_separation(v1, n1, c1: V2, v2, c2: V2):
    """Box2D 2.3.0's ``b2FindMaxSeparation`` of polygon 2 from polygon 1's faces (vertices and normals:
    lists of ``V2``; centroids), elementwise over pairs: per face i the deepest vertex of polygon 2
    below it, ``min_j n1_i . (v2_j - v1_i)``, searched from the face whose normal points most towards
    c2 - c1 (the first on ties), stepping towards its better neighbour while that improves. Returns
    (face index, its separation)."""
    n = len(v1)
    s = [min_of([nn.dot(w - v) for w in v2]) for v, nn in zip(v1, n1)]  # every face's separation
    sel = lambda i: pick_of(s, i)  # noqa: E731
    edge = argmax_of([nn.dot(c2 - c1) for nn in n1])
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


def polygon_manifold(a_vertices, a_normals, a_centroid: V2, b_vertices, b_normals, b_centroid: V2, radius):
    """Box2D's manifold of static convex polygons A and convex polygons B (world vertices and outward
    normals: lists of ``V2``, CCW; area centroids ``V2``), elementwise over any broadcast shape of
    pairs; ``radius`` is the summed skin (0.02 in Box2D). A flat manifold (``edge.finish_manifold``);
    ``polygon_polygon_manifold`` says what it holds."""
    na, nb = len(a_vertices), len(b_vertices)
    edge_a, sep_a = max_separation(a_vertices, a_normals, a_centroid, b_vertices, b_centroid)
    edge_b, sep_b = max_separation(b_vertices, b_normals, b_centroid, a_vertices, a_centroid)
    touching = (sep_a <= radius) & (sep_b <= radius)
    face_b = sep_b > RELATIVE_TOL * sep_a + ABSOLUTE_TOL

    # reference polygon 1, incident polygon 2 (swapped for face B)
    edge1 = jnp.where(face_b, edge_b, edge_a)
    iv2 = jnp.where(face_b, (edge_b + 1) % nb, (edge_a + 1) % na)
    ref_v1 = pick_of(b_vertices, edge_b).where(face_b, pick_of(a_vertices, edge_a))
    ref_v2 = pick_of(b_vertices, (edge_b + 1) % nb).where(face_b, pick_of(a_vertices, (edge_a + 1) % na))
    rn = pick_of(b_normals, edge_b).where(face_b, pick_of(a_normals, edge_a))

    # b2FindIncidentEdge: the incident polygon's face most anti-parallel to the reference normal
    inc_a = argmin_of([nn.dot(rn) for nn in a_normals])  # A incident (face B)
    inc_b = argmin_of([nn.dot(rn) for nn in b_normals])  # B incident (face A)
    p0 = pick_of(a_vertices, inc_a).where(face_b, pick_of(b_vertices, inc_b))
    i1 = jnp.where(face_b, inc_a, inc_b)
    i2 = jnp.where(face_b, (inc_a + 1) % na, (inc_b + 1) % nb)
    p1 = pick_of(a_vertices, (inc_a + 1) % na).where(face_b, pick_of(b_vertices, (inc_b + 1) % nb))
    id0 = (edge1, i1, FACE, VERTEX)
    id1 = (edge1, i2, FACE, VERTEX)

    d = ref_v2 - ref_v1
    length = jnp.sqrt(d.dot(d))
    tangent = V2(d.x / length, d.y / length)
    normal = V2(tangent.y, -tangent.x)  # b2Cross(tangent, 1)
    front = normal.dot(ref_v1)
    side1 = -tangent.dot(ref_v1) + radius
    side2 = tangent.dot(ref_v2) + radius
    q0, q1, c0, c1, ok1 = clip_segment_to_line(p0, p1, id0, id1, -tangent, side1, edge1)
    q0, q1, c0, c1, ok2 = clip_segment_to_line(q0, q1, c0, c1, tangent, side2, iv2)
    # the separations are measured from the plane through ref_v1: normal . q - front
    return finish_manifold(touching, face_b, normal, ref_v1, edge1, q0, q1, c0, c1, ok1 & ok2, radius,
                           offset=front)


def polygon_polygon_manifold(a_vertices, a_normals, a_centroid, b_vertices, b_normals, b_centroid, radius):
    """Box2D's manifold of a static convex polygon A and a convex polygon B (world vertices (N, 2) CCW,
    outward normals (N, 2), area centroids (2,)); ``radius`` is the summed skin (0.02 in Box2D).

    Returns the dict of ``edge.edge_polygon_manifold``: ``on`` (2,), ``face_b`` (), ``ref_normal`` (2,),
    ``ref_point`` (2,) (the reference face's first vertex), ``ref_index`` (), ``clip`` (2, 2) (on B for
    face A, on A for face B), ``separation`` (2,) (minus the radius), ``normal`` (2,) (A to B),
    ``point`` (2, 2) (midway between the skins), ``id`` (2,) int32.
    """
    return stack_manifold(polygon_manifold(points(a_vertices), points(a_normals), V2.of(a_centroid),
                                           points(b_vertices), points(b_normals), V2.of(b_centroid), radius))


def polygon_obstacles_manifolds(boxes, valid, vertices, normals, centroid, radius):
    """``polygon_polygon_manifold`` of one polygon (B) against every box obstacle (K, 4) as (x0, x1,
    y0, y1); ``valid`` (K,) masks obstacles that do not exist. Leaves get a leading (K,) axis."""
    bv, bn, bc = box_corners(boxes)
    m = stack_manifold(polygon_manifold(bv, bn, bc, points(vertices), points(normals), V2.of(centroid), radius))
    m["on"] = m["on"] & valid[:, None]
    return m
