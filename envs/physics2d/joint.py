"""Revolute joint with motor and angle limits, solved as in Box2D 2.3 (b2RevoluteJoint).

Velocity phase: motor row (clamped to dt * max torque), then either the 3x3 block (point + limit,
with the limit impulse clamped to one sign and the point rows re-solved when it would pull) or the
2x2 point block. Position phase: non-linear Gauss-Seidel on the limit angle and the anchor gap.
Every branch is computed and selected with ``jnp.where`` so it vectorises over a batch of worlds.

All functions act on one joint; ``va, wa, vb, wb`` are the two bodies' velocities (2,) and ().
"""
from __future__ import annotations

import jax.numpy as jnp

from envs.physics2d.vec import cross, cross_sv, rotate

INACTIVE, AT_LOWER, AT_UPPER, EQUAL = 0, 1, 2, 3


def _k33(ma, mb, ia, ib, ra, rb):
    k11 = ma + mb + ra[1] ** 2 * ia + rb[1] ** 2 * ib
    k12 = -ra[1] * ra[0] * ia - rb[1] * rb[0] * ib
    k13 = -ra[1] * ia - rb[1] * ib
    k22 = ma + mb + ra[0] ** 2 * ia + rb[0] ** 2 * ib
    k23 = ra[0] * ia + rb[0] * ib
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


def solve_velocity(joint, m, ra, rb, state, impulse, motor_impulse, va, wa, vb, wb, dt):
    """One Gauss-Seidel pass over the joint's rows; returns new impulses and velocities."""
    ma, mb, ia, ib = m
    if joint.enable_motor:
        motor_mass = 1.0 / (ia + ib) if ia + ib > 0 else 0.0
        cdot = wb - wa - joint.motor_speed
        max_imp = dt * joint.max_motor_torque
        new = jnp.clip(motor_impulse - motor_mass * cdot, -max_imp, max_imp)
        new = jnp.where(state == EQUAL, motor_impulse, new)
        d = new - motor_impulse
        motor_impulse = new
        wa = wa - ia * d
        wb = wb + ib * d
    k = _k33(ma, mb, ia, ib, ra, rb)
    k11, k12, k13, k22, k23, _ = k
    cdot1 = vb + cross_sv(wb, rb) - va - cross_sv(wa, ra)
    cdot2 = wb - wa
    # point-only (2x2) solution
    px, py = _solve22(k11, k12, k22, -cdot1[0], -cdot1[1])
    if joint.enable_limit:
        ix, iy, iz = _solve33(k, (-cdot1[0], -cdot1[1], -cdot2))
        new_z = impulse[2] + iz
        pull = jnp.where(state == AT_LOWER, new_z < 0.0, jnp.where(state == AT_UPPER, new_z > 0.0, False))
        # limit would pull: drop it and re-solve the point rows with the limit impulse removed
        rx, ry = _solve22(k11, k12, k22, -cdot1[0] + impulse[2] * k13, -cdot1[1] + impulse[2] * k23)
        bx = jnp.where(pull, rx, ix)
        by = jnp.where(pull, ry, iy)
        bz = jnp.where(pull, -impulse[2], iz)
        active = state != INACTIVE
        dx = jnp.where(active, bx, px)
        dy = jnp.where(active, by, py)
        dz = jnp.where(active, bz, 0.0)
    else:
        dx, dy, dz = px, py, 0.0
    impulse = impulse + jnp.stack([dx, dy, jnp.asarray(dz, impulse.dtype)])
    p = jnp.stack([dx, dy])
    va = va - ma * p
    wa = wa - ia * (cross(ra, p) + dz)
    vb = vb + mb * p
    wb = wb + ib * (cross(rb, p) + dz)
    return impulse, motor_impulse, va, wa, vb, wb


def solve_position(joint, m, lc_a, lc_b, state, ca, aa, cb, ab, cfg):
    """One NGS pass; returns new poses and whether this joint is within tolerance."""
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
    ra = rotate(aa, jnp.asarray(joint.local_anchor_a, jnp.float32) - lc_a)
    rb = rotate(ab, jnp.asarray(joint.local_anchor_b, jnp.float32) - lc_b)
    c = cb + rb - ca - ra
    position_error = jnp.sqrt(c[0] ** 2 + c[1] ** 2)
    k11 = ma + mb + ia * ra[1] ** 2 + ib * rb[1] ** 2
    k12 = -ia * ra[0] * ra[1] - ib * rb[0] * rb[1]
    k22 = ma + mb + ia * ra[0] ** 2 + ib * rb[0] ** 2
    ix, iy = _solve22(k11, k12, k22, -c[0], -c[1])
    imp = jnp.stack([ix, iy])
    ca = ca - ma * imp
    aa = aa - ia * cross(ra, imp)
    cb = cb + mb * imp
    ab = ab + ib * cross(rb, imp)
    ok = (position_error <= cfg.linear_slop) & (angular_error <= cfg.angular_slop)
    return ca, aa, cb, ab, ok
