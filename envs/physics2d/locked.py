"""Exact velocity solve for a jointed mechanism whose joints are all *locked* (host-side, numpy).

When every revolute joint is pinned (its motor presses it into a limit) and nothing touches the
ground, the converged sequential-impulse solution is the projection of the bodies' velocities onto
{anchor velocities equal, relative spin zero} in the mass metric. Box2D needs ~180 Gauss-Seidel
passes to get there for a light leg on a heavy hull (mass ratio ~70); for a fixed pose the
projection is one constant (3B, 3B) matrix, so the step costs a mat-vec instead.
"""
from __future__ import annotations

import numpy as np

from envs.physics2d.model import Model


def locked_velocity_projector(model: Model, com: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """P (3B, 3B) with v_new = P @ v for v = [vx_0, vy_0, w_0, vx_1, ...] at the pose (com, angle)."""
    nb = model.num_bodies
    com = np.asarray(com, np.float64)
    angle = np.asarray(angle, np.float64)
    rows = []
    for J in model.joints:
        def arm(body, local):
            c, s = np.cos(angle[body]), np.sin(angle[body])
            d = np.asarray(local, np.float64) - model.local_com[body]
            return np.array([c * d[0] - s * d[1], s * d[0] + c * d[1]])

        ra, rb = arm(J.body_a, J.local_anchor_a), arm(J.body_b, J.local_anchor_b)
        for k in range(2):  # point rows: v_b + w_b x r_b - v_a - w_a x r_a = 0
            row = np.zeros(3 * nb)
            row[3 * J.body_b + k] = 1.0
            row[3 * J.body_a + k] = -1.0
            # (w x r)_x = -w r_y, (w x r)_y = w r_x
            row[3 * J.body_b + 2] = -rb[1] if k == 0 else rb[0]
            row[3 * J.body_a + 2] = ra[1] if k == 0 else -ra[0]
            rows.append(row)
        row = np.zeros(3 * nb)  # angle row: w_b - w_a = 0
        row[3 * J.body_b + 2] = 1.0
        row[3 * J.body_a + 2] = -1.0
        rows.append(row)
    jac = np.asarray(rows).reshape(-1, 3 * nb)
    minv = np.diag(np.stack([model.inv_mass, model.inv_mass, model.inv_inertia], 1).reshape(-1))
    if jac.shape[0] == 0:
        return np.eye(3 * nb)
    a = jac @ minv @ jac.T
    return np.eye(3 * nb) - minv @ jac.T @ np.linalg.solve(a, jac)
