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
from envs.physics2d import edge as edg
from envs.physics2d import polygon as pg
from envs.physics2d import toi
from envs.physics2d.collision import polyline_points_in_polygon, vertex_segment_touching, vertex_vs_polyline
from envs.physics2d.mass import polygon_mass
from envs.physics2d.model import BodyState, Model, WorldState
from envs.physics2d.vec import V2, cross, cross_sv2, dot, rotate, rotate2, rotate_cs, sincos


def slot_points(model: Model, bodies: BodyState):
    """World positions (V, 2) of every contact slot (polygon vertex) and their arms from the COM."""
    b = np.asarray(model.slot_body, np.int32)
    local = jnp.asarray(np.asarray(model.slot_vertex, np.float32) - np.asarray(model.local_com, np.float32)[b])
    angle = bodies.angle[b]
    com = bodies.com[b]
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


BOX_KEY = -1_000_000  # warm-start keys of box obstacles: BOX_KEY - round(1000 x0), apart from the edges'


def fixture_keys(x0, box: bool = False):
    """The warm-start keys of static fixtures whose left ends are at ``x0`` (float32): round(1000 x0) for
    an edge, BOX_KEY - round(1000 x0) for a box obstacle (int32, ``x0``'s shape)."""
    keys = jnp.round(jnp.asarray(x0, jnp.float32) * 1000.0).astype(jnp.int32)
    return BOX_KEY - keys if box else keys


def edge_constraints(model: Model, bodies: BodyState, edges, valid, boxes=None, box_valid=None):
    """Box2D's manifolds of every solid polygon against every ground edge (edge-vs-polygon) and every
    box obstacle (polygon-vs-polygon), the first ``config.edge_contacts`` touching ones per polygon
    (edges first, left to right, then boxes in their order) kept as contact points.

    ``edges`` (S, 2, 2) world segments (each a separate Box2D edge), ``valid`` (S,) bool; ``boxes``
    (K, 4) static axis-aligned boxes (x0, x1, y0, y1), ``box_valid`` (K,) bool, or None. Returns a
    dict of (E,) leaves, E = ``model.num_contacts`` (polygon-major, then manifold, then point): ``on``,
    ``body`` (static tuple), ``normal`` and ``point`` (Box2D's velocity-constraint frame, world),
    ``face_b``, ``ref_normal``, ``ref_point``, ``clip`` (the manifold, world), ``key`` (E, 2) int32;
    plus ``pairs`` (num_polygons, S) bool: polygon k's manifold with edge s has points, and
    ``box_pairs`` (num_polygons, K) the same per box.

    Polygons with the same vertex count are one vmapped computation (the walker's four leg boxes: one
    set of GPU kernels and a quarter of the program instead of one copy per leg).
    """
    cfg = model.config
    k_edges = cfg.edge_contacts
    lc = np.asarray(model.local_com, np.float64)
    n_box = 0 if boxes is None else boxes.shape[0]
    keys = fixture_keys(edges[:, 0, 0])
    if n_box:
        keys = jnp.concatenate([keys, fixture_keys(boxes[:, 0], box=True)])

    def manifolds(verts, normals, centroid):  # one polygon against every edge and box
        m = edg.polygon_edges_manifolds(edges, valid, verts, normals, centroid, cfg.contact_radius)
        pairs, box_pairs = m["on"][:, 0], jnp.zeros((0,), bool)
        if n_box:
            mb = pg.polygon_obstacles_manifolds(boxes, box_valid, verts, normals, centroid, cfg.contact_radius)
            box_pairs = mb["on"][:, 0]
            m = {name: jnp.concatenate([m[name], mb[name]]) for name in m}
        sel = edg.select_edges(m, k_edges)  # leaves (K, 2, ...) per point or (K, ...) per manifold
        edge_key = jnp.sum(jnp.where(jnp.arange(keys.shape[0])[None] == sel["edge"][:, None], keys[None], 0), 1)
        two = lambda a: jnp.repeat(a, 2, axis=0)  # per manifold -> per point
        part = dict(on=sel["on"].reshape(-1), normal=two(sel["normal"]), point=sel["point"].reshape(-1, 2),
                    face_b=two(sel["face_b"]), ref_normal=two(sel["ref_normal"]), ref_point=two(sel["ref_point"]),
                    clip=sel["clip"].reshape(-1, 2), key=jnp.stack([two(edge_key), sel["id"].reshape(-1)], -1))
        return pairs, box_pairs, part

    order, pairs, box_pairs, parts = [], [], [], []
    for ks in _by_vertex_count(model):
        polys = [model.polygons[k] for k in ks]
        i = np.asarray([p.body for p in polys], np.int32)
        local = jnp.asarray(np.stack([np.asarray(p.vertices, np.float64) - lc[p.body] for p in polys]), jnp.float32)
        normals = jnp.asarray(np.stack([edg.polygon_normals(p.vertices) for p in polys]), jnp.float32)
        centroid = jnp.asarray(np.stack([polygon_mass(np.asarray(p.vertices, np.float64), 1.0)[1] - lc[p.body]  # Box2D's m_centroid
                                         for p in polys]), jnp.float32)
        com, angle = bodies.com[i], bodies.angle[i]
        p_g, bp_g, part_g = jax.vmap(manifolds)(com[:, None] + rotate(angle[:, None], local),
                                               rotate(angle[:, None], normals), com + rotate(angle, centroid))
        order += ks
        pairs.append(p_g)
        box_pairs.append(bp_g)
        parts.append(part_g)
    # back to polygon order: contacts follow edge_polygons, and pair rows of polygons without edge
    # contacts are False
    cat = lambda xs: jnp.concatenate(xs) if len(xs) > 1 else xs[0]  # noqa: E731
    pairs, box_pairs = cat(pairs), cat(box_pairs)  # (solid polygons, S), (solid polygons, K), in ``order``
    part = {name: cat([q[name] for q in parts]) for name in parts[0]}
    perm = [order.index(k) for k in model.edge_polygons]
    if perm != list(range(len(order))):
        part = {name: leaf[np.asarray(perm)] for name, leaf in part.items()}
    out = {name: leaf.reshape((-1,) + leaf.shape[2:]) for name, leaf in part.items()}  # (E, ...)
    if order != list(range(len(model.polygons))):
        row = {k: j for j, k in enumerate(order)}
        pairs, box_pairs = (jnp.stack([x[row[k]] if k in row else jnp.zeros(x.shape[1:], bool)
                                       for k in range(len(model.polygons))]) for x in (pairs, box_pairs))
    out["body"] = tuple(model.polygons[k].body for k in model.edge_polygons for _ in range(2 * k_edges))
    out["friction"] = tuple(float(np.sqrt(model.polygons[k].friction * cfg.ground_friction))  # Box2D mixing
                            for k in model.edge_polygons for _ in range(2 * k_edges))
    out["pairs"], out["box_pairs"] = pairs, box_pairs
    return out


def _by_vertex_count(model: Model) -> list[list[int]]:
    """The solid polygons (``model.edge_polygons``) grouped by vertex count, each group in polygon order:
    one vmapped computation per group gives fewer, larger GPU kernels than one copy per polygon."""
    groups: dict[int, list[int]] = {}
    for k in model.edge_polygons:
        groups.setdefault(len(model.polygons[k].vertices), []).append(k)
    return list(groups.values())


def apply_impulse(model: Model, bodies: BodyState, body: int, impulse, point) -> BodyState:
    """Box2D ApplyLinearImpulse: instant change of COM velocity and spin (point in world frame)."""
    impulse = jnp.asarray(impulse, jnp.float32)
    r = jnp.asarray(point, jnp.float32) - bodies.com[body]
    vel = bodies.vel.at[body].add(model.inv_mass[body] * impulse)
    omega = bodies.omega.at[body].add(model.inv_inertia[body] * cross(r, impulse))
    return bodies.replace(vel=vel, omega=omega)


def step(model: Model, world: WorldState, ground, gravity, force=None, torque=None, projector=None,
         position_iterations=None, free_flight: bool = False, motor_speed=None, max_motor_torque=None,
         edges=None, edge_valid=None, start_contacts: bool = True, boxes=None, box_valid=None):
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
    ``start_contacts=False`` (static, edge contacts): the caller guarantees that no solid polygon is
    within contact distance of the ground at the start pose (e.g. a body created above it). The edge
    manifolds are then skipped and the velocity and position passes solve the joints alone (the time of
    impact still runs): the full step's values at a fraction of its work and compile.
    ``edges`` (S, 2, 2), ``edge_valid`` (S,) bool: with ``config.edge_contacts`` the ground as separate
    Box2D edges, left to right (any number; invalid slots have no contact); None: every ground
    segment is its own edge. Solid polygons then touch the ground through Box2D's edge-vs-polygon
    manifolds (``edge_constraints``) instead of their vertices, with Box2D's time of impact against
    the same edges (``_time_of_impact_polygons``).
    ``boxes`` (K, 4) (x0, x1, y0, y1), ``box_valid`` (K,) bool: with ``config.edge_contacts``, static
    box obstacles besides the edges (Box2D's polygon-vs-polygon manifolds, ``polygon.py``), or None.
    The polyline should cover the edges and box tops for the sensor polygons, which touch it alone.
    info: ``touching`` (V,) slots and ``polygon_touching`` (num_polygons,) at the start pose or
    by a time of impact during the step, ``pair_touching`` (num_polygons, S) per ground segment
    (vertex contacts) or per edge (edge contacts: the solid polygons' manifolds, sensor rows False),
    ``box_touching`` (num_polygons, K) per box and ``toi_crowded`` () (edge contacts: some polygon had
    more shapes in reach of its sweep than ``config.toi_candidates``, the farthest then not tried),
    ``manifolds_crowded`` () (edge contacts: more manifolds had points than ``config.velocity_manifolds``
    packs, the last ones then left out of the velocity passes),
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
        with jax.named_scope("collide"):
            touching, poly_touch, normal, _, arm = collide(model, b, ground)
    solid = jnp.asarray([(not s) and projector is None for s in model.slot_sensor])
    active = touching & solid
    edge_mode = bool(cfg.edge_contacts) and projector is None
    if edge_mode:  # the fixtures: separate edges (every ground segment by default) and boxes
        edges = jnp.stack([ground[:-1], ground[1:]], 1) if edges is None else jnp.asarray(edges, jnp.float32)
        valid = jnp.ones((edges.shape[0],), bool) if edge_valid is None else jnp.asarray(edge_valid, bool)
        boxes = None if boxes is None else jnp.asarray(boxes, jnp.float32)
        box_valid = None if boxes is None else jnp.asarray(box_valid, bool)
    if edge_mode and (free_flight or not start_contacts):  # no manifold has points: the passes solve the joints alone
        ec = dict(on=jnp.zeros((model.num_contacts,), bool), key=jnp.zeros_like(world.contact_key), body=(),
                  friction=(), pairs=jnp.zeros((len(model.polygons), edges.shape[0]), bool),
                  box_pairs=jnp.zeros((len(model.polygons), 0 if boxes is None else boxes.shape[0]), bool))
        e_on = ec["on"]
    elif edge_mode:  # solver contacts: Box2D edge manifolds, warm started by (edge, feature)
        with jax.named_scope("edge_manifolds"):
            ec = edge_constraints(model, b, edges, valid, boxes, box_valid)
        e_on = ec["on"]
        keep = e_on & world.touching & jnp.all(ec["key"] == world.contact_key, -1) & cfg.warm_start
        lam_n = jnp.where(keep, world.normal_impulse, 0.0)
        lam_t = jnp.where(keep, world.tangent_impulse, 0.0)
    else:
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
    if edge_mode:
        ebody = ec["body"]  # () in free flight or without start contacts
        econ = _edge_velocity_constants(model, b, ec) if ebody else {}
        for k in range(len(ebody)):  # warm start (a second point Box2D drops is not applied)
            on_k = econ["on"][k]
            p = on_k * (lam_n[k] * econ["n"][k].array() + lam_t[k] * econ["t"][k].array())
            i = ebody[k]
            vel[i] = vel[i] + inv_m[i] * p
            omg[i] = omg[i] + inv_i[i] * cross(econ["arm"][k].array(), p)
    else:
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
    cslots = list(range(len(ebody))) if edge_mode else slots
    carry = (tuple(V2.of(v) for v in vel), tuple(omg), tuple((i[0], i[1], i[2]) for i in jimp), tuple(jmot),
             tuple(lam_n[k] for k in cslots), tuple(lam_t[k] for k in cslots))
    if edge_mode:  # the manifolds' constants replace the vertex slots' (none without manifolds)
        vconsts = {k: v for k, v in vconsts.items() if k not in ("on", "arm", "n", "t", "nm", "tm")}
        vconsts.update({k: v for k, v in econ.items() if k != "t"})  # the pass turns n into t itself
        vpass = functools.partial(_velocity_pass_edges, model, ebody, ec["friction"])
    else:
        vpass = functools.partial(_velocity_pass, model, slots)
    packed = edge_mode and projector is None and 0 < cfg.velocity_manifolds < len(ebody) // 2
    layout = lane_layout(ebody) if edge_mode and projector is None and cfg.velocity_lanes and not packed else None
    crowded = jnp.zeros((), bool)
    if packed:  # only manifolds with points enter the passes, packed into velocity_manifolds slots
        vconsts = {k: v for k, v in vconsts.items() if k not in econ}
        pc, ln_p, lt_p, idx, crowded = _pack_manifolds(model, ebody, ec["friction"], econ, lam_n, lam_t,
                                                       cfg.velocity_manifolds)
        vconsts.update(pc)
        carry = carry[:4] + (ln_p, lt_p)
        vpass = functools.partial(_velocity_pass_packed, model, tuple(sorted(set(ebody))))
    if projector is None:
        with jax.named_scope("velocity_passes"):
            if layout is not None:
                vel, omg, jimp, jmot, ln, lt = velocity_passes_in_lanes(
                    model, layout, ec["friction"], cfg.velocity_iterations, vconsts, carry, mode=cfg.kernel,
                    unroll=cfg.unroll)
            else:
                vel, omg, jimp, jmot, ln, lt = fused.per_world_fori_loop(
                    cfg.velocity_iterations, vpass, vconsts, carry, mode=cfg.kernel, unroll=cfg.unroll)
        if packed:
            ln = tuple(scalars_of(_unpack_impulses(idx, ln, len(ebody))))
            lt = tuple(scalars_of(_unpack_impulses(idx, lt, len(ebody))))
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
    plane_n = normal
    # plane point: start of the ground segment under the vertex at the start pose (fixed for the step)
    if free_flight:
        plane_q, inside = jnp.zeros((model.num_slots, 2), jnp.float32), jnp.zeros((model.num_slots,), bool)
    else:
        _, _, plane_q, inside = vertex_vs_polyline(slot_points(model, b)[0], ground)

    pconsts = dict(on=tuple(active[k].astype(f32) for k in slots), q=tuple(V2.of(plane_q[k]) for k in slots),
                   n=tuple(V2.of(plane_n[k]) for k in slots), state=tuple(s.astype(f32) for s in jstate))
    position_layout = None
    if edge_mode:
        pconsts = dict(_edge_position_constants(model, b, ec) if ebody else {}, state=pconsts["state"])
        ppass = functools.partial(_position_pass_edges, model, ebody)
        position_layout = lane_layout(ebody) if cfg.position_lanes else None
    else:
        ppass = functools.partial(_position_pass, model, slots)
    if n_pos > 0:
        pcarry = (tuple(V2.of(c) for c in com), tuple(ang), jnp.zeros((), f32))
        done = _position_solved if cfg.position_early_stop else None
        with jax.named_scope("position_passes"):
            if position_layout is not None:
                com, ang, solved = position_passes_in_lanes(model, position_layout, n_pos, pconsts, pcarry,
                                                            mode=cfg.kernel, unroll=cfg.unroll, done=done)
            else:
                com, ang, solved = fused.per_world_fori_loop(n_pos, ppass, pconsts, pcarry, mode=cfg.kernel,
                                                             unroll=cfg.unroll, done=done)
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
    toi_pairs = toi_box_pairs = None
    toi_crowded = jnp.zeros((), bool)
    if edge_mode and cfg.continuous and not free_flight:  # solid polygons: Box2D's time of impact
        with jax.named_scope("time_of_impact"):
            com, ang, vel, omg, toi_pairs, toi_box_pairs, toi_crowded = _time_of_impact_polygons(
                model, b, jnp.stack(com), jnp.stack(ang), jnp.stack(vel), jnp.stack(omg), edges, valid, boxes, box_valid)
        com, ang, vel, omg = list(com), list(ang), list(vel), list(omg)
    if edge_mode:  # a solid slot's vertex crossing is not a touch there; sensors keep it
        toi_touch = crossing & jnp.asarray(model.slot_sensor)
    elif cfg.continuous and not free_flight:
        alpha_slot = jnp.clip((d0 - target) / jnp.maximum(d0 - d1, 1e-9), 0.0, 1.0)
        if cfg.toi_from_touching:
            alpha_slot = jnp.where(early, 0.0, alpha_slot)
        with jax.named_scope("time_of_impact"):
            com, ang, vel, omg = _time_of_impact(model, slots, b, jnp.stack(com), jnp.stack(ang), jnp.stack(vel),
                                                 jnp.stack(omg), crossing, alpha_slot, plane_q, plane_n)
        com, ang, vel, omg = list(com), list(ang), list(vel), list(omg)

    # 8. sleep
    vel_a = jnp.stack(vel)
    omg_a = jnp.stack(omg)
    moving = (omg_a**2 > cfg.angular_sleep_tolerance**2) | (dot(vel_a, vel_a) > cfg.linear_sleep_tolerance**2)
    sleep_time = jnp.where(moving, 0.0, world.sleep_time + dt)
    asleep = (jnp.min(sleep_time) >= cfg.time_to_sleep) & solved

    zero = jnp.zeros((), jnp.float32)
    if edge_mode:
        ln_full = jnp.stack(ln) if ln else jnp.zeros((model.num_contacts,), jnp.float32)
        lt_full = jnp.stack(lt) if lt else jnp.zeros((model.num_contacts,), jnp.float32)
        # a key is kept only where its contact is on (zero elsewhere, so free flight stores the same)
        contact_key, stored_touching = jnp.where(e_on[:, None], ec["key"], 0), e_on
    else:
        pos_of = {k: s for s, k in enumerate(slots)}
        ln_full = jnp.stack([ln[pos_of[k]] if k in pos_of else zero for k in range(model.num_slots)])
        lt_full = jnp.stack([lt[pos_of[k]] if k in pos_of else zero for k in range(model.num_slots)])
        contact_key, stored_touching = world.contact_key, active
    new_world = WorldState(
        bodies=BodyState(com=jnp.stack(com), angle=jnp.stack(ang), vel=vel_a, omega=omg_a),
        sleep_time=sleep_time,
        normal_impulse=ln_full,
        tangent_impulse=lt_full,
        joint_impulse=jnp.stack(jimp) if jimp else world.joint_impulse,
        motor_impulse=jnp.stack(jmot) if jmot else world.motor_impulse,
        limit_state=jnp.stack(jstate) if jstate else world.limit_state,
        touching=stored_touching,
        asleep=asleep,
        contact_key=contact_key,
    )
    box_pairs = ec["box_pairs"] if edge_mode else None
    if edge_mode:  # per (polygon, edge): Box2D's touching (manifold points) at the start pose or at a time
        # of impact, for the solid polygons (sensor polygons' rows are False: they touch through vertices)
        solid_poly = jnp.asarray([k in model.edge_polygons for k in range(len(model.polygons))])
        edge_rows = ec["pairs"] if toi_pairs is None else ec["pairs"] | toi_pairs
        pairs = edge_rows & solid_poly[:, None]
        if toi_box_pairs is not None:
            box_pairs = box_pairs | toi_box_pairs
        poly_touch = poly_touch | jnp.any(pairs, 1) | jnp.any(box_pairs, 1)
    else:  # per (polygon, ground segment): start pose, plus segments hit by a time of impact
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
    if edge_mode:
        info["box_touching"] = box_pairs
        info["toi_crowded"] = toi_crowded
        info["manifolds_crowded"] = crowded
    return new_world, info


def _time_of_impact_polygons(model: Model, b: BodyState, com, ang, vel, omg, edges, valid, boxes, box_valid):
    """Box2D's SolveTOI for the solid polygons against the static edges and boxes (edge contacts):
    -> (com (B, 2), angle (B,), vel (B, 2), omega (B,)) at the step's end, and the (polygon, edge)
    (num_polygons, S) and (polygon, box) (num_polygons, K) pairs touching at a time of impact, and
    whether any polygon had more shapes in reach than ``config.toi_candidates``.

    Each body's sweep runs from the step's start ``b`` to the regular solve's end (``com``, ``ang``).
    Its time of impact is the earliest over its polygons and the shapes in reach (``toi.earliest_impact``,
    the touching-at-the-start rule with ``config.toi_from_touching``). A body with one moves back to that
    pose, where its manifolds (``edge_constraints``) are solved alone: ``toi_position_iterations``
    position passes with Baumgarte ``toi_baumgarte`` until its deepest point is within 1.5 slops
    (``b2ContactSolver::SolveTOIPositionConstraints``), then, from the corrected pose, ``toi_iterations``
    velocity passes without warm starting (``b2Island::SolveTOI``; joints are not in Box2D's TOI
    islands), and it moves on with the new velocity for the rest of the step. That sweep, from the
    corrected pose at the time of impact to the new end, is searched again, up to ``toi_events``
    impacts per body and step (Box2D allows up to 8 per contact). A body without a manifold point at
    its time of impact keeps its end pose (Box2D disables that contact)."""
    cfg = model.config
    nb = model.num_bodies
    shapes, ok = toi.edge_shapes(edges), valid
    if boxes is not None:
        shapes = jnp.concatenate([shapes, pg.box_polygon(boxes)[0]])
        ok = jnp.concatenate([ok, box_valid])
    sweep = (b.com, b.angle, jnp.zeros((nb,), jnp.float32))  # the sweep's start pose and its time alpha0
    end = (com, ang, vel, omg)
    pairs = box_pairs = None
    crowded = jnp.zeros((), bool)
    for _ in range(cfg.toi_events):
        sweep, end, p_e, bp_e, crowd_e = _toi_event(model, sweep, end, shapes, ok, edges, valid, boxes, box_valid)
        pairs = p_e if pairs is None else pairs | p_e
        box_pairs = bp_e if box_pairs is None else box_pairs | bp_e
        crowded = crowded | crowd_e
    return (*end, pairs, box_pairs, crowded)


def _toi_event(model: Model, sweep, end, shapes, ok, edges, valid, boxes, box_valid):
    """One time-of-impact event per body (``_time_of_impact_polygons``): ``sweep`` = (start com (B, 2),
    start angle (B,), its step time alpha0 (B,)), ``end`` = (com, angle, vel, omega) at the step's end.
    Returns the new sweep and end (bodies without an impact unchanged), the pairs touching at the
    impact and the crowded flag."""
    cfg = model.config
    f32 = jnp.float32
    nb = model.num_bodies
    s_com, s_ang, alpha0 = sweep
    com, ang, vel, omg = end
    target = max(cfg.linear_slop, cfg.contact_radius - 3.0 * cfg.linear_slop)
    tolerance = 0.25 * cfg.linear_slop
    lc = np.asarray(model.local_com, np.float32)
    beta = jnp.ones((nb,), f32)  # the impact's time within the sweep
    crowded = jnp.zeros((), bool)
    impact = jax.vmap(functools.partial(toi.earliest_impact, target=target, tolerance=tolerance,
                                        candidates=cfg.toi_candidates, samples=cfg.toi_samples,
                                        bisections=cfg.toi_bisections, from_touching=cfg.toi_from_touching),
                      in_axes=(0, 0, 0, 0, 0, None, None))
    for ks in _by_vertex_count(model):  # one vmapped search per group
        i = np.asarray([model.polygons[k].body for k in ks], np.int32)
        local = jnp.asarray(np.stack([np.asarray(model.polygons[k].vertices, np.float32) - lc[model.polygons[k].body]
                                      for k in ks]))
        with jax.named_scope("search"):
            a_k, _, crowd_k = impact(local, s_com[i], s_ang[i], com[i], ang[i], shapes, ok)
        beta = beta.at[i].min(a_k)
        crowded = crowded | jnp.any(crowd_k)
    alpha = alpha0 + (1.0 - alpha0) * beta  # the impact's time within the step
    hit = (beta < 1.0) & (alpha < 1.0 - 10.0 * float(np.finfo(np.float32).eps))  # Box2D's "no more TOI events" test

    def solve(hit):  # the impact pose's manifolds and passes; a body without an impact keeps its sweep and end
        c_t = s_com + beta[:, None] * (com - s_com)
        a_t = s_ang + beta * (ang - s_ang)
        at_toi = BodyState(com=c_t, angle=a_t, vel=vel, omega=omg)
        with jax.named_scope("manifolds"):
            ec = edge_constraints(model, at_toi, edges, valid, boxes, box_valid)
        body = ec["body"]
        cb = np.asarray(body, np.int32)
        groups = [[k for k, i in enumerate(body) if i == g] for g in range(nb)]
        has = jnp.stack([jnp.any(jnp.stack([ec["on"][k] for k in ks])) if ks else jnp.zeros((), bool) for ks in groups])
        hit = hit & has
        ec = dict(ec, on=ec["on"] & hit[cb])
        moving = [g for g in range(nb) if groups[g]]
        inv_m = [float(model.inv_mass[g]) for g in moving]
        inv_i = [float(model.inv_inertia[g]) for g in moving]
        flags = tuple(fused.BlockAny(hit[g].astype(f32)) for g in moving)

        # position passes at the time of impact, per body (its contacts only)
        with jax.named_scope("position_constants"):
            pconsts = dict(_edge_position_constants(model, at_toi, ec), hit=flags)
        carry = (tuple(V2.of(c_t[g]) for g in moving), tuple(a_t[g] for g in moving), tuple(jnp.zeros((), f32) for _ in moving))
        if cfg.toi_position_iterations > 0:
            ppass = functools.partial(_toi_position_pass_polygons, cfg, [groups[g] for g in moving], inv_m, inv_i)
            cs, as_, _ = _toi_passes(cfg, cfg.toi_position_iterations, ppass, pconsts, carry)
            c_p = c_t.at[np.asarray(moving)].set(jnp.stack([c.array() for c in cs]))
            a_p = a_t.at[np.asarray(moving)].set(jnp.stack(as_))
        else:
            c_p, a_p = c_t, a_t

        # velocity passes from the corrected pose (Box2D's "leap of faith"), no warm start
        moved = _manifolds_moved(ec, c_t[cb], a_t[cb], c_p[cb], a_p[cb])
        at_p = BodyState(com=c_p, angle=a_p, vel=vel, omega=omg)
        with jax.named_scope("velocity_constants"):
            vconsts = _edge_velocity_constants(model, at_p, moved)
        zeros = tuple(jnp.zeros((), f32) for _ in body)
        vcarry = (tuple(V2.of(vel[g]) for g in range(nb)), tuple(omg[g] for g in range(nb)), zeros, zeros)
        layout = lane_layout(body) if cfg.velocity_lanes and cfg.toi_loop else None
        if layout is not None:  # each body's manifolds in a lane of their own, as the step's velocity passes
            vs, ws, _, _ = velocity_passes_in_lanes(model, layout, ec["friction"], cfg.toi_iterations, vconsts, vcarry,
                                                    mode=cfg.kernel, unroll=cfg.unroll, joints=False)
        else:
            vpass = functools.partial(_toi_velocity_pass_polygons, model, body, ec["friction"])
            vs, ws, _, _ = _toi_passes(cfg, cfg.toi_iterations, vpass, vconsts, vcarry)
        v_t = jnp.stack([v.array() for v in vs])
        w_t = jnp.stack(ws)
        rest = (1.0 - alpha) * cfg.dt  # the rest of the step, clamped as Box2D integrates
        tr = rest[:, None] * v_t
        tr2 = dot(tr, tr)
        v_t = jnp.where((tr2 > cfg.max_translation**2)[:, None], v_t * (cfg.max_translation / jnp.sqrt(jnp.maximum(tr2, 1e-30)))[:, None], v_t)
        rot = rest * w_t
        w_t = jnp.where(rot * rot > cfg.max_rotation**2, w_t * (cfg.max_rotation / jnp.maximum(jnp.abs(rot), 1e-30)), w_t)
        hit_poly = jnp.asarray([model.polygons[k].body for k in range(len(model.polygons))], jnp.int32)
        hit_poly = hit[hit_poly][:, None]
        new_end = (jnp.where(hit[:, None], c_p + rest[:, None] * v_t, com), jnp.where(hit, a_p + rest * w_t, ang),
                   jnp.where(hit[:, None], v_t, vel), jnp.where(hit, w_t, omg))
        new_sweep = (jnp.where(hit[:, None], c_p, s_com), jnp.where(hit, a_p, s_ang), jnp.where(hit, alpha, alpha0))
        return new_sweep, new_end, ec["pairs"] & hit_poly, ec["box_pairs"] & hit_poly

    if not cfg.toi_gate:
        return (*solve(hit), crowded)
    # the solve leaves every body without a hit as it was, so a batch in which no world has one skips it
    shapes = jax.eval_shape(solve, hit)

    def skip(_):
        return (s_com, s_ang, alpha0), end, jnp.zeros(shapes[2].shape, bool), jnp.zeros(shapes[3].shape, bool)

    return (*jax.lax.cond(fused.batch_any(jnp.any(hit)), solve, skip, hit), crowded)


def _manifolds_moved(ec, com0, ang0, com1, ang1):
    """Manifold points carried rigidly with their bodies from (com0, ang0) to (com1, ang1) (per
    contact (E, 2), (E,)), as Box2D's world manifold follows the bodies' transforms: the polygon's
    side (face A's clip points, face B's face) moves, the static side stays; the velocity frame
    (``normal``, ``point`` midway between the skins) follows."""
    fb = ec["face_b"][:, None]
    turn = ang1 - ang0
    move = lambda p: com1 + rotate(turn, p - com0)  # noqa: E731
    ref_n = jnp.where(fb, rotate(turn, ec["ref_normal"]), ec["ref_normal"])
    ref_p = jnp.where(fb, move(ec["ref_point"]), ec["ref_point"])
    clip = jnp.where(fb, ec["clip"], move(ec["clip"]))
    raw = dot(clip - ref_p, ref_n)
    return dict(ec, normal=jnp.where(fb, -ref_n, ref_n), point=clip - 0.5 * raw[:, None] * ref_n,
                ref_normal=ref_n, ref_point=ref_p, clip=clip)


def _toi_position_pass_polygons(cfg, groups, inv_m, inv_i, c, carry):
    """One TOI position pass per moving body over its own manifold points (Baumgarte
    ``toi_baumgarte``); a body stops once its deepest point is within 1.5 slops (``done`` 0/1).
    Per-world scalars (``fused`` contract); a body no world of a kernel block moves back is skipped."""
    out = []
    for g, state in enumerate(zip(*carry)):
        fn = functools.partial(_toi_body_position_polygons, cfg, c, groups[g], inv_m[g], inv_i[g])
        out.append(fused.when(c["hit"][g], fn, state, cfg.skip_untouched))
    return tuple(tuple(x) for x in zip(*out))


def _toi_body_position_polygons(cfg, c, ks, inv_m, inv_i, state):
    c0, a0, done = state
    c_, a_, min_sep = c0, a0, jnp.zeros_like(a0)
    for k in ks:
        c_, a_, min_sep = _point_position(cfg, c, k, inv_m, inv_i, (c_, a_, min_sep), cfg.toi_baumgarte)
    frozen = done > 0.5
    return (c0.where(frozen, c_), jnp.where(frozen, a0, a_),
            jnp.where(frozen | (min_sep >= -1.5 * cfg.linear_slop), 1.0, 0.0).astype(jnp.float32))


def _toi_velocity_pass_polygons(model: Model, body, friction, c, carry):
    """One TOI velocity pass: the manifolds alone (no joints), every body at once (each manifold
    acts on its own body only). Per-world scalars (``fused`` contract)."""
    vel, omg, ln, lt = (list(x) for x in carry)
    _manifolds_velocity(model, body, friction, c, vel, omg, ln, lt)
    return tuple(vel), tuple(omg), tuple(ln), tuple(lt)


def _time_of_impact(model: Model, slots, b: BodyState, com, ang, vel, omg, crossing, alpha_slot, plane_q,
                    plane_n):
    """Box2D's SolveTOI, simplified, for every body at once -> (com (B, 2), angle (B,), vel (B, 2),
    omega (B,)) at the step's end.

    A body whose solid slot crosses the target separation during the step (``crossing`` (V,), at
    fraction ``alpha_slot`` (V,)) moves back to its earliest time of impact, its slots within
    ``contact_radius`` there are solved alone (``toi_position_iterations`` position passes, ``toi_iterations`` velocity passes; joints are
    not part of Box2D's TOI islands) and it moves on for the rest of the step. ``com`` (B, 2), ``ang``
    (B,), ``vel`` (B, 2), ``omg`` (B,) are the ends of the regular solve; ``b`` the start of the step.
    The pose at impact is found on (B, W) arrays (each body's slots in model order, padded to the
    largest count with slots that are never on); the passes then run on per-world scalars
    (``_toi_position_pass``, ``_toi_velocity_pass``): unrolled, or with ``config.toi_loop`` as
    ``fused.per_world_fori_loop``s (one GPU kernel each instead of an XLA loop of small kernels).
    """
    cfg = model.config
    f32 = jnp.float32
    per_body = [[k for k in slots if model.slot_body[k] == i] for i in range(model.num_bodies)]
    width = max((len(ks) for ks in per_body), default=0)
    if width == 0:
        return com, ang, vel, omg
    idx = np.asarray([ks + [0] * (width - len(ks)) for ks in per_body], np.int32)  # (B, W) slot per position
    real = jnp.asarray([[s < len(ks) for s in range(width)] for ks in per_body])
    lv = (np.asarray(model.slot_vertex, np.float32)[idx]
          - np.asarray(model.local_com, np.float32)[:, None])  # (B, W, 2) slot vertex from the centre
    q, n = plane_q[idx], plane_n[idx]  # (B, W, 2)
    t = jnp.stack([n[..., 1], -n[..., 0]], -1)
    cross_k = crossing[idx] & real
    hit = jnp.any(cross_k, 1)
    alpha = jnp.min(jnp.where(cross_k, alpha_slot[idx], 1.0), 1)
    c_t = b.com + alpha[:, None] * (com - b.com)
    a_t = b.angle + alpha * (ang - b.angle)
    arms = rotate(a_t[:, None], lv)
    on = hit[:, None] & real & (dot(c_t[:, None] + arms - q, n) <= cfg.contact_radius)

    # per-world scalars for the passes: bodies with solid slots, their real slots
    moving = [i for i in range(model.num_bodies) if per_body[i]]
    pslots = tuple(tuple(range(len(per_body[i]))) for i in moving)
    geom = dict(lv=tuple(tuple((np.float32(lv[i, s, 0]), np.float32(lv[i, s, 1])) for s in range(len(per_body[i])))
                         for i in moving),
                mu=tuple(tuple(np.float32(model.slot_friction[per_body[i][s]]) for s in range(len(per_body[i])))
                         for i in moving),
                inv_m=tuple(float(model.inv_mass[i]) for i in moving), inv_i=tuple(float(model.inv_inertia[i]) for i in moving))
    per_slot = lambda a, vec=False: tuple(tuple(V2.of(a[i, s]) if vec else a[i, s].astype(f32) for s in ss)  # noqa: E731
                                          for i, ss in zip(moving, pslots))
    consts = dict(on=per_slot(on), q=per_slot(q, True), n=per_slot(n, True), t=per_slot(t, True),
                  any=tuple(fused.BlockAny(jnp.any(on[i]).astype(f32)) for i in moving))
    run = functools.partial(_toi_passes, cfg)
    if cfg.toi_position_iterations > 0:
        carry = (tuple(V2.of(c_t[i]) for i in moving), tuple(a_t[i] for i in moving),
                 tuple(jnp.zeros((), f32) for _ in moving))
        cs, as_, _ = run(cfg.toi_position_iterations, functools.partial(_toi_position_pass, cfg, geom),
                         {k: consts[k] for k in ("on", "q", "n", "any")}, carry)
        c_t = c_t.at[np.asarray(moving)].set(jnp.stack([c.array() for c in cs]))
        a_t = a_t.at[np.asarray(moving)].set(jnp.stack(as_))
        arms = rotate(a_t[:, None], lv)
    zeros = tuple(tuple(jnp.zeros((), f32) for _ in ss) for ss in pslots)
    carry = (tuple(V2.of(vel[i]) for i in moving), tuple(omg[i] for i in moving), zeros, zeros)
    vs, ws, _, _ = run(cfg.toi_iterations, functools.partial(_toi_velocity_pass, cfg, geom),
                       dict(arm=per_slot(arms, True), n=consts["n"], t=consts["t"], on=consts["on"], any=consts["any"]),
                       carry)
    v_t = vel.at[np.asarray(moving)].set(jnp.stack([v.array() for v in vs]))
    w_t = omg.at[np.asarray(moving)].set(jnp.stack(ws))
    rest = (1.0 - alpha) * cfg.dt
    return (jnp.where(hit[:, None], c_t + rest[:, None] * v_t, com), jnp.where(hit, a_t + rest * w_t, ang),
            jnp.where(hit[:, None], v_t, vel), jnp.where(hit, w_t, omg))


def _toi_passes(cfg, n: int, body, consts, carry):
    """``n`` passes of a time-of-impact ``body`` (per-world scalars): a fused loop with
    ``config.toi_loop``, else unrolled (the same arithmetic)."""
    if cfg.toi_loop:
        return fused.per_world_fori_loop(n, body, consts, carry, mode=cfg.kernel, unroll=cfg.unroll)
    for _ in range(n):
        carry = body(consts, carry)
    return carry


def _toi_position_pass(cfg, geom, c, carry):
    """One TOI position pass per body (Box2D's SolveTOIPositionConstraints: Baumgarte ``toi_baumgarte``,
    each slot against its plane at the time of impact); a body stops moving once its deepest slot is
    within 1.5 slops (``done`` 0/1). Per-world scalars (``fused`` contract); a body no world of a
    kernel block moves back is skipped there (its pose cannot change, and ``done`` is not returned)."""
    out = [fused.when(c["any"][b_], functools.partial(_toi_body_position, cfg, geom, c, b_), state, cfg.skip_untouched)
           for b_, state in enumerate(zip(*carry))]
    return tuple(tuple(x) for x in zip(*out))


def _toi_body_position(cfg, geom, c, b_, state):
    c_, a_, done = state
    inv_m, inv_i = geom["inv_m"][b_], geom["inv_i"][b_]
    c0, a0 = c_, a_
    min_sep = jnp.zeros((), jnp.float32)
    for s, (lx, ly) in enumerate(geom["lv"][b_]):
        on, q, n = c["on"][b_][s] > 0.5, c["q"][b_][s], c["n"][b_][s]
        r = rotate2(a_, V2(lx, ly))
        sep = (c_ + r - q).dot(n) - cfg.contact_radius
        min_sep = jnp.where(on, jnp.minimum(min_sep, sep), min_sep)
        c_, a_ = _position_impulse(cfg, inv_m, inv_i, c_, a_, r, n, sep, on, cfg.toi_baumgarte)
    frozen = done > 0.5
    return (c0.where(frozen, c_), jnp.where(frozen, a0, a_),
            jnp.where(frozen | (min_sep >= -1.5 * cfg.linear_slop), 1.0, 0.0).astype(jnp.float32))


def _toi_velocity_pass(cfg, geom, c, carry):
    """One TOI velocity pass per body: each touching slot's friction, then its normal impulse, against
    the ground alone (no joints). Per-world scalars (``fused`` contract); skipped per block like the
    position pass."""
    out = [fused.when(c["any"][b_], functools.partial(_toi_body_velocity, geom, c, b_), state, cfg.skip_untouched)
           for b_, state in enumerate(zip(*carry))]
    return tuple(tuple(x) for x in zip(*out))


def _toi_body_velocity(geom, c, b_, state):
    v_t, w_t, lnn, ltt = state
    lnn, ltt = list(lnn), list(ltt)
    inv_m, inv_i = geom["inv_m"][b_], geom["inv_i"][b_]
    for s, mu in enumerate(geom["mu"][b_]):
        r, n_s, t_s, on_s = c["arm"][b_][s], c["n"][b_][s], c["t"][b_][s], c["on"][b_][s] > 0.5
        rn_, rt_ = r.cross(n_s), r.cross(t_s)
        dv = v_t + cross_sv2(w_t, r)
        new_t = jnp.clip(ltt[s] - dv.dot(t_s) / (inv_m + inv_i * rt_ * rt_), -mu * lnn[s], mu * lnn[s])
        new_t = jnp.where(on_s, new_t, 0.0)
        pt = t_s * (new_t - ltt[s])
        ltt[s] = new_t
        v_t, w_t = v_t + inv_m * pt, w_t + inv_i * r.cross(pt)
        dv = v_t + cross_sv2(w_t, r)
        new_n = jnp.maximum(lnn[s] - dv.dot(n_s) / (inv_m + inv_i * rn_ * rn_), 0.0)
        new_n = jnp.where(on_s, new_n, 0.0)
        pn = n_s * (new_n - lnn[s])
        lnn[s] = new_n
        v_t, w_t = v_t + inv_m * pn, w_t + inv_i * r.cross(pn)
    return v_t, w_t, tuple(lnn), tuple(ltt)


def _masses(model: Model, joint):
    inv_m, inv_i = model.inv_mass, model.inv_inertia
    return (float(inv_m[joint.body_a]), float(inv_m[joint.body_b]),
            float(inv_i[joint.body_a]), float(inv_i[joint.body_b]))


def _velocity_pass(model: Model, slots, c, carry):
    """One Gauss-Seidel velocity pass (joints, then each contact slot: friction, then normal).

    Per-world scalars only (``V2`` for vectors), as ``fused.per_world_fori_loop`` requires.
    """
    inv_m, inv_i = [float(x) for x in model.inv_mass], [float(x) for x in model.inv_inertia]
    sb = model.slot_body
    vel, omg, jimp, jmot, ln, lt = (list(x) for x in carry)
    _joint_velocity_pass(model, c, vel, omg, jimp, jmot)
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


def _position_solved(carry):
    """Box2D's early stop of the position passes (``b2Island::Solve`` breaks once contacts and joints
    are solved): the passes' carry ``(com, angle, solved)`` -> ``solved``."""
    return carry[2]


def _position_pass(model: Model, slots, c, carry):
    """One non-linear Gauss-Seidel position pass (contacts, then joints); frozen once solved.

    ``carry = (com, angle, solved)`` with ``solved`` a 0/1 float (per-world scalars only).
    """
    cfg = model.config
    inv_m, inv_i = [float(x) for x in model.inv_mass], [float(x) for x in model.inv_inertia]
    sb = model.slot_body
    lc = np.asarray(model.local_com, np.float32)
    local_v = np.asarray(model.slot_vertex, np.float32)
    com0, ang0, _ = carry
    com, ang = list(com0), list(ang0)
    min_sep = jnp.zeros((), jnp.float32)
    for s, k in enumerate(slots):
        i = sb[k]
        on, normal = c["on"][s] > 0.5, c["n"][s]
        arm_k = rotate2(ang[i], V2(*(local_v[k] - lc[i])))
        sep = (com[i] + arm_k - c["q"][s]).dot(normal) - cfg.contact_radius
        min_sep = jnp.where(on, jnp.minimum(min_sep, sep), min_sep)
        com[i], ang[i] = _position_impulse(cfg, inv_m[i], inv_i[i], com[i], ang[i], arm_k, normal, sep, on)
    return _joint_positions_then_freeze(model, c, lc, carry, com, ang, min_sep)


def _position_impulse(cfg, inv_m, inv_i, com, ang, arm, normal, sep, on, baumgarte=None):
    """One contact point's position correction (Box2D's SolvePositionConstraints step): the
    Baumgarte-scaled, clamped push along ``normal`` at ``arm`` from the centre of mass -> (com, angle).
    ``baumgarte``: ``cfg.baumgarte`` unless given (the time of impact's sub-step uses its own)."""
    baumgarte = cfg.baumgarte if baumgarte is None else baumgarte
    corr = jnp.clip(baumgarte * (sep + cfg.linear_slop), -cfg.max_linear_correction, 0.0)
    rnk = arm.cross(normal)
    kk = inv_m + inv_i * rnk * rnk
    imp = jnp.where(on & (kk > 0), -corr / kk, 0.0)
    p = imp * normal
    return com + inv_m * p, ang + inv_i * arm.cross(p)


def _joint_positions_then_freeze(model: Model, c, lc, carry, com, ang, min_sep):
    """The joints' position pass after the contacts' -> the pass's new carry: worlds already solved
    keep their start pose; a world is solved when no contact is deeper than 3 slops and every joint
    is within tolerance."""
    cfg = model.config
    com0, ang0, solved = carry
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


MAX_CONDITION_NUMBER = 1000.0  # Box2D's k_maxConditionNumber for the 2-point block solver


def _edge_velocity_constants(model: Model, bodies: BodyState, ec):
    """Per edge contact point (E) and per manifold (E / 2), as b2ContactSolver::InitializeVelocityConstraints:
    arm from the body's centre to Box2D's world point, normal / tangent and their effective masses; for
    two-point manifolds the block matrix K and the inverse of its determinant (the pass forms K's
    inverse from them), used when K is well conditioned (otherwise Box2D solves the first point only,
    so the second is switched off here). Per-world scalars."""
    inv_m, inv_i = model.inv_mass, model.inv_inertia
    body = ec["body"]
    ne = len(body)
    com = bodies.com[np.asarray(body, np.int32)]
    arm = ec["point"] - com
    n = ec["normal"]
    t = jnp.stack([n[:, 1], -n[:, 0]], -1)
    mb = jnp.asarray([inv_m[i] for i in body], jnp.float32)
    ib = jnp.asarray([inv_i[i] for i in body], jnp.float32)
    rn, rt = cross(arm, n), cross(arm, t)
    kn, kt = mb + ib * rn**2, mb + ib * rt**2
    nm = jnp.where(kn > 0, 1.0 / kn, 0.0)
    tm = jnp.where(kt > 0, 1.0 / kt, 0.0)
    on = ec["on"]
    c = dict(n=[], t=[], arm=[], nm=[], tm=[], on=[], blk=[], k11=[], k12=[], k22=[], inv=[])
    for p in range(ne // 2):
        a, b_ = 2 * p, 2 * p + 1
        k11, k22 = kn[a], kn[b_]
        k12 = mb[a] + ib[a] * rn[a] * rn[b_]
        det = k11 * k22 - k12 * k12
        well = k11 * k11 < MAX_CONDITION_NUMBER * det
        inv = jnp.where(det != 0.0, 1.0 / jnp.where(det != 0.0, det, 1.0), 0.0)
        blk = on[a] & on[b_] & well
        for name, val in (("k11", k11), ("k12", k12), ("k22", k22), ("inv", inv)):
            c[name].append(val)
        c["blk"].append(blk.astype(jnp.float32))
        for k, on_k in ((a, on[a]), (b_, on[b_] & well)):
            c["on"].append(on_k.astype(jnp.float32))
            c["n"].append(V2.of(n[k]))
            c["t"].append(V2.of(t[k]))
            c["arm"].append(V2.of(arm[k]))
            c["nm"].append(nm[k])
            c["tm"].append(tm[k])
    return {name: tuple(v) for name, v in c.items()}


def _edge_position_constants(model: Model, bodies: BodyState, ec):
    """Per edge contact point, what b2PositionSolverManifold needs, in the frame that stays fixed:
    face A: the edge's plane (world point ``a``, normal ``nrm``) and the clip point in the body frame
    (``pt``, from the body's centre); face B: the polygon face's point and normal in the body frame
    (``a``, ``nrm``) and the clip point on the edge (world ``pt``). Per-world scalars."""
    body = ec["body"]
    com = bodies.com[np.asarray(body, np.int32)]
    ang = bodies.angle[np.asarray(body, np.int32)]
    fb = ec["face_b"]
    to_body = lambda v: rotate(-ang, v)
    a = jnp.where(fb[:, None], to_body(ec["ref_point"] - com), ec["ref_point"])
    nrm = jnp.where(fb[:, None], to_body(ec["ref_normal"]), ec["ref_normal"])
    pt = jnp.where(fb[:, None], ec["clip"], to_body(ec["clip"] - com))
    return dict(on=tuple(ec["on"][k].astype(jnp.float32) for k in range(len(body))),
                any=tuple(fused.BlockAny(ec["on"][k].astype(jnp.float32)) for k in range(len(body))),
                fb=tuple(fb[k].astype(jnp.float32) for k in range(len(body))),
                a=tuple(V2.of(a[k]) for k in range(len(body))), nrm=tuple(V2.of(nrm[k]) for k in range(len(body))),
                pt=tuple(V2.of(pt[k]) for k in range(len(body))))


def _joint_velocity_pass(model: Model, c, vel, omg, jimp, jmot):
    """The joints' part of a velocity pass (in place on the lists)."""
    dt = model.config.dt
    for j, J in enumerate(model.joints):
        a_, b_ = J.body_a, J.body_b
        speed = c["motor_speed"][j] if "motor_speed" in c else None
        torque = c["max_motor_torque"][j] if "max_motor_torque" in c else None
        jimp[j], jmot[j], vel[a_], omg[a_], vel[b_], omg[b_] = jnt.solve_velocity(
            J, _masses(model, J), c["ra"][j], c["rb"][j], c["state"][j], jimp[j], jmot[j],
            vel[a_], omg[a_], vel[b_], omg[b_], dt, speed, torque)


def _velocity_pass_edges(model: Model, body, friction, c, carry):
    """One velocity pass with edge manifolds (b2ContactSolver::SolveVelocityConstraints): joints, then
    per manifold the friction of each point, then the normal impulses, by Box2D's 2-point block solver
    (its four cases: both points, first only, second only, none) when both points are on and K is well
    conditioned, else the first point alone. Per-world scalars only (``fused`` contract). Unlike the
    position pass it computes every manifold: skipping untouched ones per block (``fused.when``) made
    this kernel 3.4x slower on an H200 (docs/bipedal.md, speed)."""
    vel, omg, jimp, jmot, ln, lt = (list(x) for x in carry)
    _joint_velocity_pass(model, c, vel, omg, jimp, jmot)
    _manifolds_velocity(model, body, friction, c, vel, omg, ln, lt)
    return tuple(vel), tuple(omg), tuple(jimp), tuple(jmot), tuple(ln), tuple(lt)


def _manifolds_velocity(model: Model, body, friction, c, vel, omg, ln, lt):
    """The manifolds' part of a velocity pass (in place on the lists): per manifold the friction of
    each point, then the normal impulses (block solver or first point alone)."""
    inv_m, inv_i = [float(x) for x in model.inv_mass], [float(x) for x in model.inv_inertia]
    for p in range(len(body) // 2):
        k1, k2 = 2 * p, 2 * p + 1
        i = body[k1]
        vel[i], omg[i], ln[k1], ln[k2], lt[k1], lt[k2] = _manifold_velocity(
            c, p, inv_m[i], inv_i[i], np.float32(friction[k1]), np.float32(friction[k2]),
            vel[i], omg[i], ln[k1], ln[k2], lt[k1], lt[k2])


def _manifold_velocity(c, p, mi, ii, f1, f2, v, w, ln1, ln2, lt1, lt2):
    """One manifold ``p`` (points 2p, 2p + 1 of ``c``) on its body's velocity ``v``, ``w``, with the
    body's inverse mass and inertia ``mi``, ``ii`` and the points' friction ``f1``, ``f2`` (numbers,
    or per-world scalars where the manifold's body varies by world): b2ContactSolver's friction of
    each point, then the normal impulses. Returns (v, w, ln1, ln2, lt1, lt2)."""
    k1, k2 = 2 * p, 2 * p + 1
    n = c["n"][k1]
    t = V2(n.y, -n.x)  # the tangent, as Box2D's b2Cross(normal, 1.0f): two fewer kernel inputs
    lt_ = [lt1, lt2]
    for j, (k, f, ln_k) in enumerate(((k1, f1, ln1), (k2, f2, ln2))):  # friction
        arm = c["arm"][k]
        vt = (v + cross_sv2(w, arm)).dot(t)
        max_f = f * ln_k
        new_t = jnp.clip(lt_[j] - c["tm"][k] * vt, -max_f, max_f) * c["on"][k]
        pt = (new_t - lt_[j]) * t
        lt_[j] = new_t
        v = v + mi * pt
        w = w + ii * arm.cross(pt)
    r1, r2 = c["arm"][k1], c["arm"][k2]
    vn1 = (v + cross_sv2(w, r1)).dot(n)
    vn2 = (v + cross_sv2(w, r2)).dot(n)
    # one point (Box2D's pointCount == 1)
    s_new = jnp.maximum(ln1 - c["nm"][k1] * vn1, 0.0) * c["on"][k1]
    # block solve of both points
    a1, a2 = ln1, ln2
    k11, k12, k22, inv = c["k11"][p], c["k12"][p], c["k22"][p], c["inv"][p]
    m11, m12, m22 = inv * k22, -inv * k12, inv * k11  # K's inverse, in the kernel: fewer inputs held
    bx = vn1 - (k11 * a1 + k12 * a2)
    by = vn2 - (k12 * a1 + k22 * a2)
    x1 = -(m11 * bx + m12 * by)
    y1 = -(m12 * bx + m22 * by)
    ok1 = (x1 >= 0.0) & (y1 >= 0.0)
    x2 = -c["nm"][k1] * bx
    ok2 = (x2 >= 0.0) & (k12 * x2 + by >= 0.0)
    y3 = -c["nm"][k2] * by
    ok3 = (y3 >= 0.0) & (k12 * y3 + bx >= 0.0)
    ok4 = (bx >= 0.0) & (by >= 0.0)
    bxn = jnp.where(ok1, x1, jnp.where(ok2, x2, jnp.where(ok3, 0.0, jnp.where(ok4, 0.0, a1))))
    byn = jnp.where(ok1, y1, jnp.where(ok2, 0.0, jnp.where(ok3, y3, jnp.where(ok4, 0.0, a2))))
    blk = c["blk"][p] > 0.5
    new1 = jnp.where(blk, bxn, s_new)
    new2 = jnp.where(blk, byn, ln2)
    d1, d2 = new1 - ln1, new2 - ln2
    p1, p2 = d1 * n, d2 * n
    v = v + mi * (p1 + p2)
    w = w + ii * (r1.cross(p1) + r2.cross(p2))
    return v, w, new1, new2, lt_[0], lt_[1]


def lane_layout(body) -> tuple | None:
    """How the passes in lanes (``_velocity_pass_lanes``, ``_position_pass_lanes``, the time of impact's
    velocity passes) lay out edge manifolds whose points belong to bodies ``body``
    (per point): ``((body, (manifold, ...)), ...)`` per lane, the bodies in their order of first
    appearance and each body's manifolds in their order; None unless there are ``fused.TILE`` bodies
    with as many manifolds each."""
    n_man = len(body) // 2
    bodies = tuple(dict.fromkeys(body[2 * p] for p in range(n_man)))
    layout = tuple((b, tuple(p for p in range(n_man) if body[2 * p] == b)) for b in bodies)
    if len(layout) != fused.TILE or len({len(m) for _, m in layout}) != 1:
        return None
    return layout


def velocity_passes_in_lanes(model: Model, layout, friction, n: int, consts, carry, *, mode: str, unroll: int = 1,
                             joints: bool = True):
    """``n`` velocity passes in lane form (``fused`` lanes, 4 threads per world), taking and returning
    the sequential passes' ``consts`` and ``carry``: ``_velocity_pass_edges``' (vel, omg, jimp, jmot,
    ln, lt), or with ``joints=False`` the time of impact's ``_toi_velocity_pass_polygons``' (vel, omg,
    ln, lt), manifolds alone."""
    full = carry if joints else carry[:2] + ((), ()) + carry[2:]
    lpass, lconsts, lcarry = to_lanes(model, layout, friction, consts, full, joints=joints)
    out = from_lanes(layout, fused.per_world_fori_loop(n, lpass, lconsts, lcarry, mode=mode, unroll=unroll,
                                                       lanes=fused.TILE))
    return out if joints else out[:2] + out[4:]


def position_passes_in_lanes(model: Model, layout, n: int, consts, carry, *, mode: str, unroll: int = 1, done=None):
    """``n`` position passes of ``_position_pass_edges`` in lane form (``to_position_lanes``), taking its
    ``consts`` and carry (com, angle, solved, per-world scalars) and returning the carry; ``done``: the
    early stop, as ``fused.per_world_fori_loop``'s."""
    lpass, lconsts = to_position_lanes(model, layout, consts)
    return fused.per_world_fori_loop(n, lpass, lconsts, carry, mode=mode, unroll=unroll, done=done, lanes=fused.TILE)


def to_lanes(model: Model, layout, friction, consts, carry, joints: bool = True):
    """The fused velocity loop of ``_velocity_pass_edges`` (its ``consts`` and ``carry``) in lane form,
    -> (pass, consts, carry) for ``fused.per_world_fori_loop(..., lanes=fused.TILE)``: per lane (body of
    ``layout``) its manifolds' constants and impulses as lane vectors; the joints' as they are.
    ``joints=False``: manifolds alone (the carry's joint impulses empty); ``velocity_passes_in_lanes``
    runs the loop."""
    per_lane = len(layout[0][1])
    man = [[ms[m] for _, ms in layout] for m in range(per_lane)]  # [m][lane] -> manifold
    pts = [[2 * man[m][j] + q for j in range(len(layout))] for m in range(per_lane) for q in (0, 1)]

    def lanes(values, idx):
        return jnp.stack([values[k] for k in idx], -1)

    c = {k: v for k, v in consts.items() if k not in ("on", "arm", "n", "nm", "tm", "blk", "k11", "k12", "k22", "inv", "t")}
    for name in ("on", "nm", "tm"):
        c[name] = tuple(lanes(consts[name], idx) for idx in pts)
    for name in ("n", "arm"):
        c[name] = tuple(V2(lanes([v.x for v in consts[name]], idx), lanes([v.y for v in consts[name]], idx))
                        for idx in pts)
    for name in ("blk", "k11", "k12", "k22", "inv"):
        c[name] = tuple(lanes(consts[name], idx) for idx in man)
    vel, omg, jimp, jmot, ln, lt = carry
    carry = (vel, omg, jimp, jmot, tuple(lanes(ln, idx) for idx in pts), tuple(lanes(lt, idx) for idx in pts))
    inv_m, inv_i = model.inv_mass, model.inv_inertia
    f = tuple(tuple(float(friction[k]) for k in idx) for idx in pts)
    mass = (tuple(float(inv_m[b]) for b, _ in layout), tuple(float(inv_i[b]) for b, _ in layout))
    return functools.partial(_velocity_pass_lanes, model, tuple(b for b, _ in layout), mass, f, joints), c, carry


def from_lanes(layout, carry):
    """``to_lanes``' carry (after the loop) back in ``_velocity_pass_edges``' form."""
    vel, omg, jimp, jmot, ln_l, lt_l = carry
    per_lane = len(layout[0][1])
    n_points = 2 * sum(len(ms) for _, ms in layout)
    ln, lt = [None] * n_points, [None] * n_points
    for m in range(per_lane):
        for q in (0, 1):
            for j, (_, ms) in enumerate(layout):
                k = 2 * ms[m] + q
                ln[k], lt[k] = ln_l[2 * m + q][..., j], lt_l[2 * m + q][..., j]
    return vel, omg, jimp, jmot, tuple(ln), tuple(lt)


def _velocity_pass_lanes(model: Model, lane_bodies, mass, friction, joints, c, carry):
    """``_velocity_pass_edges`` in lane form (``to_lanes``): the joints on per-world scalars (unless
    ``joints`` is False), then every lane's manifolds at once, lane j on body ``lane_bodies[j]``'s
    velocity (``fused`` lanes). A body's manifolds change only its own velocity (the ground is static),
    so each lane does the operations Box2D's sequential order does for that body, in that order."""
    vel, omg, jimp, jmot, ln, lt = (list(x) for x in carry)
    if joints:
        _joint_velocity_pass(model, c, vel, omg, jimp, jmot)
    v = V2(fused.lanes_of(*(vel[b].x for b in lane_bodies)), fused.lanes_of(*(vel[b].y for b in lane_bodies)))
    w = fused.lanes_of(*(omg[b] for b in lane_bodies))
    mi, ii = fused.lanes_of(*mass[0]), fused.lanes_of(*mass[1])
    for p in range(len(ln) // 2):
        k1, k2 = 2 * p, 2 * p + 1
        v, w, ln[k1], ln[k2], lt[k1], lt[k2] = _manifold_velocity(
            c, p, mi, ii, fused.lanes_of(*friction[k1]), fused.lanes_of(*friction[k2]), v, w,
            ln[k1], ln[k2], lt[k1], lt[k2])
    for j, b in enumerate(lane_bodies):
        vel[b] = V2(fused.lane(v.x, j), fused.lane(v.y, j))
        omg[b] = fused.lane(w, j)
    return tuple(vel), tuple(omg), tuple(jimp), tuple(jmot), tuple(ln), tuple(lt)


def _pack_manifolds(model: Model, body, friction, econ, ln, lt, slots: int):
    """The velocity passes' inputs with the manifolds that have points packed, in their order, into
    ``slots`` manifold slots (``SolverConfig.velocity_manifolds``). A manifold without points changes
    nothing in a pass, so while a world has at most ``slots`` of them the passes give what they give
    over every manifold; a world with more keeps its first ``slots``. Returns (consts: ``econ``'s
    entries packed, plus per slot its body ``bid``, inverse mass and inertia ``mi``, ``ii`` and per
    point its friction ``f``; ``ln``, ``lt`` packed (2 slots,); ``idx`` (slots,) int32, each slot's
    manifold (``len(body) // 2`` where a slot is empty); ``crowded``: more manifolds than slots)."""
    n_man = len(body) // 2
    on_pt = jnp.stack(econ["on"]) > 0.5
    has = on_pt[0::2] | on_pt[1::2]  # (n_man,) the manifold has a point
    rank = jnp.cumsum(has) - 1
    slot_of = jnp.where(has & (rank < slots), rank, slots)  # ``slots``: not packed
    idx = jnp.full((slots + 1,), n_man, jnp.int32).at[slot_of].set(jnp.arange(n_man, dtype=jnp.int32))[:slots]
    crowded = jnp.sum(has) > slots

    def man(x):  # (n_man,) -> (slots,), zero in empty slots
        return jnp.concatenate([jnp.asarray(x, jnp.float32), jnp.zeros((1,), jnp.float32)])[idx]

    def pts(x):  # (2 n_man,) -> (2 slots,)
        x = jnp.concatenate([jnp.asarray(x, jnp.float32).reshape(n_man, 2), jnp.zeros((1, 2), jnp.float32)])
        return x[idx].reshape(-1)

    scalars = scalars_of
    inv_m, inv_i = np.asarray(model.inv_mass, np.float32), np.asarray(model.inv_inertia, np.float32)
    b = np.asarray(body[0::2], np.int32)
    c = {"bid": scalars(man(b.astype(np.float32))), "mi": scalars(man(inv_m[b])), "ii": scalars(man(inv_i[b])),
         "f": scalars(pts(np.asarray(friction, np.float32)))}
    for name in ("on", "nm", "tm"):
        c[name] = scalars(pts(jnp.stack(econ[name])))
    for name in ("n", "arm"):
        x, y = pts(jnp.stack([v.x for v in econ[name]])), pts(jnp.stack([v.y for v in econ[name]]))
        c[name] = tuple(V2(x[k], y[k]) for k in range(2 * slots))
    for name in ("blk", "k11", "k12", "k22", "inv"):
        c[name] = scalars(man(jnp.stack(econ[name])))
    return c, scalars(pts(ln)), scalars(pts(lt)), idx, crowded


def scalars_of(a):
    """The entries of a 1-D array as a tuple of scalars."""
    return tuple(a[k] for k in range(a.shape[0]))


def _unpack_impulses(idx, packed, n_points: int):
    """The packed slots' impulses (2 slots,) back at their points (n_points,), zero where unpacked."""
    x = jnp.zeros((n_points // 2 + 1, 2), jnp.float32).at[idx].set(jnp.stack(packed).reshape(-1, 2))
    return x[:-1].reshape(-1)


def _velocity_pass_packed(model: Model, bodies, c, carry):
    """``_velocity_pass_edges`` over packed manifold slots (``_pack_manifolds``): each slot's body is
    a per-world input (``bid``), so the slot reads that body's velocity out of ``bodies`` (the bodies
    with contacts) by selects and writes it back the same way. Per-world scalars only."""
    vel, omg, jimp, jmot, ln, lt = (list(x) for x in carry)
    _joint_velocity_pass(model, c, vel, omg, jimp, jmot)
    for q in range(len(c["bid"])):
        k1, k2 = 2 * q, 2 * q + 1
        at = [c["bid"][q] == np.float32(j) for j in bodies]
        v, w = vel[bodies[0]], omg[bodies[0]]
        for j, here in zip(bodies[1:], at[1:]):
            v, w = vel[j].where(here, v), jnp.where(here, omg[j], w)
        v, w, ln[k1], ln[k2], lt[k1], lt[k2] = _manifold_velocity(
            c, q, c["mi"][q], c["ii"][q], c["f"][k1], c["f"][k2], v, w, ln[k1], ln[k2], lt[k1], lt[k2])
        for j, here in zip(bodies, at):
            vel[j], omg[j] = v.where(here, vel[j]), jnp.where(here, w, omg[j])
    return tuple(vel), tuple(omg), tuple(jimp), tuple(jmot), tuple(ln), tuple(lt)


def _position_pass_edges(model: Model, body, c, carry):
    """One position pass with edge manifolds (b2ContactSolver::SolvePositionConstraints with
    b2PositionSolverManifold): face A, the body's clip point against the edge's fixed plane; face B,
    the edge's fixed clip point against the body's face (its normal turns with the body, the
    impulse acts along its negation); then the joints. Frozen once solved, as ``_position_pass``; a
    point no world of a kernel block touches is skipped there (``fused.when``)."""
    cfg = model.config
    inv_m, inv_i = [float(x) for x in model.inv_mass], [float(x) for x in model.inv_inertia]
    lc = np.asarray(model.local_com, np.float32)
    com0, ang0, _ = carry
    com, ang = list(com0), list(ang0)
    min_sep = jnp.zeros_like(ang[0])  # a per-world scalar, also as a branch operand in the kernel
    for k, i in enumerate(body):
        point = functools.partial(_point_position, cfg, c, k, inv_m[i], inv_i[i])
        com[i], ang[i], min_sep = fused.when(c["any"][k], point, (com[i], ang[i], min_sep), cfg.skip_untouched)
    return _joint_positions_then_freeze(model, c, lc, carry, com, ang, min_sep)


def to_position_lanes(model: Model, layout, consts):
    """The position loop of ``_position_pass_edges`` (its ``consts``) in lane form, -> (pass, consts)
    for ``fused.per_world_fori_loop(..., lanes=fused.TILE)``: per lane (body of ``layout``) its
    manifolds' points' constants as lane vectors, in the body's order; the joints' as they are. The
    carry stays per-world scalars."""
    per_lane = len(layout[0][1])
    pts = [[2 * ms[m] + q for _, ms in layout] for m in range(per_lane) for q in (0, 1)]  # [point][lane] -> point

    def lanes(values, idx):
        return jnp.stack([values[k] for k in idx], -1)

    c = {"state": consts["state"]}
    for name in ("on", "fb"):
        c[name] = tuple(lanes(consts[name], idx) for idx in pts)
    c["any"] = tuple(fused.BlockAny(lanes([f.flag for f in consts["any"]], idx)) for idx in pts)
    for name in ("a", "nrm", "pt"):
        c[name] = tuple(V2(lanes([v.x for v in consts[name]], idx), lanes([v.y for v in consts[name]], idx))
                        for idx in pts)
    mass = (tuple(float(model.inv_mass[b]) for b, _ in layout), tuple(float(model.inv_inertia[b]) for b, _ in layout))
    return functools.partial(_position_pass_lanes, model, tuple(b for b, _ in layout), mass), c


def _position_pass_lanes(model: Model, lane_bodies, mass, c, carry):
    """``_position_pass_edges`` in lane form (``to_position_lanes``): every lane's contact points at once,
    lane j on body ``lane_bodies[j]``'s pose, then the joints on per-world scalars. A point corrects
    only its own body (the ground is static) and the deepest separation is a minimum, so each lane
    does the operations Box2D's sequential order does for that body, in that order."""
    cfg = model.config
    com0, ang0, _ = carry
    com, ang = list(com0), list(ang0)
    al = fused.lanes_of(*(ang[b] for b in lane_bodies))
    state = (V2(fused.lanes_of(*(com[b].x for b in lane_bodies)), fused.lanes_of(*(com[b].y for b in lane_bodies))),
             al, jnp.zeros_like(al))
    mi, ii = fused.lanes_of(*mass[0]), fused.lanes_of(*mass[1])
    for k in range(len(c["on"])):
        point = functools.partial(_point_position, cfg, c, k, mi, ii)
        state = fused.when(c["any"][k], point, state, cfg.skip_untouched)
    cl, al, sep = state
    for j, b in enumerate(lane_bodies):
        com[b], ang[b] = V2(fused.lane(cl.x, j), fused.lane(cl.y, j)), fused.lane(al, j)
    lc = np.asarray(model.local_com, np.float32)
    return _joint_positions_then_freeze(model, c, lc, carry, com, ang, fused.lane_min(sep))


def _point_position(cfg, c, k, inv_m, inv_i, state, baumgarte=None):
    """One edge contact point's position correction -> (com, angle, deepest separation so far);
    ``baumgarte``: ``_position_impulse``'s."""
    com, ang, min_sep = state
    on, fb = c["on"][k] > 0.5, c["fb"][k] > 0.5
    sin, cos = sincos(ang)  # once for the three vectors
    ra_ = rotate_cs(cos, sin, c["a"][k])
    rn_ = rotate_cs(cos, sin, c["nrm"][k])
    rp_ = rotate_cs(cos, sin, c["pt"][k])
    ref_n = rn_.where(fb, c["nrm"][k])
    plane = (com + ra_).where(fb, c["a"][k])
    clip = c["pt"][k].where(fb, com + rp_)
    sep = (clip - plane).dot(ref_n) - cfg.contact_radius
    normal = (ref_n * -1.0).where(fb, ref_n)
    min_sep = jnp.where(on, jnp.minimum(min_sep, sep), min_sep)
    com, ang = _position_impulse(cfg, inv_m, inv_i, com, ang, clip - com, normal, sep, on, baumgarte)
    return com, ang, min_sep
