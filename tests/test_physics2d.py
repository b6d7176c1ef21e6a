"""envs.physics2d: mass properties, free fall, resting contact and sleep, friction, joints, locked solve."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.physics2d.box2d_reference import box_trajectory
from envs import physics2d
from envs.lander import model as LM

DT = 1.0 / 50.0
BOX = ((-0.5, -0.25), (0.5, -0.25), (0.5, 0.25), (-0.5, 0.25))
FLAT = jnp.asarray([[0.0, 1.0], [10.0, 1.0], [20.0, 1.0]], jnp.float32)


def box_model(friction=0.4, vi=8, pi=3):
    cfg = physics2d.SolverConfig(dt=DT, velocity_iterations=vi, position_iterations=pi)
    return physics2d.make_model(1, [physics2d.Polygon(0, BOX, density=2.0, friction=friction)], (), cfg)


def run(model, world, n, gravity=-10.0, ground=FLAT):
    def body(w, _):
        w, info = physics2d.step(model, w, ground, gravity)
        return w, (w.bodies.com, w.bodies.vel, info["touching"], w.asleep)

    return jax.lax.scan(body, world, None, length=n)


def test_lander_mass_properties_match_box2d():
    m = LM.lander_model()
    # Box2D (measured): hull mass 4.8167, GetInertia() = I about the body origin 0.83331, COM (0, 0.10131)
    np.testing.assert_allclose(m.mass, [4.8166667, 0.0711111, 0.0711111], rtol=1e-5)
    np.testing.assert_allclose(m.local_com[0], [0.0, 0.1013072], atol=1e-6)
    i_origin = m.inertia + m.mass * np.sum(m.local_com**2, 1)
    np.testing.assert_allclose(i_origin, [0.83331, 0.0017909, 0.0017909], rtol=1e-4)


def test_bad_models_raise():
    with pytest.raises(ValueError, match="counter-clockwise"):
        physics2d.polygon_mass(np.asarray(BOX[::-1]), 1.0)
    with pytest.raises(ValueError, match="body index"):
        physics2d.make_model(1, [physics2d.Polygon(1, BOX, 1.0, 0.1)])
    with pytest.raises(ValueError, match="velocity_iterations"):
        physics2d.SolverConfig(velocity_iterations=0)


def test_free_fall_is_semi_implicit_euler_exactly():
    m = box_model()
    w = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[5.0, 10.0]], [0.0]))
    n = 20
    w, (com, vel, touching, _) = run(m, w, n, gravity=-7.0)
    k = np.arange(1, n + 1)
    np.testing.assert_allclose(vel[:, 0, 1], -7.0 * DT * k, rtol=1e-5)
    np.testing.assert_allclose(com[:, 0, 1], 10.0 - 7.0 * DT**2 * k * (k + 1) / 2, rtol=1e-5)
    assert not np.any(touching)


def test_box_comes_to_rest_on_ground_and_sleeps():
    m = box_model()
    w = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[5.0, 1.5]], [0.0]))
    w, (com, vel, touching, asleep) = run(m, w, 120)
    # resting separation: Box2D keeps radius - slop = 0.015 between the core shapes
    bottom = float(com[-1, 0, 1]) - 0.25
    assert abs(bottom - 1.0 - 0.015) < 0.004
    assert np.all(touching[-1, :2]) and not np.any(touching[-1, 2:])
    # warm-started normal impulses carry the weight: sum = m g dt
    np.testing.assert_allclose(float(jnp.sum(w.normal_impulse)), 2.0 * 0.5 * 10.0 * DT, rtol=1e-3)
    first = int(np.argmax(asleep))
    assert asleep[first] and 25 <= first < 80  # 0.5 s below the sleep tolerances after settling


def test_friction_decelerates_a_sliding_box_at_mu_g():
    m = box_model(friction=0.4)
    mu = np.sqrt(0.4 * 0.1)  # Box2D mixing with the ground's friction 0.1
    b = physics2d.bodies_from_origin(m, [[3.0, 1.0 + 0.25 + 0.015]], [0.0], vel=[[2.0, 0.0]])
    w = physics2d.init_world(m, b)
    w, (com, vel, _, _) = run(m, w, 30)
    dv = np.diff(np.asarray(vel[5:25, 0, 0]))
    np.testing.assert_allclose(dv, -mu * 10.0 * DT, rtol=0.02)


def pendulum_model(**joint):
    cfg = physics2d.SolverConfig(dt=DT, velocity_iterations=20, position_iterations=5)
    polys = [physics2d.Polygon(0, BOX, 1.0, 0.1, sensor=True), physics2d.Polygon(1, BOX, 1.0, 0.1, sensor=True)]
    j = physics2d.RevoluteJoint(0, 1, (0.5, 0.0), (-0.5, 0.0), **joint)
    return physics2d.make_model(2, polys, (j,), cfg)


def test_revolute_joint_keeps_anchors_together_and_conserves_momentum():
    m = pendulum_model()
    b = physics2d.bodies_from_origin(m, [[5.0, 5.0], [6.0, 5.0]], [0.0, 0.0], vel=[[0.0, 1.0], [0.0, -1.0]])
    w = physics2d.init_world(m, b)
    step = jax.jit(lambda w: physics2d.step(m, w, FLAT, 0.0)[0])
    for _ in range(30):
        w = step(w)
        bb = w.bodies
        a = bb.com[0] + physics2d.world.rotate(bb.angle[0], jnp.asarray([0.5, 0.0]))
        c = bb.com[1] + physics2d.world.rotate(bb.angle[1], jnp.asarray([-0.5, 0.0]))
        assert float(jnp.linalg.norm(a - c)) < 2e-3
    np.testing.assert_allclose(np.sum(np.asarray(w.bodies.vel), 0), [0.0, 0.0], atol=1e-4)  # equal masses
    assert float(jnp.abs(w.bodies.omega[0])) > 0.1  # the pair spins


def test_motor_reaches_target_speed_and_limit_stops_it():
    m = pendulum_model(enable_motor=True, motor_speed=1.0, max_motor_torque=50.0)
    w = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[5.0, 5.0], [6.0, 5.0]], [0.0, 0.0]))
    w, _ = run(m, w, 5, gravity=0.0)
    np.testing.assert_allclose(float(w.bodies.omega[1] - w.bodies.omega[0]), 1.0, rtol=1e-3)
    m = pendulum_model(enable_motor=True, motor_speed=1.0, max_motor_torque=50.0, enable_limit=True,
                       lower=-0.2, upper=0.3)
    w = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[5.0, 5.0], [6.0, 5.0]], [0.0, 0.0]))
    w, _ = run(m, w, 40, gravity=0.0)
    rel = float(w.bodies.angle[1] - w.bodies.angle[0])
    assert 0.3 - 1e-3 < rel < 0.3 + 2.0 / 180 * np.pi + 1e-3  # held at the upper limit (within slop)
    assert abs(float(w.bodies.omega[1] - w.bodies.omega[0])) < 1e-3


def test_locked_projector_is_a_momentum_preserving_projection():
    m = LM.lander_model()
    pos, ang = LM.initial_pose()
    b = physics2d.bodies_from_origin(m, pos, ang)
    p = physics2d.locked_velocity_projector(m, np.asarray(b.com), np.asarray(b.angle))
    np.testing.assert_allclose(p @ p, p, atol=1e-9)  # a projection
    v = np.random.default_rng(0).normal(size=9)
    u = p @ v
    mass = np.repeat(m.mass, 2)
    lin = lambda x: np.stack([np.sum(m.mass * x[0::3]), np.sum(m.mass * x[1::3])])
    np.testing.assert_allclose(lin(u), lin(v), rtol=1e-9, atol=1e-9)
    assert mass.shape == (6,)
    np.testing.assert_allclose(u[2::3], u[2], atol=1e-9)  # all bodies spin together


def test_step_vmaps_over_worlds_and_gravity():
    m = box_model()
    b = physics2d.bodies_from_origin(m, [[5.0, 10.0]], [0.0])
    w = physics2d.init_world(m, b)
    ws = jax.tree_util.tree_map(lambda x: jnp.stack([x] * 3), w)
    g = jnp.asarray([-1.0, -5.0, -11.0])
    out, _ = jax.vmap(lambda w, g: physics2d.step(m, w, FLAT, g))(ws, g)
    np.testing.assert_allclose(out.bodies.vel[:, 0, 1], g * DT, rtol=1e-6)


def test_vertex_segment_touching_ignores_far_points_below_steep_segment_lines():
    from envs.physics2d.collision import vertex_segment_touching

    ground = jnp.asarray([[0.0, 0.0], [2.0, 0.0], [4.0, 5.0]], jnp.float32)  # flat, then steep
    pts = jnp.asarray([[1.0, 0.01], [1.0, 0.5], [10.0, 3.0], [3.0, 2.0]], jnp.float32)
    t = np.asarray(vertex_segment_touching(pts, ground, 0.02))
    # near the flat one; clear of both; far right (below the steep line's extension, not touching);
    # under the steep segment itself (penetrating)
    np.testing.assert_array_equal(t, [[True, False], [False, False], [False, False], [False, True]])


@pytest.mark.optimized  # bitwise: two programs
def test_free_flight_step_equals_full_step_for_the_landers_reset():
    """The lander's reset step skips collision (free_flight); it must give exactly the full step's result.

    Terrain from the lander's own generator, plus the worst case (every height at its maximum of
    0.99 H/2); pushes up to Gymnasium's INITIAL_RANDOM, every gravity and wind in range.
    """
    from envs.lander import env as LE

    m = LM.lander_model()
    pos, ang = LM.initial_pose()
    world = physics2d.init_world(m, physics2d.bodies_from_origin(m, pos, ang))
    proj = LM.reset_projector()
    n = 64
    keys = jax.random.split(jax.random.PRNGKey(3), n)
    heights = jax.vmap(LE.terrain)(keys).at[:2].set(0.99 * LM.H / 2)
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(4), 3)
    push = jax.random.uniform(k1, (n, 2), jnp.float32, -LM.INITIAL_RANDOM, LM.INITIAL_RANDOM)
    # worst cases: highest terrain with the strongest push down (and sideways), at the strongest gravity
    push = push.at[0].set(jnp.asarray([-LM.INITIAL_RANDOM, -LM.INITIAL_RANDOM]))
    push = push.at[1].set(jnp.asarray([LM.INITIAL_RANDOM, -LM.INITIAL_RANDOM]))
    gravity = jax.random.uniform(k2, (n,), jnp.float32, -12.0, 0.0).at[:2].set(-12.0)
    wind = jax.random.uniform(k3, (n, 2), jnp.float32, -20.0, 20.0)

    def one(h, p, g, w, free):
        ground = jnp.stack([jnp.asarray(LM.CHUNK_X), h], -1)
        force = jnp.zeros((3, 2), jnp.float32).at[0].set(p + jnp.stack([w[0], 0.0]))
        torque = jnp.zeros((3,), jnp.float32).at[0].set(w[1] / 10.0)
        return physics2d.step(m, world, ground, g, force, torque, projector=proj,
                              position_iterations=LM.RESET_POSITION_ITERATIONS, free_flight=free)

    full = jax.jit(jax.vmap(lambda *a: one(*a, False)))(heights, push, gravity, wind)
    free = jax.jit(jax.vmap(lambda *a: one(*a, True)))(heights, push, gravity, wind)
    assert not np.any(np.asarray(full[1]["touching"]))  # the premise: nothing can touch at creation
    for a, b in zip(jax.tree_util.tree_leaves(full), jax.tree_util.tree_leaves(free)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_vertex_vs_polyline_selects_the_segment_below_exactly():
    """The masked-sum selection returns the very normal and start point of the segment below (no rounding)."""
    from envs.physics2d.collision import segment_frames, vertex_vs_polyline

    rng = np.random.default_rng(5)
    xs = np.sort(rng.uniform(0.0, 20.0, 12)).astype(np.float32)
    ground = jnp.asarray(np.stack([xs, rng.uniform(0.0, 7.0, 12).astype(np.float32)], -1))
    pts = jnp.asarray(np.stack([rng.uniform(-1.0, 21.0, 200), rng.uniform(0.0, 9.0, 200)], -1).astype(np.float32))
    sep, n, q, inside = vertex_vs_polyline(pts, ground)
    p0, normal, _, _ = segment_frames(ground)
    seg = np.clip(np.searchsorted(xs, np.asarray(pts[:, 0]), side="right") - 1, 0, len(xs) - 2)
    ok = (np.asarray(pts[:, 0]) >= xs[0]) & (np.asarray(pts[:, 0]) <= xs[-1])
    np.testing.assert_array_equal(np.asarray(inside), ok)
    np.testing.assert_array_equal(np.asarray(n)[ok], np.asarray(normal)[seg[ok]])
    np.testing.assert_array_equal(np.asarray(q)[ok], np.asarray(p0)[seg[ok]])
    np.testing.assert_array_equal(np.asarray(n)[~ok], 0.0)
    assert np.all(np.isinf(np.asarray(sep)[~ok]))


def test_polyline_points_in_polygon_against_numpy():
    """The hull-sensor test: a terrain point within ``radius`` of the inside of a convex polygon."""
    from envs.physics2d.collision import polyline_points_in_polygon

    square = np.asarray([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], np.float32)  # CCW
    rng = np.random.default_rng(6)
    for _ in range(50):
        ground = np.stack([np.sort(rng.uniform(-2, 3, 5)), rng.uniform(-1, 2, 5)], -1).astype(np.float32)
        radius = 0.05
        # numpy reference: signed distance to each face's outward normal; inside if every one <= radius
        inside = np.all([(ground - square[f]) @ np.asarray([e[1], -e[0]]) / np.hypot(*e) <= radius
                         for f, e in enumerate(np.roll(square, -1, 0) - square)], axis=0)
        got = bool(polyline_points_in_polygon(jnp.asarray(ground), jnp.asarray(square), radius))
        assert got == bool(inside.any())
    hit = jnp.asarray([[-1.0, 0.0], [0.5, 0.5], [2.0, 0.0]], jnp.float32)  # a peak inside the square
    miss = jnp.asarray([[-1.0, 0.0], [0.5, -0.2], [2.0, 0.0]], jnp.float32)
    assert bool(polyline_points_in_polygon(hit, jnp.asarray(square), 0.01))
    assert not bool(polyline_points_in_polygon(miss, jnp.asarray(square), 0.01))


def test_lander_step_has_no_reduced_precision_matrix_product():
    """On GPUs a float32 dot at default precision is TF32; the lander's only dot is the reset's
    locked-joint projection, at HIGHEST (contact selection is masked sums, docs/log/benchmarks.md "Exact contact selection and a free-flight reset")."""
    import re

    import envs

    env = envs.make("lander")
    s = env.reset(jax.random.PRNGKey(0), env.default_params)[1]
    text = jax.jit(env.step).lower(jax.random.PRNGKey(1), s, jnp.int32(2), env.default_params).as_text()
    found = re.findall(r"dot_general.*?precision = \[(\w+), (\w+)\]", text)
    assert found and all(p == ("HIGHEST", "HIGHEST") for p in found), found
    assert len(re.findall(r"dot_general", text)) == len(found)  # every dot states its precision


def test_time_of_impact_position_passes_leave_box2ds_resting_distance():
    """A box hitting the ground within one step stops at the time of impact: at the TOI target
    (0.005 m) without position passes; with Box2D's TOI passes (Baumgarte 0.75 until separation
    >= -1.5 slop) pushed out to between radius - 2.5 slop and radius - slop (0.0075..0.015 m)."""
    out = []
    for n in (0, 20):
        cfg = physics2d.SolverConfig(dt=DT, toi_position_iterations=n, toi_loop=n > 0)
        m = physics2d.make_model(1, [physics2d.Polygon(0, BOX, density=2.0, friction=0.4)], (), cfg)
        b = physics2d.bodies_from_origin(m, [[5.0, 1.0 + 0.25 + 0.1]], [0.0], vel=[[0.0, -10.0]])
        w, info = jax.jit(lambda w: physics2d.step(m, w, FLAT, 0.0))(physics2d.init_world(m, b))
        out.append(float(w.bodies.com[0, 1]) - 0.25 - 1.0)
        assert bool(info["polygon_touching"][0]) and abs(float(w.bodies.vel[0, 1])) < 0.1  # from 10 m/s, 4 TOI passes
        assert abs(float(w.bodies.angle[0])) < 5e-3  # sequential vertex passes tilt it slightly
    assert abs(out[0] - 0.005) < 1e-3, out  # (less the residual speed over the rest of the step)
    assert 0.0075 - 1e-4 <= out[1] <= 0.015 + 1e-4, out


def test_time_of_impact_moves_each_body_as_if_alone():
    """The time of impact runs on all bodies at once (slots padded to the largest polygon): in one world,
    a box and a triangle (fewer slots) that both hit the ground within the step and a triangle that
    does not end where each ends alone in its own world (to rounding), in any body order; the hitting
    bodies are stopped by their time of impact, the free one falls freely. "To rounding": each body's
    passes run on its own scalars, which XLA:CPU compiles differently for one body and for three (at
    the suite's optimisation level the triangle's spin differed by 3e-6 of 1.08)."""
    cfg = physics2d.SolverConfig(dt=DT, toi_position_iterations=20, toi_loop=True)
    tri = ((-0.4, -0.2), (0.4, -0.2), (0.0, 0.3))
    shapes = {"box": (BOX, [2.0, 1.35], [0.0, -10.0], 0.0), "tri": (tri, [6.0, 1.3], [0.0, -12.0], 0.0),
              "free": (tri, [12.0, 4.0], [0.5, -3.0], 0.2)}

    def end(names):
        polys = [physics2d.Polygon(i, shapes[n][0], density=2.0, friction=0.4) for i, n in enumerate(names)]
        m = physics2d.make_model(len(names), polys, (), cfg)
        b = physics2d.bodies_from_origin(m, [shapes[n][1] for n in names], [shapes[n][3] for n in names],
                                         vel=[shapes[n][2] for n in names])
        w, info = jax.jit(lambda w: physics2d.step(m, w, FLAT, -10.0))(physics2d.init_world(m, b))
        rows = {n: np.concatenate([w.bodies.com[i], w.bodies.vel[i], w.bodies.angle[i:i + 1], w.bodies.omega[i:i + 1]])
                for i, n in enumerate(names)}
        return rows, np.asarray(info["polygon_touching"])

    alone = {n: end([n])[0][n] for n in shapes}
    for names in (["box", "tri", "free"], ["free", "tri", "box"], ["tri", "free", "box"]):
        rows, touching = end(names)
        assert touching.tolist() == [n != "free" for n in names]
        for n in names:
            np.testing.assert_allclose(rows[n], alone[n], rtol=0, atol=1e-5)
    assert abs(alone["box"][3]) < 0.1 and abs(alone["tri"][3]) < 1.0  # from 10 and 12 m/s: stopped at impact
    np.testing.assert_allclose(alone["free"][2:4], [0.5, -3.0 - 10.0 * DT], atol=1e-5)  # free fall, no contact


def test_tilted_box_landing_on_its_corner_follows_box2d():
    """A walker shin (Gymnasium's lower-leg box) tilted 0.3 rad, 2 mm above the ground, sliding at
    1 m/s: with Box2D's time-of-impact rules (touching at t = 0 within the target, the TOI position
    passes) our trajectory follows pybox2d's (Gymnasium's Box2D) step for step; without the first
    rule the box stays 6 mm lower and drifts off within 20 steps."""
    b2 = pytest.importorskip("Box2D")
    hx, hy, ang0 = 0.8 * 8 / 30 / 2, 34 / 30 / 2, 0.3
    y0 = 0.302 + hy * np.cos(ang0) + hx * np.sin(ang0)
    ref = box_trajectory(b2, [((0, 0.3), (10, 0.3))], (5, y0), ang0, (hx, hy))
    box = ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))
    ground = jnp.asarray([[0.0, 0.3], [5.0, 0.3], [10.0, 0.3]], jnp.float32)
    out = {}
    for touching in (True, False):
        cfg = physics2d.SolverConfig(dt=1 / 50, velocity_iterations=180, position_iterations=60, ground_friction=2.5,
                                     toi_loop=True, toi_position_iterations=20, toi_from_touching=touching)
        m = physics2d.make_model(1, [physics2d.Polygon(0, box, 1.0, 0.2)], (), cfg)
        w = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[5.0, y0]], [ang0], vel=[[1.0, 0.0]]))

        def body_fn(w, _, m=m):
            w, _ = physics2d.step(m, w, ground, -10.0)
            return w, jnp.concatenate([w.bodies.com[0], w.bodies.angle[:1]])

        out[touching] = np.asarray(jax.jit(lambda w, f=body_fn: jax.lax.scan(f, w, None, length=20)[1])(w))
    np.testing.assert_allclose(out[True][:5], ref[:5], atol=1e-3)
    np.testing.assert_allclose(out[True], ref, atol=1e-2)
    assert abs(out[False][0, 1] - ref[0, 1]) > 5e-3  # the old rule: 6 mm low after the first step
