"""envs.physics2d.polygon: Box2D 2.3.0's polygon-vs-polygon manifold (a static box against a moving
polygon), by hand and against pybox2d (Gymnasium's Box2D) where it is installed."""
import jax.numpy as jnp
import numpy as np
import pytest

from envs.physics2d import edge as E
from envs.physics2d import polygon as PG

SHIN = (0.8 * 8 / 30 / 2, 34 / 30 / 2)  # Gymnasium's lower-leg half sizes
STUMP = (1.0, 1.4667, 0.0, 0.4667)  # (x0, x1, y0, y1): a one-step stump


def manifold(box, hx, hy, pos, ang):
    """Our manifold of the static ``box`` (A) and a (2 hx x 2 hy) box at ``pos`` / ``ang`` (B), numpy dict."""
    b = np.array([(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)])
    c, s = np.cos(ang), np.sin(ang)
    rot = np.array([[c, -s], [s, c]])
    f = lambda a: jnp.asarray(a, jnp.float32)
    av, an, ac = PG.box_polygon(f(box))
    m = PG.polygon_polygon_manifold(av, an, ac, f(b @ rot.T + np.asarray(pos)), f(E.polygon_normals(b) @ rot.T),
                                    f(pos), 0.02)
    return {k: np.asarray(v) for k, v in m.items()}


def test_box_polygon_has_box2ds_hull_order():
    v, n, c = (np.asarray(a) for a in PG.box_polygon(jnp.asarray(STUMP, jnp.float32)))
    np.testing.assert_allclose(v, [[1.4667, 0.0], [1.4667, 0.4667], [1.0, 0.4667], [1.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(n, [[1, 0], [0, 1], [-1, 0], [0, -1]])
    np.testing.assert_allclose(n, E.polygon_normals(v), atol=1e-6)  # outward, face i = v_i -> v_i+1
    np.testing.assert_allclose(c, [1.23335, 0.23335], atol=1e-6)


def test_foot_flat_on_a_stump_top_gives_two_face_a_points():
    # a shin upright over the stump's top, its bottom face 0.005 above it: the stump's top face (A's
    # face 1) is the reference, both bottom corners are points, separation 0.005 - 0.02, each
    # contact point midway between the skins (0.005 / 2 below the corner)
    hx, hy = SHIN
    m = manifold(STUMP, hx, hy, (1.2, 0.4667 + hy + 0.005), 0.0)
    assert m["on"].tolist() == [True, True] and not m["face_b"]
    np.testing.assert_allclose(m["normal"], [0.0, 1.0], atol=1e-7)
    np.testing.assert_allclose(m["clip"], [[1.2 - hx, 0.4717], [1.2 + hx, 0.4717]], atol=1e-5)
    np.testing.assert_allclose(m["separation"], [-0.015, -0.015], atol=1e-5)
    np.testing.assert_allclose(m["point"], [[1.2 - hx, 0.4692], [1.2 + hx, 0.4692]], atol=1e-5)
    # features: A's face 1 against B's vertices 0 and 1 (b2ContactFeature (1, i, face, vertex))
    assert m["id"].tolist() == [1 + 256 * 0 + 65536, 1 + 256 * 1 + 65536]


def test_shin_against_the_stump_side_and_clear_of_it():
    hx, hy = SHIN
    # upright shin pressed 0.01 into the stump's left face: normal -x (from the stump to the shin)
    m = manifold(STUMP, hx, hy, (1.0 - hx + 0.01, 0.3), 0.0)
    assert m["on"].tolist() == [True, True]
    np.testing.assert_allclose(m["normal"], [-1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(m["separation"], [-0.03, -0.03], atol=1e-5)
    # the shin's lower half overlaps the stump's height; the points are its right face, clipped to the
    # stump's side plane (y <= 0.4667 + skin) and the bottom (y >= -skin)
    assert m["clip"][:, 1].min() >= -0.02 - 1e-6 and m["clip"][:, 1].max() <= 0.4667 + 0.02 + 1e-6
    assert not manifold(STUMP, hx, hy, (1.0 - hx - 0.021, 0.3), 0.0)["on"].any()  # beyond the skin
    assert manifold(STUMP, hx, hy, (1.0 - hx - 0.019, 0.3), 0.0)["on"].all()  # within it


def test_tilted_shin_on_the_stump_corner_uses_its_own_face():
    # a shin tilted 0.6 rad with its bottom face resting on the stump's top-left corner: the shin's
    # face separates more than any of the stump's, so its face is the reference (face B), the normal
    # is minus its bottom face's and the one point is the stump's corner
    hx, hy = SHIN
    ang = 0.6
    down = np.array([np.sin(ang), -np.cos(ang)])  # the shin's bottom-face normal
    pos = np.array([1.0, 0.4667]) - (hy - 0.005) * down
    m = manifold(STUMP, hx, hy, pos, ang)
    assert m["face_b"] and m["on"].tolist() == [True, False]
    np.testing.assert_allclose(m["normal"], -down, atol=1e-5)
    np.testing.assert_allclose(m["clip"][0], [1.0, 0.4667], atol=1e-6)


def box2d_manifold(b2, box, hx, hy, pos, ang):
    """pybox2d's manifold of a static box fixture (A) and a dynamic box after a zero-length step."""
    world = b2.b2World(gravity=(0, -10))
    x0, x1, y0, y1 = box
    world.CreateStaticBody(fixtures=b2.b2FixtureDef(shape=b2.b2PolygonShape(vertices=[(x0, y0), (x1, y0), (x1, y1), (x0, y1)])))
    world.CreateDynamicBody(position=tuple(pos), angle=ang,
                            fixtures=b2.b2FixtureDef(shape=b2.b2PolygonShape(box=(hx, hy)), density=1.0))
    world.Step(0.0, 1, 1)
    for c in world.contacts:
        assert c.fixtureA.body.type == b2.b2_staticBody
        m, wm = c.manifold, c.worldManifold
        n = m.pointCount
        return (n, np.asarray(wm.normal), np.asarray([tuple(wm.points[i]) for i in range(n)]),
                [m.points[i].id.key for i in range(n)], m.type_ == b2.b2Manifold.e_faceB)
    return 0, None, None, None, None


def test_manifolds_match_pybox2d_around_a_stump():
    """Random shin poses around and inside a stump: point count, normal, points, feature ids and the
    reference face as Box2D's (the hysteresis and face search are Box2D 2.3.0's, which pybox2d builds)."""
    b2 = pytest.importorskip("Box2D")
    hx, hy = SHIN
    rng = np.random.default_rng(0)
    checked = {False: 0, True: 0}
    for _ in range(300):
        ang = rng.uniform(-np.pi, np.pi)
        pos = np.array([rng.uniform(0.4, 2.1), rng.uniform(-0.3, 1.2)])
        n, normal, points, ids, face_b = box2d_manifold(b2, STUMP, hx, hy, pos, ang)
        m = manifold(STUMP, hx, hy, pos, ang)
        assert int(m["on"].sum()) == n, (pos, ang)
        if n:
            checked[face_b] += 1
            assert bool(m["face_b"]) == face_b, (pos, ang)
            np.testing.assert_allclose(m["normal"], normal, atol=1e-5)
            np.testing.assert_allclose(m["point"][:n], points, atol=1e-5)
            assert m["id"][:n].tolist() == ids
    assert checked[False] > 30 and checked[True] > 30


def test_shin_tipping_over_a_stump_corner_follows_box2d():
    """Gymnasium's shin tilted 0.3 rad, sliding at 1 m/s on flat ground into a one-step stump: its top
    corner hits the stump's face and it stands up against it. With the stump as a Box2D polygon
    (``step(boxes=...)``) our trajectory follows pybox2d's to 1e-3 m / rad over 40 steps (2.4e-4 seen;
    without the stump it slides on past x = 1 and falls, 0.7 off)."""
    b2 = pytest.importorskip("Box2D")
    import jax

    from envs.physics2d.box2d_reference import box_trajectory
    from envs import physics2d

    hx, hy = SHIN
    ang0 = 0.3
    y0 = 0.002 + hy * np.cos(ang0) + hx * np.sin(ang0)
    stump = (1.0, 1.4667, 0.0, 0.4667)
    edges = [((-2.0, 0.0), (1.0, 0.0)), ((1.0, 0.0), (1.4667, 0.0)), ((1.4667, 0.0), (4.0, 0.0))]
    ref = box_trajectory(b2, edges, (0.7, y0), ang0, (hx, hy), steps=40, boxes=[stump])
    ground = jnp.asarray([edges[0][0]] + [e[1] for e in edges], jnp.float32)
    box = ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))
    cfg = physics2d.SolverConfig(dt=1 / 50, velocity_iterations=180, position_iterations=60, ground_friction=2.5,
                                 toi_loop=True, toi_position_iterations=20, toi_from_touching=True, edge_contacts=2)
    m = physics2d.make_model(1, [physics2d.Polygon(0, box, 1.0, 0.2)], (), cfg)
    w = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[0.7, y0]], [ang0], vel=[[1.0, 0.0]]))
    boxes, ok = jnp.asarray([stump], jnp.float32), jnp.asarray([True])

    def body_fn(w, _):
        w, info = physics2d.step(m, w, ground, -10.0, boxes=boxes, box_valid=ok)
        return w, (jnp.concatenate([physics2d.body_origin(m, w.bodies)[0], w.bodies.angle[:1]]), info["box_touching"][0, 0])

    out, touched = jax.jit(lambda w: jax.lax.scan(body_fn, w, None, length=40)[1])(w)
    assert bool(jnp.any(touched))  # the stump was hit
    assert ref[-1, 0] + hx < 1.0 and abs(ref[-1, 2]) < 0.01  # in Box2D: stopped by its face, upright
    np.testing.assert_allclose(np.asarray(out), ref, atol=1e-3)
