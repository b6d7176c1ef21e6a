"""One world step (Box2D 2.3 island solver, sequential impulses), plus impulse helpers.

Order inside ``step`` (as b2World::Step / b2Island::Solve):
  1. collide at the start pose: polygon vertices vs the ground polyline -> touching slots
  2. integrate velocities (gravity, forces, torques; semi-implicit Euler, no damping)
  3. warm start contacts (impulses kept for slots touching on both steps) and joints
  4. ``velocity_iterations`` Gauss-Seidel passes: joints, then contacts (friction, then normal)
  5. integrate positions (translation / rotation per step clamped like Box2D)
  6. ``position_iterations`` NGS passes (contacts, then joints), frozen once within tolerance
  7. sleep timers; the island (all bodies, linked by joints) sleeps when every timer >= 0.5 s and
     positions were solved.
All bodies are treated as one island (true for jointed mechanisms such as the lander; see
docs/lander.md). Sensor polygons are detected in 1 but never solved.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from envs.physics2d import fused
from envs.physics2d import joint as jnt
from envs.physics2d.collision import polyline_points_in_polygon, vertex_segment_touching, vertex_vs_polyline
from envs.physics2d.model import BodyState, Model, WorldState
from envs.physics2d.vec import V2, cross, cross_sv, cross_sv2, dot, rotate, rotate2


def slot_points(model: Model, bodies: BodyState):
    """World positions (V, 2) of every contact slot (polygon vertex) and their arms from the COM."""
    b = list(model.slot_body)
    lc = jnp.asarray(model.local_com, jnp.float32)
    local = jnp.asarray(model.slot_vertex, jnp.float32) - jnp.stack([lc[i] for i in b])
    angle = jnp.stack([bodies.angle[i] for i in b])
    com = jnp.stack([bodies.com[i] for i in b])
    arm = rotate(angle, local)
    return com + arm, arm


def collide(model: Model, bodies: BodyState, ground):
    """Touching slots (V,) and touching polygons (num_polygons,), plus contact frames."""
    cfg = model.config
    points, arm = slot_points(model, bodies)
    sep, normal, _, inside = vertex_vs_polyline(points, ground)
    touching = inside & (sep <= cfg.contact_radius)
    poly_touch = []
    for k, poly in enumerate(model.polygons):
        idx = [i for i, p in enumerate(model.slot_polygon) if p == k]
        t = jnp.any(jnp.stack([touching[i] for i in idx]))
        if poly.sensor:  # also terrain points inside the polygon (peaks touching a face)
            t = t | polyline_points_in_polygon(ground, jnp.stack([points[i] for i in idx]), cfg.contact_radius)
        poly_touch.append(t)
    return touching, jnp.stack(poly_touch), normal, sep, arm


def apply_impulse(model: Model, bodies: BodyState, body: int, impulse, point) -> BodyState:
    """Box2D ApplyLinearImpulse: instant change of COM velocity and spin (point in world frame)."""
    impulse = jnp.asarray(impulse, jnp.float32)
    r = jnp.asarray(point, jnp.float32) - bodies.com[body]
    vel = bodies.vel.at[body].add(model.inv_mass[body] * impulse)
    omega = bodies.omega.at[body].add(model.inv_inertia[body] * cross(r, impulse))
    return bodies.replace(vel=vel, omega=omega)


def step(model: Model, world: WorldState, ground, gravity, force=None, torque=None, projector=None,
         position_iterations=None, free_flight: bool = False, motor_speed=None, max_motor_torque=None):
    """Advance ``world`` by one time step. Returns (new world, info).

    ``projector``: optional constant (3B, 3B) matrix from ``locked_velocity_projector``; when given,
    the velocity phase is that exact projection (joints locked, contacts ignored) instead of the
    Gauss-Seidel passes, and no impulses are stored. ``position_iterations`` overrides the config.

    ``ground``: (P, 2) polyline with increasing x. ``gravity``: (2,) or scalar y-gravity.
    ``force`` (B, 2) at the centres of mass and ``torque`` (B,), applied during this step only.
    ``free_flight`` (static): the caller guarantees that no polygon can reach the ground during
    this step (e.g. a body created high above it). Collision and time of impact are then skipped and
    reported as no contact: the same values as the full step (up to the sign of zero in unused
    contact frames) at a fraction of its work. The lander's reset step (``projector`` given) is
    checked bitwise in tests/test_physics2d.py.
    ``motor_speed``, ``max_motor_torque``: optional (J,) per-joint motor targets for this step (what
    Box2D's SetMotorSpeed / SetMaxMotorTorque set before ``b2World::Step``; a batch of worlds can
    give each its own); None keeps every joint's static ``RevoluteJoint`` values. Entries of joints
    without a motor are ignored.
    info: ``touching`` (V,) slots and ``polygon_touching`` (num_polygons,) at the start pose or
    by a time of impact during the step, ``pair_touching`` (num_polygons, S) per ground segment,
    ``position_solved`` (), ``asleep`` ().
    """
    cfg = model.config
    dt = cfg.dt
    nb = model.num_bodies
    n_pos = cfg.position_iterations if position_iterations is None else int(position_iterations)
    gravity = jnp.asarray(gravity, jnp.float32)
    if gravity.ndim == 0:
        gravity = jnp.stack([jnp.zeros_like(gravity), gravity])
    force = jnp.zeros((nb, 2), jnp.float32) if force is None else jnp.asarray(force, jnp.float32)
    torque = jnp.zeros((nb,), jnp.float32) if torque is None else jnp.asarray(torque, jnp.float32)
    inv_m = [float(x) for x in model.inv_mass]
    inv_i = [float(x) for x in model.inv_inertia]
    lc = jnp.asarray(model.local_com, jnp.float32)
    b = world.bodies

    # 1. collide at the start pose
    if free_flight:
        _, arm = slot_points(model, b)
        touching = jnp.zeros((model.num_slots,), bool)
        poly_touch = jnp.zeros((len(model.polygons),), bool)
        normal = jnp.zeros((model.num_slots, 2), jnp.float32)
    else:
        touching, poly_touch, normal, _, arm = collide(model, b, ground)
    solid = jnp.asarray([(not s) and projector is None for s in model.slot_sensor])
    active = touching & solid
    keep = active & world.touching & cfg.warm_start
    lam_n = jnp.where(keep, world.normal_impulse, 0.0)
    lam_t = jnp.where(keep, world.tangent_impulse, 0.0)

    # 2. integrate velocities
    vel = [b.vel[i] + dt * (gravity + inv_m[i] * force[i]) for i in range(nb)]
    omg = [b.omega[i] + dt * inv_i[i] * torque[i] for i in range(nb)]

    # 3. contact constraint frames and warm start
    slots = [k for k in range(model.num_slots) if not model.slot_sensor[k] and projector is None]
    tangent = jnp.stack([normal[:, 1], -normal[:, 0]], -1)
    rn = cross(arm, normal)
    rt = cross(arm, tangent)
    sb = model.slot_body
    mslot = jnp.asarray([inv_m[sb[k]] for k in range(model.num_slots)], jnp.float32)
    islot = jnp.asarray([inv_i[sb[k]] for k in range(model.num_slots)], jnp.float32)
    normal_mass = 1.0 / (mslot + islot * rn**2)
    tangent_mass = 1.0 / (mslot + islot * rt**2)
    mu = jnp.asarray(model.slot_friction, jnp.float32)
    for k in slots:
        p = lam_n[k] * normal[k] + lam_t[k] * tangent[k]
        i = sb[k]
        vel[i] = vel[i] + inv_m[i] * p
        omg[i] = omg[i] + inv_i[i] * cross(arm[k], p)

    # joints: arms, limit states, warm start
    jprep = []
    jimp, jmot, jstate = [], [], []
    for j, J in enumerate(model.joints):
        m = _masses(model, J)
        ra, rb, st, imp = jnt.prepare(J, lc[J.body_a], lc[J.body_b], b.angle[J.body_a], b.angle[J.body_b],
                                      world.limit_state[j], world.joint_impulse[j], cfg)
        mot = world.motor_impulse[j] if (J.enable_motor and cfg.warm_start) else jnp.zeros((), jnp.float32)
        if not cfg.warm_start:
            imp = jnp.zeros_like(imp)
        va, wa, vb, wb = jnt.warm_start(J, m, ra, rb, imp, mot, vel[J.body_a], omg[J.body_a], vel[J.body_b], omg[J.body_b])
        vel[J.body_a], omg[J.body_a], vel[J.body_b], omg[J.body_b] = va, wa, vb, wb
        jprep.append((ra, rb))
        jimp.append(imp)
        jmot.append(mot)
        jstate.append(st)

    # 4. velocity iterations (component form: per-world scalars, so the loop can run fused)
    f32 = jnp.float32
    vconsts = dict(
        on=tuple(active[k].astype(f32) for k in slots),
        arm=tuple(V2.of(arm[k]) for k in slots), n=tuple(V2.of(normal[k]) for k in slots),
        t=tuple(V2.of(tangent[k]) for k in slots),
        nm=tuple(normal_mass[k] for k in slots), tm=tuple(tangent_mass[k] for k in slots),
        ra=tuple(V2.of(p[0]) for p in jprep), rb=tuple(V2.of(p[1]) for p in jprep),
        state=tuple(s.astype(f32) for s in jstate),
    )
    if motor_speed is not None:
        ms = jnp.asarray(motor_speed, f32)
        vconsts["motor_speed"] = tuple(ms[j] for j in range(len(model.joints)))
    if max_motor_torque is not None:
        mt = jnp.asarray(max_motor_torque, f32)
        vconsts["max_motor_torque"] = tuple(mt[j] for j in range(len(model.joints)))
    carry = (tuple(V2.of(v) for v in vel), tuple(omg), tuple((i[0], i[1], i[2]) for i in jimp), tuple(jmot),
             tuple(lam_n[k] for k in slots), tuple(lam_t[k] for k in slots))
    if projector is None:
        vel, omg, jimp, jmot, ln, lt = fused.per_world_fori_loop(
            cfg.velocity_iterations, functools.partial(_velocity_pass, model, slots), vconsts, carry,
            mode=cfg.kernel, unroll=cfg.unroll)
        vel, omg = [v.array() for v in vel], list(omg)
        jimp = [jnp.stack(list(i)) for i in jimp]
    else:  # exact locked-joint solve from the integrated (not warm-started) velocities
        v = jnp.concatenate([jnp.concatenate([b.vel[i] + dt * (gravity + inv_m[i] * force[i]),
                                              (b.omega[i] + dt * inv_i[i] * torque[i])[None]]) for i in range(nb)])
        v = jnp.dot(jnp.asarray(projector, jnp.float32), v, precision=jax.lax.Precision.HIGHEST)  # no TF32
        vel = [v[3 * i: 3 * i + 2] for i in range(nb)]
        omg = [v[3 * i + 2] for i in range(nb)]
        jimp = [jnp.zeros_like(x) for x in jimp]
        jmot = [jnp.zeros_like(x) for x in jmot]
        ln, lt = carry[4], carry[5]

    # 5. integrate positions (Box2D clamps the motion per step)
    com, ang = [], []
    for i in range(nb):
        tr = dt * vel[i]
        tr2 = dot(tr, tr)
        vel[i] = jnp.where(tr2 > cfg.max_translation**2, vel[i] * (cfg.max_translation / jnp.sqrt(tr2)), vel[i])
        rot = dt * omg[i]
        omg[i] = jnp.where(rot * rot > cfg.max_rotation**2, omg[i] * (cfg.max_rotation / jnp.abs(rot)), omg[i])
        com.append(b.com[i] + dt * vel[i])
        ang.append(b.angle[i] + dt * omg[i])

    # 6. position iterations (non-linear Gauss-Seidel); stop changing once solved
    local_v = jnp.asarray(model.slot_vertex, jnp.float32)
    plane_n = normal
    # plane point: start of the ground segment under the vertex at the start pose (fixed for the step)
    if free_flight:
        plane_q, inside = jnp.zeros((model.num_slots, 2), jnp.float32), jnp.zeros((model.num_slots,), bool)
    else:
        _, _, plane_q, inside = vertex_vs_polyline(slot_points(model, b)[0], ground)

    pconsts = dict(on=tuple(active[k].astype(f32) for k in slots), q=tuple(V2.of(plane_q[k]) for k in slots),
                   n=tuple(V2.of(plane_n[k]) for k in slots), state=tuple(s.astype(f32) for s in jstate))
    if n_pos > 0:
        com, ang, solved = fused.per_world_fori_loop(
            n_pos, functools.partial(_position_pass, model, slots),
            pconsts, (tuple(V2.of(c) for c in com), tuple(ang), jnp.zeros((), f32)),
            mode=cfg.kernel, unroll=cfg.unroll)
        com, ang, solved = [c.array() for c in com], list(ang), solved > 0.5
    else:
        solved = jnp.zeros((), bool)

    # 7. continuous collision (Box2D SolveTOI, simplified): a body whose slot crosses the TOI target
    #    separation during the step is moved back to the time of impact, its contacts there are
    #    solved alone (joints are not part of Box2D's TOI islands), and it moves on for the rest of
    #    the step. A touch found this way also counts as touching for this step (BeginContact fires).
    start_pts, _ = slot_points(model, b)
    end_bodies = BodyState(com=jnp.stack(com), angle=jnp.stack(ang), vel=jnp.stack(vel), omega=jnp.stack(omg))
    end_pts, _ = slot_points(model, end_bodies)
    target = max(cfg.linear_slop, cfg.contact_radius - 3.0 * cfg.linear_slop)
    d0 = dot(start_pts - plane_q, plane_n)
    d1 = dot(end_pts - plane_q, plane_n)
    if free_flight:
        crossing = jnp.zeros((model.num_slots,), bool)
    else:
        _, _, _, inside_end = vertex_vs_polyline(end_pts, ground)
        crossing = inside & inside_end & (d0 > target) & (d1 < target)
        if cfg.toi_from_touching:  # b2TimeOfImpact: already within target + tolerance -> touching at t = 0
            early = inside & (d0 > 0.0) & (d0 < target + 0.25 * cfg.linear_slop)
            crossing = crossing | early
    toi_touch = crossing
    if cfg.continuous and not free_flight:
        alpha_slot = jnp.clip((d0 - target) / jnp.maximum(d0 - d1, 1e-9), 0.0, 1.0)
        if cfg.toi_from_touching:
            alpha_slot = jnp.where(early, 0.0, alpha_slot)
        com, ang, vel, omg = list(com), list(ang), list(vel), list(omg)
        for i in range(nb):
            ks = [k for k in slots if sb[k] == i]
            if not ks:
                continue
            hit = jnp.any(jnp.stack([crossing[k] for k in ks]))
            alpha = jnp.min(jnp.stack([jnp.where(crossing[k], alpha_slot[k], 1.0) for k in ks]))
            c_t = b.com[i] + alpha * (com[i] - b.com[i])
            a_t = b.angle[i] + alpha * (ang[i] - b.angle[i])
            v_t, w_t = vel[i], omg[i]
            arms = [rotate(a_t, local_v[k] - lc[i]) for k in ks]
            on = [hit & (dot(c_t + r - plane_q[k], plane_n[k]) <= cfg.contact_radius) for r, k in zip(arms, ks)]
            if cfg.toi_position_iterations > 0:
                def toi_position(_, carry, i=i, ks=ks, on=on):
                    c_, a_, done = carry
                    c0, a0 = c_, a_
                    min_sep = jnp.zeros((), jnp.float32)
                    for s, k in enumerate(ks):
                        r = rotate(a_, local_v[k] - lc[i])
                        sep = dot(c_ + r - plane_q[k], plane_n[k]) - cfg.contact_radius
                        min_sep = jnp.where(on[s], jnp.minimum(min_sep, sep), min_sep)
                        corr = jnp.clip(cfg.toi_baumgarte * (sep + cfg.linear_slop), -cfg.max_linear_correction, 0.0)
                        rn_ = cross(r, plane_n[k])
                        kk = inv_m[i] + inv_i[i] * rn_ * rn_
                        p = jnp.where(on[s] & (kk > 0), -corr / kk, 0.0) * plane_n[k]
                        c_ = c_ + inv_m[i] * p
                        a_ = a_ + inv_i[i] * cross(r, p)
                    c_ = jnp.where(done, c0, c_)
                    a_ = jnp.where(done, a0, a_)
                    return c_, a_, done | (min_sep >= -1.5 * cfg.linear_slop)

                c_t, a_t, _ = jax.lax.fori_loop(0, cfg.toi_position_iterations, toi_position,
                                                (c_t, a_t, jnp.zeros((), bool)))
                arms = [rotate(a_t, local_v[k] - lc[i]) for k in ks]
            lnn = [jnp.zeros((), jnp.float32) for _ in ks]
            ltt = [jnp.zeros((), jnp.float32) for _ in ks]

            def toi_pass(v_t, w_t, lnn, ltt, i=i, ks=ks, arms=arms, on=on):
                lnn, ltt = list(lnn), list(ltt)
                for s, (r, k) in enumerate(zip(arms, ks)):
                    n, t = plane_n[k], jnp.stack([plane_n[k][1], -plane_n[k][0]])
                    rn_, rt_ = cross(r, n), cross(r, t)
                    dv = v_t + cross_sv(w_t, r)
                    new_t = jnp.clip(ltt[s] - dot(dv, t) / (inv_m[i] + inv_i[i] * rt_ * rt_), -mu[k] * lnn[s], mu[k] * lnn[s])
                    new_t = jnp.where(on[s], new_t, 0.0)
                    pt = (new_t - ltt[s]) * t
                    ltt[s] = new_t
                    v_t, w_t = v_t + inv_m[i] * pt, w_t + inv_i[i] * cross(r, pt)
                    dv = v_t + cross_sv(w_t, r)
                    new_n = jnp.maximum(lnn[s] - dot(dv, n) / (inv_m[i] + inv_i[i] * rn_ * rn_), 0.0)
                    new_n = jnp.where(on[s], new_n, 0.0)
                    pn = (new_n - lnn[s]) * n
                    lnn[s] = new_n
                    v_t, w_t = v_t + inv_m[i] * pn, w_t + inv_i[i] * cross(r, pn)
                return v_t, w_t, tuple(lnn), tuple(ltt)

            if cfg.toi_loop:  # one traced pass in a loop: a smaller program, much less compile time
                v_t, w_t, _, _ = jax.lax.fori_loop(0, cfg.toi_iterations, lambda _, c: toi_pass(*c),
                                                   (v_t, w_t, tuple(lnn), tuple(ltt)))
            else:
                for _ in range(cfg.toi_iterations):
                    v_t, w_t, lnn, ltt = toi_pass(v_t, w_t, lnn, ltt)
            rest = (1.0 - alpha) * dt
            com[i] = jnp.where(hit, c_t + rest * v_t, com[i])
            ang[i] = jnp.where(hit, a_t + rest * w_t, ang[i])
            vel[i] = jnp.where(hit, v_t, vel[i])
            omg[i] = jnp.where(hit, w_t, omg[i])

    # 8. sleep
    vel_a = jnp.stack(vel)
    omg_a = jnp.stack(omg)
    moving = (omg_a**2 > cfg.angular_sleep_tolerance**2) | (dot(vel_a, vel_a) > cfg.linear_sleep_tolerance**2)
    sleep_time = jnp.where(moving, 0.0, world.sleep_time + dt)
    asleep = (jnp.min(sleep_time) >= cfg.time_to_sleep) & solved

    zero = jnp.zeros((), jnp.float32)
    pos_of = {k: s for s, k in enumerate(slots)}
    ln_full = jnp.stack([ln[pos_of[k]] if k in pos_of else zero for k in range(model.num_slots)])
    lt_full = jnp.stack([lt[pos_of[k]] if k in pos_of else zero for k in range(model.num_slots)])
    new_world = WorldState(
        bodies=BodyState(com=jnp.stack(com), angle=jnp.stack(ang), vel=vel_a, omega=omg_a),
        sleep_time=sleep_time,
        normal_impulse=ln_full,
        tangent_impulse=lt_full,
        joint_impulse=jnp.stack(jimp) if jimp else world.joint_impulse,
        motor_impulse=jnp.stack(jmot) if jmot else world.motor_impulse,
        limit_state=jnp.stack(jstate) if jstate else world.limit_state,
        touching=active,
        asleep=asleep,
    )
    # per (polygon, ground segment) touching: start pose, plus segments hit by a time of impact
    if free_flight:
        pairs_v = jnp.zeros((model.num_slots, ground.shape[0] - 1), bool)
    else:
        seg_sel = (plane_q[:, None, 0] == ground[None, :-1, 0]) & inside[:, None]  # (V, S) segment used
        pairs_v = vertex_segment_touching(start_pts, ground, cfg.contact_radius) | (seg_sel & toi_touch[:, None])
    pairs = jnp.stack([jnp.any(jnp.stack([pairs_v[i] for i, p in enumerate(model.slot_polygon) if p == k]), 0)
                       for k in range(len(model.polygons))])
    began = []
    for k, poly in enumerate(model.polygons):
        idx = [i for i, p in enumerate(model.slot_polygon) if p == k]
        began.append(jnp.any(jnp.stack([toi_touch[i] for i in idx])))
    poly_touch = poly_touch | jnp.stack(began)
    info = dict(touching=touching | toi_touch, polygon_touching=poly_touch, pair_touching=pairs,
                position_solved=solved, asleep=asleep)
    return new_world, info


def _masses(model: Model, joint):
    inv_m, inv_i = model.inv_mass, model.inv_inertia
    return (float(inv_m[joint.body_a]), float(inv_m[joint.body_b]),
            float(inv_i[joint.body_a]), float(inv_i[joint.body_b]))


def _velocity_pass(model: Model, slots, c, carry):
    """One Gauss-Seidel velocity pass (joints, then each contact slot: friction, then normal).

    Per-world scalars only (``V2`` for vectors), as ``fused.per_world_fori_loop`` requires.
    """
    dt = model.config.dt
    inv_m, inv_i = [float(x) for x in model.inv_mass], [float(x) for x in model.inv_inertia]
    sb = model.slot_body
    vel, omg, jimp, jmot, ln, lt = (list(x) for x in carry)
    for j, J in enumerate(model.joints):
        a_, b_ = J.body_a, J.body_b
        speed = c["motor_speed"][j] if "motor_speed" in c else None
        torque = c["max_motor_torque"][j] if "max_motor_torque" in c else None
        jimp[j], jmot[j], vel[a_], omg[a_], vel[b_], omg[b_] = jnt.solve_velocity(
            J, _masses(model, J), c["ra"][j], c["rb"][j], c["state"][j], jimp[j], jmot[j],
            vel[a_], omg[a_], vel[b_], omg[b_], dt, speed, torque)
    for s, k in enumerate(slots):
        i = sb[k]
        on, arm, normal, tangent = c["on"][s], c["arm"][s], c["n"][s], c["t"][s]
        # friction first (Box2D order), bounded by the current normal impulse
        dv = vel[i] + cross_sv2(omg[i], arm)
        vt = dv.dot(tangent)
        max_f = np.float32(model.slot_friction[k]) * ln[s]
        new_t = jnp.clip(lt[s] - c["tm"][s] * vt, -max_f, max_f) * on
        p = (new_t - lt[s]) * tangent
        lt[s] = new_t
        vel[i] = vel[i] + inv_m[i] * p
        omg[i] = omg[i] + inv_i[i] * arm.cross(p)
        dv = vel[i] + cross_sv2(omg[i], arm)
        vn = dv.dot(normal)
        new_n = jnp.maximum(ln[s] - c["nm"][s] * vn, 0.0) * on
        p = (new_n - ln[s]) * normal
        ln[s] = new_n
        vel[i] = vel[i] + inv_m[i] * p
        omg[i] = omg[i] + inv_i[i] * arm.cross(p)
    return tuple(vel), tuple(omg), tuple(jimp), tuple(jmot), tuple(ln), tuple(lt)


def _position_pass(model: Model, slots, c, carry):
    """One non-linear Gauss-Seidel position pass (contacts, then joints); frozen once solved.

    ``carry = (com, angle, solved)`` with ``solved`` a 0/1 float (per-world scalars only).
    """
    cfg = model.config
    inv_m, inv_i = [float(x) for x in model.inv_mass], [float(x) for x in model.inv_inertia]
    sb = model.slot_body
    lc = np.asarray(model.local_com, np.float32)
    local_v = np.asarray(model.slot_vertex, np.float32)
    com0, ang0, solved = carry
    com, ang = list(com0), list(ang0)
    min_sep = jnp.zeros((), jnp.float32)
    for s, k in enumerate(slots):
        i = sb[k]
        on, normal = c["on"][s] > 0.5, c["n"][s]
        arm_k = rotate2(ang[i], V2(*(local_v[k] - lc[i])))
        sep = (com[i] + arm_k - c["q"][s]).dot(normal) - cfg.contact_radius
        min_sep = jnp.where(on, jnp.minimum(min_sep, sep), min_sep)
        corr = jnp.clip(cfg.baumgarte * (sep + cfg.linear_slop), -cfg.max_linear_correction, 0.0)
        rnk = arm_k.cross(normal)
        kk = inv_m[i] + inv_i[i] * rnk * rnk
        imp = jnp.where(on & (kk > 0), -corr / kk, 0.0)
        p = imp * normal
        com[i] = com[i] + inv_m[i] * p
        ang[i] = ang[i] + inv_i[i] * arm_k.cross(p)
    ok = min_sep >= -3.0 * cfg.linear_slop
    for j, J in enumerate(model.joints):
        a_, b_ = J.body_a, J.body_b
        com[a_], ang[a_], com[b_], ang[b_], jok = jnt.solve_position(
            J, _masses(model, J), V2(*lc[a_]), V2(*lc[b_]), c["state"][j], com[a_], ang[a_], com[b_], ang[b_], cfg)
        ok = ok & jok
    done = solved > 0.5
    com = tuple(c0.where(done, c1) for c0, c1 in zip(com0, com))
    ang = tuple(jnp.where(done, a0, a1) for a0, a1 in zip(ang0, ang))
    return com, ang, jnp.where(done | ok, 1.0, 0.0).astype(jnp.float32)
