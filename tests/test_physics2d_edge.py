"""envs.physics2d.edge: Box2D 2.3's edge-vs-polygon manifold for lone edges, and the solver with it.

Hand-computed cases (a box flat on an edge, hanging over an edge's end, clear of it) and, where
pybox2d (Gymnasium's Box2D) is installed, the manifolds and a short trajectory against Box2D itself.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.physics2d.box2d_reference import box_trajectory
from envs import physics2d
from envs.physics2d import edge as E

FACE_A_KEY0, FACE_A_KEY1 = 65536, 65792  # b2ContactFeature (0, i, face, vertex) of polygon vertices 0 and 1
SHIN = (0.8 * 8 / 30 / 2, 34 / 30 / 2)  # Gymnasium's lower-leg half sizes


def manifold(e1, e2, hx, hy, pos, ang):
    """Our manifold of a (2 hx x 2 hy) box at ``pos`` / ``ang`` against the edge e1 -> e2 (numpy dict)."""
    box = np.array([(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)])
    c, s = np.cos(ang), np.sin(ang)
    rot = np.array([[c, -s], [s, c]])
    f = lambda a: jnp.asarray(a, jnp.float32)
    m = E.edge_polygon_manifold(f(e1), f(e2), f(box @ rot.T + np.asarray(pos)), f(E.polygon_normals(box) @ rot.T),
                                f(pos), 0.02)
    return {k: np.asarray(v) for k, v in m.items()}


def box2d_manifolds(b2, edges, hx, hy, pos, ang):
    """pybox2d's manifold of each edge (a separate static edge fixture) with a dynamic box, after a
    zero-length step (contacts found and collided, nothing moved): {edge index: (count, normal, points, ids)}."""
    world = b2.b2World(gravity=(0, -10))
    for e in edges:
        world.CreateStaticBody(fixtures=b2.b2FixtureDef(shape=b2.b2EdgeShape(vertices=[tuple(e[0]), tuple(e[1])])))
    world.CreateDynamicBody(position=tuple(pos), angle=ang,
                            fixtures=b2.b2FixtureDef(shape=b2.b2PolygonShape(box=(hx, hy)), density=1.0))
    world.Step(0.0, 1, 1)
    out = {}
    for c in world.contacts:
        v = [tuple(x) for x in c.fixtureA.shape.vertices]
        k = [i for i, e in enumerate(edges) if np.allclose(v, e)][0]
        m, wm = c.manifold, c.worldManifold
        n = m.pointCount
        out[k] = (n, np.asarray(wm.normal), np.asarray([tuple(wm.points[i]) for i in range(n)]),
                  [m.points[i].id.key for i in range(n)])
    return out


def test_box_flat_on_one_edge_gives_two_face_a_points():
    # bottom face 0.01 above the edge: normal up, both bottom corners, separation 0.01 - 0.02 skin
    m = manifold((-2.0, 0.0), (2.0, 0.0), 0.5, 0.25, (0.3, 0.26), 0.0)
    assert m["on"].tolist() == [True, True] and not m["face_b"]
    np.testing.assert_allclose(m["normal"], [0.0, 1.0], atol=1e-7)
    np.testing.assert_allclose(m["clip"], [[-0.2, 0.01], [0.8, 0.01]], atol=1e-6)
    np.testing.assert_allclose(m["separation"], [-0.01, -0.01], atol=1e-6)
    np.testing.assert_allclose(m["point"], [[-0.2, 0.005], [0.8, 0.005]], atol=1e-6)  # midway between skins
    assert m["id"].tolist() == [FACE_A_KEY0, FACE_A_KEY1]


def test_box_over_the_end_of_an_edge_is_clipped_there():
    # the box spans x 0.7 .. 1.7 over an edge ending at x = 1: its second point is clipped to the end
    m = manifold((0.0, 0.0), (1.0, 0.0), 0.5, 0.25, (1.2, 0.26), 0.0)
    assert m["on"].tolist() == [True, True] and not m["face_b"]
    np.testing.assert_allclose(m["clip"], [[0.7, 0.01], [1.0, 0.01]], atol=1e-6)
    # the clipped point: A's vertex 1 (the edge's end) against B's face 0 (b2ClipSegmentToLine's id)
    assert m["id"].tolist() == [FACE_A_KEY0, 1 + 16777216]


def test_box_clear_of_the_edge_has_no_points():
    assert not manifold((0.0, 0.0), (1.0, 0.0), 0.5, 0.25, (0.5, 0.25 + 0.021), 0.0)["on"].any()  # above the skin
    assert not manifold((0.0, 0.0), (1.0, 0.0), 0.5, 0.25, (1.6, 0.25), 0.0)["on"].any()  # past the edge's end
    assert manifold((0.0, 0.0), (1.0, 0.0), 0.5, 0.25, (0.5, 0.25 + 0.019), 0.0)["on"].all()  # within the skin


def test_tilted_shin_over_a_junction_gets_box2ds_face_b_contact():
    """A shin tilted 0.1 rad across the junction of two separate edges (Gymnasium's grass): with the
    first edge the edge is the reference face (normal up, one point clipped at the junction); with the
    second the shin's own bottom face is (normal = minus its face normal, tilted 0.1 rad) and the first
    point is the edge's start vertex."""
    hx, hy = SHIN
    a = manifold((0.0, 0.0), (1.0, 0.0), hx, hy, (1.0, hy - 0.007), 0.1)
    b = manifold((1.0, 0.0), (2.0, 0.0), hx, hy, (1.0, hy - 0.007), 0.1)
    assert not a["face_b"] and a["on"].all()
    np.testing.assert_allclose(a["normal"], [0.0, 1.0], atol=1e-7)
    np.testing.assert_allclose(a["clip"][1, 0], 1.0, atol=1e-6)
    assert b["face_b"] and b["on"].all()
    np.testing.assert_allclose(b["normal"], [-np.sin(0.1), np.cos(0.1)], atol=1e-6)
    np.testing.assert_allclose(b["clip"][0], [1.0, 0.0], atol=1e-7)
    assert b["clip"][1, 1] == 0.0 and b["clip"][1, 0] > 1.0  # clipped by the shin's side, on the edge


def test_manifolds_match_pybox2d_near_a_junction():
    b2 = pytest.importorskip("Box2D")
    hx, hy = SHIN
    edges = [((0.0, 0.0), (0.4667, 0.0)), ((0.4667, 0.0), (0.9333, 0.05)), ((0.9333, 0.05), (1.4, 0.05))]
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(40):
        ang = rng.uniform(-0.8, 0.8)
        x = rng.uniform(0.3, 1.1)
        lowest = hy * np.cos(ang) + hx * abs(np.sin(ang))
        pos = (x, lowest + rng.uniform(-0.03, 0.05))
        ref = box2d_manifolds(b2, edges, hx, hy, pos, ang)
        for k, e in enumerate(edges):
            m = manifold(e[0], e[1], hx, hy, pos, ang)
            n, normal, points, ids = ref.get(k, (0, None, None, None))
            assert int(m["on"].sum()) == n, (k, pos, ang)
            if n:
                checked += 1
                np.testing.assert_allclose(m["normal"], normal, atol=1e-5)
                np.testing.assert_allclose(m["point"][:n], points, atol=1e-5)
                assert m["id"][:n].tolist() == ids
    assert checked > 20


def test_sliding_shin_across_junctions_follows_box2d():
    """Gymnasium's shin tilted 0.3 rad, 2 mm above ground made of separate edges, sliding at 1 m/s
    across two junctions and rocking onto its other corner: with edge manifolds our trajectory follows
    pybox2d's to 1e-3 m / rad for 20 steps; the vertex model misses the junction contacts (8e-3 rad off
    within 5 steps)."""
    b2 = pytest.importorskip("Box2D")
    hx, hy = SHIN
    ang0 = 0.3
    y0 = 0.302 + hy * np.cos(ang0) + hx * np.sin(ang0)
    edges = [((0.0, 0.3), (4.9, 0.3)), ((4.9, 0.3), (5.367, 0.3)), ((5.367, 0.3), (10.0, 0.3))]
    ref = box_trajectory(b2, edges, (4.8, y0), ang0, (hx, hy))
    ground = jnp.asarray([edges[0][0]] + [e[1] for e in edges], jnp.float32)
    box = ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))
    out = {}
    for k in (0, 2):
        cfg = physics2d.SolverConfig(dt=1 / 50, velocity_iterations=180, position_iterations=60, ground_friction=2.5,
                                     toi_loop=True, toi_position_iterations=20, toi_from_touching=True, edge_contacts=k)
        m = physics2d.make_model(1, [physics2d.Polygon(0, box, 1.0, 0.2)], (), cfg)
        w = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[4.8, y0]], [ang0], vel=[[1.0, 0.0]]))

        def body_fn(w, _, m=m):
            w, _ = physics2d.step(m, w, ground, -10.0)
            return w, jnp.concatenate([physics2d.body_origin(m, w.bodies)[0], w.bodies.angle[:1]])

        out[k] = np.asarray(jax.jit(lambda w, f=body_fn: jax.lax.scan(f, w, None, length=20)[1])(w))
    np.testing.assert_allclose(out[2], ref, atol=1e-3)
    assert np.abs(out[0][:5] - ref[:5]).max() > 5e-3


@pytest.mark.parametrize("touching", [[1, 4, 5, 6], [2], []])
def test_select_edges_keeps_the_first_touching_edges_in_order_exactly(touching):
    """The first ``count`` edges with points, in edge order, every leaf exactly as it was (the sign of
    a zero included), an empty slot zero / False with edge -1; a later touching edge is dropped."""
    S, count = 8, 3
    rng = np.random.default_rng(len(touching))
    on = np.zeros((S, 2), bool)
    on[touching, 0] = True
    on[touching[::2], 1] = True
    clip = rng.normal(size=(S, 2, 2)).astype(np.float32)
    clip[:, 0, 1] = -0.0
    m = dict(on=jnp.asarray(on), clip=jnp.asarray(clip), face_b=jnp.asarray(rng.random(S) < 0.5),
             id=jnp.asarray(rng.integers(-9, 1 << 20, S), jnp.int32))
    got = jax.jit(E.select_edges, static_argnums=1)(m, count)
    want_edges = touching[:count] + [-1] * (count - len(touching[:count]))
    np.testing.assert_array_equal(np.asarray(got["edge"]), want_edges)
    for k, e in enumerate(want_edges):
        for name, leaf in m.items():
            ref = np.asarray(leaf)[e] if e >= 0 else np.zeros_like(np.asarray(leaf)[0])
            assert np.asarray(got[name][k]).tobytes() == ref.tobytes(), (name, k)


def test_box_at_rest_on_an_edge_shares_its_weight_between_two_points():
    """Box2D's block solver: a box resting flat on one edge carries m g dt in its two normal impulses,
    half each; the other edge slots stay empty."""
    cfg = physics2d.SolverConfig(dt=1 / 50, velocity_iterations=8, position_iterations=3, edge_contacts=2)
    box = ((-0.5, -0.25), (0.5, -0.25), (0.5, 0.25), (-0.5, 0.25))
    m = physics2d.make_model(1, [physics2d.Polygon(0, box, 2.0, 0.4)], (), cfg)
    ground = jnp.asarray([[0.0, 1.0], [10.0, 1.0], [20.0, 1.0]], jnp.float32)
    w = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[5.0, 1.3]], [0.0]))
    assert w.normal_impulse.shape == (4,) and w.contact_key.shape == (4, 2)
    w = jax.jit(lambda w: jax.lax.scan(lambda w, _: (physics2d.step(m, w, ground, -10.0)[0], None), w, None,
                                       length=60)[0])(w)
    mgdt = 2.0 * 0.5 * 10.0 / 50
    assert w.touching.tolist() == [True, True, False, False]
    np.testing.assert_allclose(np.asarray(w.normal_impulse[:2]), [mgdt / 2, mgdt / 2], rtol=1e-3)
    assert abs(float(w.bodies.com[0, 1]) - 0.25 - 1.0 - 0.015) < 1e-3  # Box2D's resting gap (radius - slop)


@pytest.mark.optimized  # bitwise: two programs
def test_edge_contacts_run_in_the_fused_kernel_bitwise():
    """The edge solver's passes and the looped time of impact keep the fused loop's contract (per-world
    scalars, elementwise ops, ``fused.when`` skips): through the Pallas kernel's interpreter a vmapped
    batch ends bitwise where plain XLA does. The fourth world falls fast enough for a time of impact."""
    box = ((-0.5, -0.25), (0.5, -0.25), (0.5, 0.25), (-0.5, 0.25))
    ground = jnp.asarray([[0.0, 1.0], [5.2, 1.0], [10.0, 1.0]], jnp.float32)  # a junction under the box
    out = {}
    for kernel in ("xla", "interpret"):
        cfg = physics2d.SolverConfig(dt=1 / 50, velocity_iterations=8, position_iterations=3, edge_contacts=2,
                                     kernel=kernel, toi_loop=True, toi_position_iterations=20)
        m = physics2d.make_model(1, [physics2d.Polygon(0, box, 2.0, 0.4)], (), cfg)
        make = lambda y, a, v, m=m: physics2d.init_world(m, physics2d.bodies_from_origin(
            m, jnp.stack([jnp.stack([5.0, y])]), a[None], vel=jnp.stack([jnp.stack([0.0, v])])))
        ws = jax.vmap(make)(jnp.asarray([1.3, 1.26, 1.4, 1.4]), jnp.asarray([0.0, 0.1, -0.2, 0.0]),
                            jnp.asarray([0.0, 0.0, 0.0, -10.0]))
        step = lambda w, _, m=m: (physics2d.step(m, w, ground, -10.0)[0],) * 2
        run = lambda w: jax.lax.scan(step, w, None, length=10)
        out[kernel] = jax.jit(jax.vmap(run))(ws)
    for a, b in zip(jax.tree_util.tree_leaves(out["xla"]), jax.tree_util.tree_leaves(out["interpret"])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    first_vy = out["xla"][1].bodies.vel[3, 0, 0, 1]  # the fast box after its first step
    assert abs(float(first_vy)) < 1.0, first_vy  # from 10.2 m/s: stopped by the time of impact


def test_the_time_of_impact_gate_skips_only_batches_without_an_impact():
    """``SolverConfig.toi_gate``: the time of impact's solve runs for the vmapped batch only when some
    world has an impact candidate (``fused.batch_any``: a cond, not a select). A batch with a box that
    falls fast enough for one, and a batch of three slower ones, end where the ungated solver ends (to
    float32 rounding: the solve is a branch of its own program), the fast box stopped in its first step."""
    box = ((-0.5, -0.25), (0.5, -0.25), (0.5, 0.25), (-0.5, 0.25))
    ground = jnp.asarray([[0.0, 1.0], [5.2, 1.0], [10.0, 1.0]], jnp.float32)

    def program(gate):
        cfg = physics2d.SolverConfig(dt=1 / 50, velocity_iterations=8, position_iterations=3, edge_contacts=2,
                                     kernel="xla", toi_loop=True, toi_position_iterations=20, toi_gate=gate)
        m = physics2d.make_model(1, [physics2d.Polygon(0, box, 2.0, 0.4)], (), cfg)
        make = lambda y, v: physics2d.init_world(m, physics2d.bodies_from_origin(  # noqa: E731
            m, jnp.stack([jnp.stack([5.0, y])]), jnp.zeros((1,)), vel=jnp.stack([jnp.stack([0.0, v])])))
        step = lambda w, _: (physics2d.step(m, w, ground, -10.0)[0],) * 2  # noqa: E731

        def go(vy):
            ws = jax.vmap(make)(jnp.asarray([1.3, 1.4, 1.26]), vy)
            return jax.vmap(lambda w: jax.lax.scan(step, w, None, length=10)[1])(ws)

        return jax.jit(go), str(jax.make_jaxpr(go)(jnp.zeros(3)))

    (gated, jaxpr), (plain, plain_jaxpr) = program(True), program(False)
    assert jaxpr.count("cond[") == plain_jaxpr.count("cond[") + 1  # the gate's (the rest: per-platform code)
    assert jaxpr.count("select_n") <= plain_jaxpr.count("select_n")  # a cond under vmap, not selects of both
    for vy in ([0.0, -10.0, 0.0], [0.0, 0.0, 0.0]):  # one box fast enough for an impact; three slow ones
        vy = jnp.asarray(vy, jnp.float32)
        g, p = gated(vy), plain(vy)
        for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(p)):
            if np.issubdtype(np.asarray(a).dtype, np.floating):
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
            else:
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        if vy[1]:
            assert abs(float(g.bodies.vel[1, 0, 0, 1])) < 1.0  # from 10 m/s: stopped by the time of impact


@pytest.mark.optimized  # bitwise: several programs
def test_velocity_passes_over_packed_manifolds_equal_the_passes_over_every_slot():
    """``SolverConfig.velocity_manifolds``: two boxes on ground edges (4 manifold slots), the first across
    a junction (2 manifolds with points once landed), the second on one edge (1). Packed into 3 slots the
    velocity passes give the passes over all 4 (to float32 rounding: the programs differ), the same
    bitwise through the kernel's interpreter as with XLA loops (a slot's body is a per-world input
    there), and report no crowding; packed into 2 they report it and the trajectories differ."""
    box = ((-0.5, -0.25), (0.5, -0.25), (0.5, 0.25), (-0.5, 0.25))
    ground = jnp.asarray([[0.0, 1.0], [5.2, 1.0], [10.0, 1.0], [20.0, 1.0]], jnp.float32)

    def run(slots, kernel):
        cfg = physics2d.SolverConfig(dt=1 / 50, velocity_iterations=8, position_iterations=3, edge_contacts=2,
                                     velocity_manifolds=slots, kernel=kernel, continuous=False)  # no TOI: a third of the compile
        m = physics2d.make_model(2, [physics2d.Polygon(0, box, 2.0, 0.4), physics2d.Polygon(1, box, 1.0, 0.3)], (), cfg)

        def make(y, a):
            return physics2d.init_world(m, physics2d.bodies_from_origin(
                m, jnp.stack([jnp.stack([5.0, y]), jnp.stack([12.0, y + 0.02])]), jnp.stack([a, -a]),
                vel=jnp.asarray([[0.3, 0.0], [-0.2, 0.0]], jnp.float32)))

        ws = jax.vmap(make)(jnp.asarray([1.3, 1.26, 1.28]), jnp.asarray([0.0, 0.02, -0.01]))

        def step(w, _):
            w, info = physics2d.step(m, w, ground, -10.0)
            return w, (w, info["manifolds_crowded"])

        return jax.jit(jax.vmap(lambda w: jax.lax.scan(step, w, None, length=12)[1]))(ws)

    full, _ = run(0, "xla")
    on = np.asarray(full.touching).reshape(3, 12, 4, 2).any(-1).sum(-1)  # manifolds with points
    assert on.max() == 3 and (on == 3).sum() >= 12, on  # the case the packing must get right
    packed = {kernel: run(3, kernel) for kernel in ("xla", "interpret")}
    for a, b, c in zip(*(jax.tree_util.tree_leaves(x) for x in (full, packed["xla"][0], packed["interpret"][0]))):
        np.testing.assert_array_equal(np.asarray(b), np.asarray(c))  # the kernel's contract
        if np.issubdtype(np.asarray(a).dtype, np.floating):  # XLA may fuse the two programs' sums apart
            np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=2e-5, atol=1e-6)
        else:
            np.testing.assert_array_equal(np.asarray(b), np.asarray(a))
    assert not np.asarray(packed["xla"][1]).any()
    short, crowded = run(2, "xla")
    np.testing.assert_array_equal(np.asarray(crowded), on > 2)
    assert not np.array_equal(np.asarray(short.normal_impulse), np.asarray(full.normal_impulse))


def test_edge_constraints_of_several_polygons_are_each_polygons_own_in_polygon_order():
    """Polygons are grouped by vertex count for one vmapped computation per group; the result must be
    each solid polygon's own manifolds, in polygon order: a box, a triangle, a sensor and a box (groups
    {0, 3} and {1}, so the contacts are put back in order) against edges and a box obstacle, equal to the
    same model with every other polygon made a sensor."""
    import dataclasses

    from envs.physics2d.model import BodyState
    from envs.physics2d.world import edge_constraints

    box = ((-0.2, -0.1), (0.2, -0.1), (0.2, 0.1), (-0.2, 0.1))
    tri = ((-0.15, -0.1), (0.15, -0.1), (0.0, 0.15))
    polys = [physics2d.Polygon(0, box, 1.0, 0.5), physics2d.Polygon(1, tri, 1.0, 0.3),
             physics2d.Polygon(2, box, 1.0, 0.2, sensor=True), physics2d.Polygon(3, box, 2.0, 0.8)]
    cfg = physics2d.SolverConfig(dt=1 / 50, velocity_iterations=8, position_iterations=3, edge_contacts=2)
    model = physics2d.make_model(4, polys, (), cfg)
    f = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    # bodies resting on (or just into) the ground at x = 0, 1, 2, 3; the last one on the obstacle
    bodies = BodyState(com=f([[0.0, 0.095], [1.05, 0.09], [2.0, 0.09], [3.0, 0.39]]), angle=f([0.05, -0.1, 0.0, 0.02]),
                       vel=f(np.zeros((4, 2))), omega=f(np.zeros(4)))
    edges = f([[[-1.0, 0.0], [0.5, 0.0]], [[0.5, 0.0], [1.5, 0.0]], [[1.5, 0.0], [4.0, 0.0]], [[4.0, 0.0], [5.0, 0.0]]])
    valid = jnp.asarray([True, True, True, False])
    boxes, box_valid = f([[2.7, 3.3, 0.0, 0.3]]), jnp.asarray([True])
    whole = edge_constraints(model, bodies, edges, valid, boxes, box_valid)
    assert whole["on"].shape == (model.num_contacts,) == (3 * 2 * 2,)
    per_point = [name for name in whole if name not in ("pairs", "box_pairs", "body", "friction")]
    for j, k in enumerate(model.edge_polygons):
        alone = [dataclasses.replace(p, sensor=p.sensor or i != k) for i, p in enumerate(polys)]
        one = edge_constraints(physics2d.make_model(4, alone, (), cfg), bodies, edges, valid, boxes, box_valid)
        assert bool(jnp.any(one["on"])), k  # each solid polygon touches something
        for name in per_point:
            np.testing.assert_array_equal(np.asarray(whole[name][4 * j:4 * j + 4]), np.asarray(one[name]), err_msg=f"{name} {k}")
        assert whole["body"][4 * j:4 * j + 4] == one["body"] and whole["friction"][4 * j:4 * j + 4] == one["friction"]
        for name in ("pairs", "box_pairs"):
            np.testing.assert_array_equal(np.asarray(whole[name][k]), np.asarray(one[name][k]))
    assert not np.asarray(whole["pairs"][2]).any() and not np.asarray(whole["box_pairs"][2]).any()  # the sensor
    assert bool(whole["box_pairs"][3, 0]) and not np.asarray(whole["box_pairs"][:3]).any()
    # without boxes: the contacts of a box list none of which exists, and (polygons, 0) box pairs
    bare = edge_constraints(model, bodies, edges, valid)
    gone = edge_constraints(model, bodies, edges, valid, boxes, jnp.asarray([False]))
    assert bare["box_pairs"].shape == (4, 0) and not bool(jnp.any(bare["on"][8:]))  # body 3 stands on the box
    for name in per_point + ["pairs"]:
        np.testing.assert_array_equal(np.asarray(bare[name]), np.asarray(gone[name]), err_msg=name)


def test_passes_in_lanes_equal_the_sequential_passes(monkeypatch):
    """``SolverConfig.velocity_lanes`` and ``position_lanes``: four boxes of different masses on ground
    edges, two of them across a junction (2 manifolds each), one landing through the time of impact,
    so each body's manifolds run in a lane of their own (the step's passes and the time of impact's
    velocity passes; ``fused`` lanes, 4 threads per world in the kernel). A body's manifolds touch no
    other dynamic body, so the lanes do each body's operations in Box2D's order (the position passes' deepest
    separation is a minimum, over the lanes): the trajectories are the sequential passes', through XLA
    loops and through the kernel's interpreter, to float32 rounding (XLA fuses, and so contracts, the
    lane programs' multiply-adds apart: a few ulps per step, where a manifold on the wrong body or
    point would be off by the impulse itself). A layout other than 4 bodies with as many manifolds
    each keeps the sequential passes."""
    from envs.physics2d import world as W

    box = ((-0.5, -0.25), (0.5, -0.25), (0.5, 0.25), (-0.5, 0.25))
    ground = jnp.asarray([[0.0, 1.0], [5.2, 1.0], [10.0, 1.0], [15.1, 1.0], [30.0, 1.0]], jnp.float32)
    xs = (5.0, 9.0, 15.0, 21.0)  # the first and third across a junction
    assert W.lane_layout((0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3)) == tuple(
        (b, (2 * b, 2 * b + 1)) for b in range(4))
    assert W.lane_layout((0, 0, 1, 1, 2, 2)) is None and W.lane_layout((0, 0, 0, 0, 1, 1, 2, 2, 3, 3)) is None
    calls = {"_velocity_pass_lanes": 0, "_position_pass_lanes": 0}
    for name in calls:
        fn = getattr(W, name)
        monkeypatch.setattr(W, name, lambda *a, _fn=fn, _name=name: calls.__setitem__(_name, calls[_name] + 1) or _fn(*a))
    to_lanes = W.to_lanes
    monkeypatch.setattr(W, "to_lanes", lambda *a, joints=True: calls.__setitem__(
        "time of impact", calls.get("time of impact", 0) + (not joints)) or to_lanes(*a, joints=joints))

    def run(lanes, kernel, position_iterations=3, continuous=True):
        cfg = physics2d.SolverConfig(dt=1 / 50, velocity_iterations=8, position_iterations=position_iterations,
                                     edge_contacts=2, velocity_lanes=lanes, position_lanes=lanes, kernel=kernel,
                                     continuous=continuous, toi_loop=True)  # the walker's time-of-impact loops
        m = physics2d.make_model(4, [physics2d.Polygon(b, box, 1.0 + 0.5 * b, 0.2 + 0.1 * b) for b in range(4)], (), cfg)

        def make(y, a):
            pos = jnp.stack([jnp.stack([x, y + 0.01 * b]) for b, x in enumerate(xs)])
            return physics2d.init_world(m, physics2d.bodies_from_origin(
                m, pos, jnp.stack([a, -a, 0.5 * a, 0.0]), vel=jnp.asarray([[0.3, 0.0], [-0.2, 0.0], [0.1, -1.0], [0.0, -20.0]], jnp.float32)))

        ws = jax.vmap(make)(jnp.asarray([1.3, 1.26, 1.28]), jnp.asarray([0.0, 0.02, -0.01]))
        step = lambda w, _: (physics2d.step(m, w, ground, -10.0)[0],) * 2  # noqa: E731
        return jax.jit(jax.vmap(lambda w: jax.lax.scan(step, w, None, length=12)[1]))(ws)

    seq = run(False, "xla")
    assert not any(calls.values())
    touching = np.asarray(seq.touching).reshape(3, 12, 4, 2, 2).any(-1).sum(-1)  # manifolds with points per body
    assert touching[..., 0].max() == 2 and touching[..., 2].max() == 2 and touching[:, -1].min() >= 1, touching
    lanes = {kernel: run(True, kernel) for kernel in ("xla", "interpret")}
    assert all(calls.values()), calls

    def close(got, want):
        if np.issubdtype(np.asarray(want).dtype, np.floating):  # rounding, against each quantity's own scale
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=2e-5,
                                       atol=1e-5 * float(np.abs(np.asarray(want)).max(initial=0.0)) + 2e-6)
        else:
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))

    for a, b, c in zip(*(jax.tree_util.tree_leaves(x) for x in (seq, lanes["xla"], lanes["interpret"]))):
        close(b, a)
        close(c, a)
    # the position passes and the time of impact (the last box lands at 20 m/s: 0.4 m a step) matter
    # here: without either the poses are off by far more than the tolerance
    for other in (run(False, "xla", position_iterations=0), run(False, "xla", continuous=False)):
        with pytest.raises(AssertionError):
            close(other.bodies.com, seq.bodies.com)
    impulses = np.abs(np.asarray(seq.normal_impulse))
    assert impulses.max() > 0.05  # the tolerance is far below what a misplaced manifold would move
