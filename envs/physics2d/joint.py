"""Revolute joint with motor and angle limits, solved as in Box2D 2.3 (b2RevoluteJoint).

Velocity phase: motor row (clamped to dt * max torque), then either the 3x3 block (point + limit,
with the limit impulse clamped to one sign and the point rows re-solved when it would pull) or the
2x2 point block. Position phase: non-linear Gauss-Seidel on the limit angle and the anchor gap.
Every branch is computed and selected with ``jnp.where`` so it vectorises over a batch of worlds.

All functions act on one joint; ``va, wa, vb, wb`` are the two bodies' velocities and spins: (2,)
arrays in ``warm_start``, ``V2`` in the iteration passes.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from envs.physics2d.vec import V2, cross, cross_sv2, rotate, rotate2

INACTIVE, AT_LOWER, AT_UPPER, EQUAL = 0, 1, 2, 3


def _k33(ma, mb, ia, ib, ra, rb):
    k11 = ma + mb + ra.y ** 2 * ia + rb.y ** 2 * ib
    k12 = -ra.y * ra.x * ia - rb.y * rb.x * ib
    k13 = -ra.y * ia - rb.y * ib
    k22 = ma + mb + ra.x ** 2 * ia + rb.x ** 2 * ib
    k23 = ra.x * ia + rb.x * ib
    k33 = ia + ib
    return k11, k12, k13, k22, k23, k33


def _solve22(k11, k12, k22, b1, b2):
    det = k11 * k22 - k12 * k12
    det = jnp.where(det != 0, 1.0 / det, 0.0)
    return det * (k22 * b1 - k12 * b2), det * (k11 * b2 - k12 * b1)


def _solve33(k, b):
    k11, k12, k13, k22, k23, k33 = k
    b1, b2, b3 = b
    # Cramer's rule on a symmetric 3x3 matrix
    c11 = k22 * k33 - k23 * k23
    c12 = k13 * k23 - k12 * k33
    c13 = k12 * k23 - k13 * k22
    det = k11 * c11 + k12 * c12 + k13 * c13
    det = jnp.where(det != 0, 1.0 / det, 0.0)
    c22 = k11 * k33 - k13 * k13
    c23 = k12 * k13 - k11 * k23
    c33 = k11 * k22 - k12 * k12
    return (
        det * (c11 * b1 + c12 * b2 + c13 * b3),
        det * (c12 * b1 + c22 * b2 + c23 * b3),
        det * (c13 * b1 + c23 * b2 + c33 * b3),
    )


def prepare(joint, lc_a, lc_b, angle_a, angle_b, prev_state, impulse, cfg):
    """Anchor arms, limit state and (possibly reset) accumulated impulses at the start of a step."""
    ra = rotate(angle_a, jnp.asarray(joint.local_anchor_a, jnp.float32) - lc_a)
    rb = rotate(angle_b, jnp.asarray(joint.local_anchor_b, jnp.float32) - lc_b)
    angle = angle_b - angle_a - joint.reference_angle
    if joint.enable_limit:
        if abs(joint.upper - joint.lower) < 2.0 * cfg.angular_slop:
            state = jnp.full_like(prev_state, EQUAL)
        else:
            state = jnp.where(angle <= joint.lower, AT_LOWER, jnp.where(angle >= joint.upper, AT_UPPER, INACTIVE))
        keep_z = (state == prev_state) & (state != INACTIVE)
        impulse = impulse.at[2].set(jnp.where(keep_z, impulse[2], 0.0))
    else:
        state = jnp.zeros_like(prev_state)
        impulse = impulse.at[2].set(0.0)
    return ra, rb, state.astype(jnp.int32), impulse


def warm_start(joint, m, ra, rb, impulse, motor_impulse, va, wa, vb, wb):
    ma, mb, ia, ib = m
    p = impulse[:2]
    lz = motor_impulse + impulse[2]
    va = va - ma * p
    wa = wa - ia * (cross(ra, p) + lz)
    vb = vb + mb * p
    wb = wb + ib * (cross(rb, p) + lz)
    return va, wa, vb, wb


def solve_velocity(joint, m, ra, rb, state, impulse, motor_impulse, va, wa, vb, wb, dt, motor_speed=None,
                   max_motor_torque=None):
    """One Gauss-Seidel pass over the joint's rows; returns new impulses and velocities.

    Component form (runs inside ``fused.per_world_fori_loop``): ``ra, rb, va, vb`` are ``V2``,
    ``impulse`` is the (x, y, limit) triple, ``state`` the limit state as a float.
    ``motor_speed`` / ``max_motor_torque``: per-world values for this step (Box2D's SetMotorSpeed /
    SetMaxMotorTorque before a step); None uses the joint's static ones.
    """
    ma, mb, ia, ib = m
    if joint.enable_motor:
        motor_mass = 1.0 / (ia + ib) if ia + ib > 0 else 0.0
        speed = joint.motor_speed if motor_speed is None else motor_speed
        torque = joint.max_motor_torque if max_motor_torque is None else max_motor_torque
        cdot = wb - wa - speed
        max_imp = dt * torque
        new = jnp.clip(motor_impulse - motor_mass * cdot, -max_imp, max_imp)
        new = jnp.where(state == EQUAL, motor_impulse, new)
        d = new - motor_impulse
        motor_impulse = new
        wa = wa - ia * d
        wb = wb + ib * d
    k = _k33(ma, mb, ia, ib, ra, rb)
    k11, k12, k13, k22, k23, _ = k
    cdot1 = vb + cross_sv2(wb, rb) - va - cross_sv2(wa, ra)
    cdot2 = wb - wa
    # point-only (2x2) solution
    px, py = _solve22(k11, k12, k22, -cdot1.x, -cdot1.y)
    if joint.enable_limit:
        ix, iy, iz = _solve33(k, (-cdot1.x, -cdot1.y, -cdot2))
        new_z = impulse[2] + iz
        pull = jnp.where(state == AT_LOWER, new_z < 0.0, jnp.where(state == AT_UPPER, new_z > 0.0, False))
        # limit would pull: drop it and re-solve the point rows with the limit impulse removed
        rx, ry = _solve22(k11, k12, k22, -cdot1.x + impulse[2] * k13, -cdot1.y + impulse[2] * k23)
        bx = jnp.where(pull, rx, ix)
        by = jnp.where(pull, ry, iy)
        bz = jnp.where(pull, -impulse[2], iz)
        active = state != INACTIVE
        dx = jnp.where(active, bx, px)
        dy = jnp.where(active, by, py)
        dz = jnp.where(active, bz, 0.0)
    else:
        dx, dy, dz = px, py, 0.0
    impulse = (impulse[0] + dx, impulse[1] + dy, impulse[2] + dz)
    p = V2(dx, dy)
    va = va - ma * p
    wa = wa - ia * (ra.cross(p) + dz)
    vb = vb + mb * p
    wb = wb + ib * (rb.cross(p) + dz)
    return impulse, motor_impulse, va, wa, vb, wb


def solve_position(joint, m, lc_a, lc_b, state, ca, aa, cb, ab, cfg):
    """One NGS pass; returns new poses and whether this joint is within tolerance.

    Component form: ``lc_a, lc_b`` (float32 constants), ``ca, cb`` are ``V2``; ``state`` a float.
    """
    ma, mb, ia, ib = m
    angular_error = jnp.zeros((), jnp.float32)
    if joint.enable_limit:
        motor_mass = 1.0 / (ia + ib) if ia + ib > 0 else 0.0
        angle = ab - aa - joint.reference_angle
        c_eq = jnp.clip(angle - joint.lower, -cfg.max_angular_correction, cfg.max_angular_correction)
        c_lo = jnp.clip(angle - joint.lower + cfg.angular_slop, -cfg.max_angular_correction, 0.0)
        c_up = jnp.clip(angle - joint.upper - cfg.angular_slop, 0.0, cfg.max_angular_correction)
        c = jnp.where(state == EQUAL, c_eq, jnp.where(state == AT_LOWER, c_lo, jnp.where(state == AT_UPPER, c_up, 0.0)))
        angular_error = jnp.where(
            state == EQUAL, jnp.abs(c_eq),
            jnp.where(state == AT_LOWER, joint.lower - angle, jnp.where(state == AT_UPPER, angle - joint.upper, 0.0)),
        )
        limit_impulse = -motor_mass * c
        aa = aa - ia * limit_impulse
        ab = ab + ib * limit_impulse
    f32 = np.float32
    ra = rotate2(aa, V2(f32(joint.local_anchor_a[0]) - lc_a.x, f32(joint.local_anchor_a[1]) - lc_a.y))
    rb = rotate2(ab, V2(f32(joint.local_anchor_b[0]) - lc_b.x, f32(joint.local_anchor_b[1]) - lc_b.y))
    c = cb + rb - ca - ra
    position_error = jnp.sqrt(c.x ** 2 + c.y ** 2)
    k11 = ma + mb + ia * ra.y ** 2 + ib * rb.y ** 2
    k12 = -ia * ra.x * ra.y - ib * rb.x * rb.y
    k22 = ma + mb + ia * ra.x ** 2 + ib * rb.x ** 2
    ix, iy = _solve22(k11, k12, k22, -c.x, -c.y)
    imp = V2(ix, iy)
    ca = ca - ma * imp
    aa = aa - ia * ra.cross(imp)
    cb = cb + mb * imp
    ab = ab + ib * rb.cross(imp)
    ok = (position_error <= cfg.linear_slop) & (angular_error <= cfg.angular_slop)
    return ca, aa, cb, ab, ok
