"""Mass properties of convex polygons (host side, numpy), as Box2D's b2PolygonShape::ComputeMass.

Box2D ignores the polygon skin radius for mass; so do we.
"""
from __future__ import annotations

import numpy as np


def polygon_mass(vertices: np.ndarray, density: float):
    """(mass, centroid (2,), rotational inertia about the body origin) of a CCW convex polygon."""
    v = np.asarray(vertices, np.float64)
    if v.ndim != 2 or v.shape[1] != 2 or v.shape[0] < 3:
        raise ValueError(f"polygon needs >= 3 vertices of shape (n, 2), got {v.shape}")
    ref = v[0]
    area = 0.0
    center = np.zeros(2)
    inertia = 0.0
    for i in range(1, v.shape[0] - 1):  # fan triangulation around v[0]
        e1, e2 = v[i] - ref, v[i + 1] - ref
        d = e1[0] * e2[1] - e1[1] * e2[0]
        tri = 0.5 * d
        if tri <= 0:
            raise ValueError("polygon vertices must be counter-clockwise and convex")
        area += tri
        center += tri * (e1 + e2) / 3.0
        intx2 = e1[0] ** 2 + e2[0] * e1[0] + e2[0] ** 2
        inty2 = e1[1] ** 2 + e2[1] * e1[1] + e2[1] ** 2
        inertia += (0.25 / 3.0 * d) * (intx2 + inty2)
    mass = density * area
    center = center / area
    centroid = center + ref
    # inertia about the reference point -> about the centroid -> about the body origin
    i_origin = density * inertia + mass * (centroid @ centroid - center @ center)
    return mass, centroid, i_origin
