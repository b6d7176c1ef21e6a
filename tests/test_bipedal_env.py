"""BipedalWalker on physics2d: shapes, per-env isolation in one vmapped batch, motors and joint limits
(hand-computed), lidar on a hand-made terrain, reward identity, termination, no NaN on Insane, and
the drawing (each body where the solver holds it).

The walker's physics step compiles slowly on CPU, so every walker test reuses one jitted
``vmap(step)`` at batch 4; initial states come from that same program (an episode at its time limit
auto-resets), so the file compiles one walker program.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import physics2d
from envs.bipedal import BipedalWalker, heuristic, heuristic_init
from envs.bipedal import model as BM
from envs.bipedal.env import BACK_COLUMNS, motor_targets
from envs.walker import constants as C
from envs.walker import terrain as T
from envs.walker import levels as LV
from envs.walker.levels import LEVELS
from envs.walker.params import PARAM_NAMES

B = 4
pytestmark = pytest.mark.xdist_group("bipedal")


def stack(ps):
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *ps)


def take(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


@pytest.fixture(scope="module")
def sim():
    env = envs.make("bipedal")
    step = jax.jit(jax.vmap(env.step))

    def reset(key, params):
        """Fresh episodes through the shared program: a state at its time limit auto-resets."""
        dummy = jax.vmap(env.reset_env)  # structure only, never compiled
        shape = jax.eval_shape(dummy, jax.random.split(key, B), params)[1]
        state = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shape)
        state = state.replace(time=params.max_steps - 1)
        obs, state, _, done, _ = step(jax.random.split(key, B), state, jnp.zeros((B, 4)), params)
        assert bool(jnp.all(done))
        return obs, state.replace(time=jnp.zeros((B,), jnp.int32), episode_return=jnp.zeros((B,)))

    return env, reset, step


def levels(names, seeds=None):
    seeds = range(len(names)) if seeds is None else seeds
    return stack([LEVELS[n](terrain_seed=s, fixed_terrain=True) for n, s in zip(names, seeds)])


def rollout(step, state, params, actions, key=0):
    keys = jax.random.split(jax.random.PRNGKey(key), actions.shape[0])
    out = []
    for k, a in zip(keys, actions):
        o, state, r, d, info = step(jax.random.split(k, B), state, jnp.asarray(a, jnp.float32), params)
        out.append(jax.tree_util.tree_map(np.asarray, (o, state, r, d, info)))
    return state, out


def hull_x_angle(env, world):
    """Hull origin x and angle from the bodies, by hand: origin = com - R(angle) local_com."""
    lc = env.model.local_com[0]
    a = np.asarray(world.bodies.angle)[..., 0]
    com = np.asarray(world.bodies.com)[..., 0, :]
    return com[..., 0] - (np.cos(a) * lc[0] - np.sin(a) * lc[1]), a


# ----------------------------------------------------------------------------------- no physics compile
def test_registered_options_and_spaces():
    env = envs.make("bipedal")
    assert isinstance(env, BipedalWalker) and env.name == "bipedal" and env.ued is LV.UED  # the MJX walker's
    assert env.observation_space().shape == (24,) and env.action_space().shape == (4,)
    assert env.param_space.names == PARAM_NAMES
    with pytest.raises(ValueError, match="unknown option"):
        BipedalWalker(substeps=3)
    with pytest.raises(ValueError, match="window_columns"):
        BipedalWalker(window_columns=4)
    with pytest.raises(ValueError, match="solver_kernel"):
        BipedalWalker(solver_kernel="cuda")
    with pytest.raises(ValueError, match="contacts"):
        BipedalWalker(contacts="polygon")
    with pytest.raises(ValueError, match="obstacles"):
        BipedalWalker(obstacles="box")
    with pytest.raises(ValueError, match="window_boxes"):
        BipedalWalker(window_boxes=65)
    with pytest.raises(ValueError, match="toi_velocity_iterations"):
        BipedalWalker(toi_velocity_iterations=0)
    m = env.model
    # a leg's time-of-impact solve: 4 velocity passes by default; None gives it the step's, as
    # b2World::SolveTOI gives its sub-step
    assert m.config.toi_iterations == 4 and m.config.toi_position_iterations == 20
    assert BipedalWalker(toi_velocity_iterations=None).model.config.toi_iterations == 180
    assert BipedalWalker(toi_velocity_iterations=None, velocity_iterations=90).model.config.toi_iterations == 90
    # legs against Box2D-style separate terrain edges by default; the vertex model on request
    assert m.config.edge_contacts == BM.EDGE_CONTACTS and m.edge_polygons == (0, 1, 3, 4)  # not the hull (sensor)
    assert BipedalWalker(contacts="vertex").model.config.edge_contacts == 0
    # Box2D's mass properties (measured in Gymnasium): hull 5.4222 / 1.99940 about the COM
    # (-0.020036, -0.0056466); legs 0.30222 / 0.034140 and 0.24178 / 0.026796
    np.testing.assert_allclose(m.mass, [5.4222226, 0.3022222, 0.2417778, 0.3022222, 0.2417778], rtol=1e-6)
    np.testing.assert_allclose(m.inertia, [1.9993952, 0.0341399, 0.0267961, 0.0341399, 0.0267961], rtol=1e-5)
    np.testing.assert_allclose(m.local_com[0], [-0.0200364, -0.0056466], atol=1e-6)
    assert [m.joints[k].reference_angle for k in BM.MODEL_JOINT] == [-0.05, 0.0, 0.05, 0.0]  # Gymnasium order


def test_terrain_edges_are_gymnasiums_grass_edges():
    """A straight terrain column (grass: flat or sloped) is one Box2D edge from column end to column end,
    as Gymnasium's edge fixtures; a column with an obstacle keeps one edge per profile segment."""
    env = envs.make("bipedal")
    r = env.options.terrain_resolution
    dx = C.TERRAIN_STEP / r
    ys = np.concatenate([np.full(r, 1.0), 1.0 + 0.2 * np.arange(r) / r, [1.2, 1.5, 1.5, 1.2][:r], np.full(r + 1, 1.2)])
    ground = jnp.asarray(np.stack([np.arange(ys.size) * dx, ys], -1), jnp.float32)
    edges, valid = env.terrain_edges(ground)
    ground = np.asarray(ground)
    assert edges.shape == (4 * r, 2, 2) and valid.shape == (4 * r,)
    first = np.arange(4 * r) % r == 0
    np.testing.assert_array_equal(np.asarray(valid), first | (np.arange(4 * r) // r == 2))
    for c in (0, 1, 3):  # one edge per straight column, over the whole column
        np.testing.assert_allclose(np.asarray(edges[c * r]), np.asarray(ground[[c * r, (c + 1) * r]]), atol=1e-6)
    np.testing.assert_allclose(np.asarray(edges[2 * r: 3 * r]),
                               np.stack([ground[2 * r: 3 * r], ground[2 * r + 1: 3 * r + 1]], 1), atol=1e-6)


def test_fixture_window_is_gymnasiums_edges_and_every_box_in_reach():
    """The "polygon" obstacles' window: one edge per window column, the level's polyline segment
    (Gymnasium's edge fixture), and every obstacle box
    that reaches into the window, in the generator's order; over sampled FULL levels and Hardcore at
    every window position, no more boxes reach a window than ``window_boxes`` holds."""
    env = envs.make("bipedal")
    o = env.options
    full = env.param_space.sample(jax.random.PRNGKey(3), (48,))
    hard = stack([LEVELS["Hardcore"](terrain_seed=s, fixed_terrain=True) for s in range(16)])
    params = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), full, hard)
    keys = jax.random.split(jax.random.PRNGKey(4), 64)
    terrains = jax.jit(jax.vmap(env.terrain))(keys, params)
    profiles = jax.jit(jax.vmap(lambda t: T.rasterise(t, env.grid)))(terrains)
    cols = np.arange(-4, 200 - o.window_columns + 4, 3)

    @jax.jit
    def windows(t, profile):
        def at(c):
            ground, col = env.ground_window(profile, (c + BACK_COLUMNS) * C.TERRAIN_STEP + 0.1)
            # a box that meets the window at one end (x0 == its last x, x1 == its first: common, as
            # both lie on terrain columns) may go either way: XLA may round this copy of the window's
            # ends otherwise than fixture_window's
            reach = lambda m: jnp.sum(t.box_valid & (t.boxes[:, 1] >= ground[0, 0] + m) & (t.boxes[:, 0] <= ground[-1, 0] - m))
            return (col,) + env.fixture_window(t, ground, col) + (reach(1e-4), reach(-1e-4))
        return jax.vmap(at)(jnp.asarray(cols))

    out = jax.tree_util.tree_map(np.asarray, jax.vmap(windows)(terrains, profiles))
    col, edges, valid, boxes, box_ok, index, n_inside, n_reach = out
    assert n_reach.max() <= o.window_boxes, n_reach.max()
    assert n_inside.max() >= 3  # the windows do reach obstacles
    assert np.all(box_ok.sum(-1) >= n_inside) and np.all(box_ok.sum(-1) <= n_reach)
    tx, ty = np.asarray(terrains.x), np.asarray(terrains.y)
    tb = np.asarray(terrains.boxes)
    for lv in range(0, 64, 7):
        for w in range(0, len(cols), 5):
            c0 = col[lv, w]
            assert edges.shape[2] == o.window_columns
            for j in range(o.window_columns):
                c = c0 + j
                assert valid[lv, w, j] == (0 <= c <= 198)
                if 0 <= c <= 198:
                    np.testing.assert_array_equal(edges[lv, w, j], [[tx[lv, c], ty[lv, c]], [tx[lv, c + 1], ty[lv, c + 1]]])
            k = box_ok[lv, w]
            np.testing.assert_array_equal(boxes[lv, w][k], tb[lv][index[lv, w][k]])
            assert np.all(np.diff(index[lv, w][k]) > 0)


def test_motor_targets_are_gymnasiums():
    speed, torque = motor_targets(jnp.asarray([0.5, -1.0, 0.0, 2.0]))
    np.testing.assert_allclose(speed, [4.0, -6.0, 0.0, 6.0])  # hips 4, knees 6 rad/s
    np.testing.assert_allclose(torque, [40.0, 80.0, 0.0, 80.0])


def _rotor_model(**joint):
    """Two boxes pinned at their common centre (no point-constraint torque), no gravity or contacts."""
    box = ((-0.5, -0.1), (0.5, -0.1), (0.5, 0.1), (-0.5, 0.1))
    cfg = physics2d.SolverConfig(dt=0.02, velocity_iterations=20, position_iterations=5)
    polys = [physics2d.Polygon(0, box, 1.0, 0.1, sensor=True), physics2d.Polygon(1, box, 2.0, 0.1, sensor=True)]
    j = physics2d.RevoluteJoint(0, 1, (0.0, 0.0), (0.0, 0.0), enable_motor=True, **joint)
    return physics2d.make_model(2, polys, (j,), cfg)


def test_per_step_motor_speed_and_torque_per_world():
    m = _rotor_model()
    ground = jnp.asarray([[-10.0, -5.0], [10.0, -5.0]])
    w = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[0.0, 0.0], [0.0, 0.0]], [0.0, 0.0]))

    @jax.jit
    @jax.vmap
    def one_step(world, speed, torque):
        return physics2d.step(m, world, ground, 0.0, motor_speed=speed[None], max_motor_torque=torque[None])[0]

    speed = jnp.asarray([4.0, -6.0, 0.5])
    torque = jnp.asarray([1.0, 2.0, 80.0])
    ws = jax.tree_util.tree_map(lambda x: jnp.stack([x] * 3), w)
    ws = one_step(ws, speed, torque)
    rel = np.asarray(ws.bodies.omega[:, 1] - ws.bodies.omega[:, 0])
    # saturated motors: one step changes the relative spin by dt * T * (1/I_a + 1/I_b)
    k = float(m.inv_inertia[0] + m.inv_inertia[1])
    np.testing.assert_allclose(rel[:2], [0.02 * 1.0 * k, -0.02 * 2.0 * k], rtol=1e-5)
    np.testing.assert_allclose(rel[2], 0.5, rtol=1e-5)  # strong motor: at its target speed at once
    # the motor reaction conserves angular momentum
    np.testing.assert_allclose(np.asarray(ws.bodies.omega[:, 0] * m.inertia[0] + ws.bodies.omega[:, 1] * m.inertia[1]),
                               0.0, atol=1e-6)
    assert float(jnp.max(jnp.abs(ws.bodies.com))) < 1e-6  # the pin holds


def test_joint_limit_stops_a_motor_at_each_end():
    m = _rotor_model(enable_limit=True, lower=-0.4, upper=0.3)
    ground = jnp.asarray([[-10.0, -5.0], [10.0, -5.0]])
    w0 = physics2d.init_world(m, physics2d.bodies_from_origin(m, [[0.0, 0.0], [0.0, 0.0]], [0.0, 0.0]))

    @jax.jit
    def run(speed):
        def body(w, _):
            return physics2d.step(m, w, ground, 0.0, motor_speed=speed[None], max_motor_torque=jnp.asarray([50.0]))[0], None
        return jax.lax.scan(body, w0, None, length=60)[0]

    slop = 2.0 / 180 * np.pi
    for speed, limit in ((3.0, 0.3), (-3.0, -0.4)):
        w = run(jnp.float32(speed))
        angle = float(w.bodies.angle[1] - w.bodies.angle[0])
        assert abs(angle - limit) <= slop + 1e-4, (speed, angle)
        assert abs(float(w.bodies.omega[1] - w.bodies.omega[0])) < 1e-4
        assert int(w.limit_state[0]) == (2 if speed > 0 else 1)  # AT_UPPER / AT_LOWER


def test_lidar_against_hand_made_terrain():
    env = BipedalWalker()
    g = env.grid
    xs = g.x_min + g.dx * np.arange(g.n)
    h0, h1, x1 = 3.0, 4.0, 12.0
    profile = jnp.asarray(np.where(xs >= x1, h1, h0), jnp.float32)  # a plateau from x1 (one-cell face)
    hx, hy = 10.0, 6.0
    pos, ang = BM.initial_pose()
    pos = pos + np.asarray([hx - pos[0, 0], hy - pos[0, 1]], np.float32)
    world = physics2d.init_world(env.model, physics2d.bodies_from_origin(env.model, pos, ang))
    obs = np.asarray(env.observation(world, jnp.zeros(2, bool), profile))
    theta = 0.15 * np.arange(10)
    expect = []
    for t in theta:
        d_low = (hy - h0) / np.cos(t)  # hits the low ground if that point lies before the face
        x_low = hx + d_low * np.sin(t)
        d_high = (hy - h1) / np.cos(t)
        x_high = hx + d_high * np.sin(t)
        d = d_low if x_low < x1 - g.dx else (d_high if x_high >= x1 else np.nan)
        expect.append(min(d / C.LIDAR_RANGE, 1.0))
    expect = np.asarray(expect)
    known = np.isfinite(expect)
    assert known.sum() >= 8
    np.testing.assert_allclose(obs[14:][known], expect[known], rtol=1e-5)
    assert np.all(obs[14:] > 0) and np.all(obs[14:] <= 1)
    np.testing.assert_allclose(obs[[0, 1, 2, 3]], 0.0, atol=1e-7)  # hull at rest, level
    np.testing.assert_allclose(obs[[4, 6, 9, 11]], [0.0, 1.0, 0.0, 1.0], atol=1e-6)  # created pose: joints at 0


def test_heuristic_matches_gymnasiums_controller():
    gym_bw = pytest.importorskip("gymnasium.envs.box2d.bipedal_walker")
    rng = np.random.default_rng(0)
    h_gym = gym_bw.BipedalWalkerHeuristics()
    h = heuristic_init()
    step = jax.jit(heuristic)
    phases = set()
    for _ in range(300):
        s = rng.uniform(-1, 1, 24).astype(np.float32)
        s[[8, 13]] = rng.random(2) < 0.5
        a_gym = h_gym.step_heuristic(s)
        a, h = step(h, jnp.asarray(s))
        np.testing.assert_allclose(np.asarray(a), a_gym, atol=1e-5)
        assert int(h.phase) == h_gym.state and int(h.moving_leg) == h_gym.moving_leg
        phases.add(h_gym.state)
    assert phases == {1, 2, 3}


def test_parity_fall_sites_count_the_nearest_obstacle():
    """The parity harness's falls by obstacle: runs of non-grass columns are obstacles; a fall counts
    for the nearest one within 3 terrain steps of the hull, else for grass; episodes that did not
    fall are not counted; the episodes at the time limit without a fall are counted the same way."""
    from envs.bipedal.parity import column_obstacles, end_sites, site_fields

    S = C.TERRAIN_STEP
    kinds = np.array([C.GRASS, C.STUMP, C.GRASS, C.GRASS, C.PIT, C.PIT, C.PIT, C.STAIRS, C.STAIRS, C.GRASS])
    xs = np.arange(10) * S
    obs = column_obstacles(kinds, xs)
    assert [k for _, _, k in obs] == ["stump", "pit", "stairs"]
    np.testing.assert_allclose([(a, b) for a, b, _ in obs], [(S, 2 * S), (4 * S, 7 * S), (7 * S, 9 * S)])
    assert column_obstacles(np.array([C.GRASS, C.PIT]), np.array([0.0, S]))[0][2] == "pit"  # a run at the end
    x = [1.5 * S, 5 * S, 2.9 * S, 30 * S, 3 * S]
    fell = [True, True, True, True, False]
    assert end_sites(x, fell, [obs] * 5) == {"stump": 2, "stairs": 0, "pit": 1, "grass": 1}
    # episode 1 stands in the pit until the limit, episode 4 ends early without a fall (not counted)
    d = dict(x=x, fall=[True, False, True, True, False], length=[10, 2000, 10, 10, 40], obstacles=[obs] * 5)
    sites = site_fields("ours", d, limit=2000)
    assert sites["ours_fall_sites"] == {"stump": 2, "stairs": 0, "pit": 0, "grass": 1}
    assert sites["ours_limit_sites"] == {"stump": 0, "stairs": 0, "pit": 1, "grass": 0}


def test_parity_reads_gymnasiums_obstacles_from_its_polygons():
    """Gymnasium's fixtures -> obstacles: a pit's two walls (1 x 4 steps, the second one's top level
    with the pit floor's polyline, not the ground's) are one pit, a 4-step-wide box a stair step, a
    square a stump; edge fixtures are skipped."""
    b2 = pytest.importorskip("Box2D")
    from types import SimpleNamespace

    from envs.bipedal.parity import gym_obstacles

    S = C.TERRAIN_STEP

    def body(shape):
        return SimpleNamespace(fixtures=[SimpleNamespace(shape=shape)])

    def box(x0, x1, y0, y1):
        return body(b2.b2PolygonShape(vertices=[(x0, y0), (x1, y0), (x1, y1), (x0, y1)]))

    y = 4.0
    terrain = [box(10 * S, 11 * S, y - 4 * S, y), box(13 * S, 14 * S, y - 4 * S, y),  # a pit, walls 3 steps apart
               box(20 * S, 22 * S, y, y + 2 * S),  # a 2-step stump
               box(30 * S, 34 * S, y - S, y), box(34 * S, 38 * S, y, y + S),  # two stair steps
               box(45 * S, 46 * S, y, y + S),  # a 1-step stump
               box(50 * S, 51 * S, y - 4 * S, y), box(54 * S, 55 * S, y - 4 * S, y),  # another pit
               body(b2.b2EdgeShape(vertices=[(0.0, y), (S, y)]))]
    got = gym_obstacles(SimpleNamespace(terrain=terrain))
    assert [k for _, _, k in got] == ["pit", "stump", "stairs", "stairs", "stump", "pit"]
    np.testing.assert_allclose([got[0][:2], got[-1][:2]], [(10 * S, 14 * S), (50 * S, 55 * S)], rtol=1e-6)


# ----------------------------------------------------------------------------------- the shared program
def test_reset_shapes_and_created_pose(sim):
    env, reset, _ = sim
    params = levels(["BipedalWalker", "Stump", "Insane", "Hardcore"])
    obs, s = reset(jax.random.PRNGKey(0), params)
    assert obs.shape == (B, 24) and obs.dtype == jnp.float32
    assert s.world.bodies.com.shape == (B, 5, 2) and s.profile.shape == (B, env.grid.n)
    x, a = hull_x_angle(env, s.world)
    # the reset step pulls the legs onto the hips (0.53 m) and lands them; the hull barely moves
    # sideways (push U(-5, 5) N for one step) and tilts less than 0.01 rad
    assert np.all(np.abs(x - BM.INIT_X) < 0.01) and np.all(np.abs(a) < 0.01)
    # the first 8 rays hit the flat start pad, the same in every level (the far ones may see obstacles)
    np.testing.assert_allclose(np.asarray(obs[:, 14:22]), np.tile(np.asarray(obs[0, 14:22]), (B, 1)), atol=1e-6)
    assert np.all(np.asarray(obs[:, [8, 13]]) == 1.0)  # both feet land in the reset step, as in Gymnasium
    # fixed terrains replay: the same level gives the same profile
    _, s2 = reset(jax.random.PRNGKey(9), params)
    np.testing.assert_array_equal(np.asarray(s.profile), np.asarray(s2.profile))


def test_render_draws_the_bodies_where_the_solver_holds_them(sim):
    """The frame shows each body at its own position and angle, not a skeleton rebuilt from the
    joint angles: joints are soft constraints (a knee is 0.23 m apart after the reset step)."""
    from envs.walker import render as R

    env, reset, step = sim
    params = levels(["BipedalWalker", "Stump", "Insane", "Hardcore"])
    _, s = reset(jax.random.PRNGKey(0), params)
    _, out = rollout(step, s, params, np.zeros((30, B, 4), np.float32))
    s0 = take(out[-1][1], 0)
    polys = env.body_polygons(s0)
    assert sorted(polys) == ["hull", "lower0", "lower1", "upper0", "upper1"]
    # the hull by hand: origin + R(angle) local vertex, local vertices Gymnasium's (scaled)
    x, a = hull_x_angle(env, jax.tree_util.tree_map(lambda v: v[None], s0.world))
    z = float(env.hull_origin(s0.world)[1])
    rot = np.array([[np.cos(a[0]), -np.sin(a[0])], [np.sin(a[0]), np.cos(a[0])]])
    hull = np.asarray(C.HULL_POLY, np.float64) / C.SCALE @ rot.T + [x[0], z]
    np.testing.assert_allclose(np.sort(polys["hull"], 0), np.sort(hull, 0), atol=1e-5)
    # standing for 30 steps the joints hold: the skeleton from the joint angles is the same picture
    ang = np.asarray(s0.world.bodies.angle)
    q = [x[0], z, ang[0], ang[1] - ang[0], ang[2] - ang[1], ang[3] - ang[0], ang[4] - ang[3]]
    skeleton = R.body_polygons(q)
    for name, poly in polys.items():
        gap = max(np.min(np.linalg.norm(skeleton[name] - v, axis=1)) for v in poly)
        assert gap < 0.01, (name, gap)
    # a knee pulled apart by 0.5 m (angles unchanged): the drawn shin moves with it
    moved = s0.replace(world=s0.world.replace(bodies=s0.world.bodies.replace(
        com=jnp.asarray(s0.world.bodies.com).at[BM.LOWER[0], 0].add(0.5))))
    np.testing.assert_allclose(env.body_polygons(moved)["lower0"], polys["lower0"] + [0.5, 0.0], atol=1e-5)
    frame, frame_moved = env.render(s0), env.render(moved)
    assert frame.shape == (267, 400, 3) and frame.dtype == np.uint8
    assert np.count_nonzero(np.any(frame != frame_moved, -1)) > 100  # the shin's pixels moved
    # the terrain drawn is the physics' fixtures: a stump's box taken out of the state's terrain leaves
    # the frame (the profile, which only the lidar reads, still has it)
    s1 = take(out[-1][1], 1)  # the Stump level
    t, x1 = s1.terrain, float(env.hull_origin(s1.world)[0])
    boxes, ok = np.asarray(t.boxes), np.asarray(t.box_valid)
    in_view = np.nonzero(ok & (boxes[:, 0] > x1) & (boxes[:, 1] < x1 + 10.0))[0]
    assert in_view.size, "no stump in view: pick another terrain seed"
    gone = s1.replace(terrain=t.replace(box_valid=jnp.asarray(ok).at[in_view].set(False)))
    with_box, without = env.render(s1), env.render(gone)
    changed = np.any(with_box != without, -1)
    cols = np.nonzero(changed.any(0))[0]
    assert np.count_nonzero(changed) > 20 and cols.size
    # the changed pixels lie over the removed boxes (400 px for the 20 m view, hull at a quarter of it)
    px = lambda x: (x - (x1 - 5.0)) * 20.0  # noqa: E731
    assert px(boxes[in_view, 0].min()) - 2 <= cols.min() and cols.max() <= px(boxes[in_view, 1].max()) + 2


def test_per_env_isolation(sim):
    env, reset, step = sim
    rng = np.random.default_rng(1)
    params = levels(["BipedalWalker", "Stump", "Insane", "Stairs"])
    _, s = reset(jax.random.PRNGKey(1), params)
    actions = rng.uniform(-1, 1, (25, B, 4)).astype(np.float32)
    _, out_a = rollout(step, s, params, actions)
    # env 3: other actions and another level (terrain), everything else the same
    actions_b = actions.copy()
    actions_b[:, 3] = rng.uniform(-1, 1, (25, 4))
    params_b = jax.tree_util.tree_map(lambda p, q: p.at[3].set(q), params, LEVELS["PitGap"](terrain_seed=7, fixed_terrain=True))
    s_b = s.replace(profile=s.profile.at[3].set(s.profile[0] + 0.1))
    _, out_b = rollout(step, s_b, params_b, actions_b)
    for (oa, sa, ra, da, _), (ob, sb, rb, db, _) in zip(out_a, out_b):
        np.testing.assert_array_equal(oa[:3], ob[:3])
        np.testing.assert_array_equal(ra[:3], rb[:3])
        np.testing.assert_array_equal(sa.world.bodies.com[:3], sb.world.bodies.com[:3])
    assert not np.array_equal(out_a[-1][0][3], out_b[-1][0][3])


def test_reward_is_gymnasiums_shaping_difference(sim):
    env, reset, step = sim
    rng = np.random.default_rng(2)
    params = levels(["BipedalWalker"] * B)
    _, s = reset(jax.random.PRNGKey(2), params)
    for t in range(12):
        a = rng.uniform(-1.3, 1.3, (B, 4)).astype(np.float32)
        x0, a0 = hull_x_angle(env, s.world)
        _, s1, r, d, info = step(jax.random.split(jax.random.PRNGKey(t), B), s, jnp.asarray(a), params)
        x1, a1 = hull_x_angle(env, s1.world)
        live = ~np.asarray(d)
        expect = 130.0 / 30.0 * (x1 - x0) - 5.0 * (np.abs(a1) - np.abs(a0)) - 0.00035 * 80 * np.abs(np.clip(a, -1, 1)).sum(1)
        np.testing.assert_allclose(np.asarray(r)[live], expect[live], atol=2e-4)
        s = s1


def test_termination_rules(sim):
    env, reset, step = sim
    params = levels(["BipedalWalker"] * B)
    _, s = reset(jax.random.PRNGKey(3), params)
    flat = jnp.full_like(s.profile, C.TERRAIN_HEIGHT)
    # env 0 as is; env 1 moved to x = -0.5; env 2 past the finish line; env 3 with the hull sunk into the ground
    x, _ = hull_x_angle(env, s.world)
    shift = np.zeros((B, 1, 2), np.float32)
    shift[1, 0, 0] = -0.5 - x[1]
    shift[2, 0, 0] = C.FINISH_X + 0.2 - x[2]
    shift[3, 0, 1] = -2.3  # the whole walker: hull bottom 0.2 m below the ground
    world = s.world.replace(bodies=s.world.bodies.replace(com=s.world.bodies.com + shift))
    s = s.replace(world=world, profile=flat, window=jnp.zeros((B,), jnp.int32),
                  leg_pairs=jnp.zeros_like(s.leg_pairs))
    _, _, r, d, info = step(jax.random.split(jax.random.PRNGKey(0), B), s, jnp.zeros((B, 4)), params)
    r, d = np.asarray(r), np.asarray(d)
    assert not d[0] and abs(r[0]) < 1.0
    assert d[1] and r[1] == -100.0 and bool(info["terminated"][1])
    assert d[2] and r[2] != -100.0 and bool(info["finished"][2]) and bool(info["terminated"][2])
    assert d[3] and r[3] == -100.0 and bool(info["hull_contact"][3])


def test_no_nan_under_random_actions_on_insane(sim):
    env, reset, step = sim
    rng = np.random.default_rng(4)
    params = stack([LEVELS["Insane"](terrain_seed=s) for s in range(B)])  # new terrain every episode
    obs, s = reset(jax.random.PRNGKey(4), params)
    dones = 0
    for t in range(150):
        a = jnp.asarray(rng.uniform(-1, 1, (B, 4)), jnp.float32)
        obs, s, r, d, info = step(jax.random.split(jax.random.PRNGKey(100 + t), B), s, a, params)
        assert np.all(np.isfinite(np.asarray(obs))) and np.all(np.isfinite(np.asarray(r)))
        assert np.all(np.isfinite(np.asarray(s.world.bodies.com)))
        dones += int(np.sum(np.asarray(d)))
    assert dones >= 1  # random actions fall over (and the episodes auto-reset)


def test_light_reset_is_the_full_reset_step():
    """``light_reset`` (the default) skips the edge manifolds in the reset's physics step because the
    feet are created 0.27 m above every level's flat start: the same observation and state as the
    full step (flags exactly, floats to rounding), on obstacle levels and sampled ones, each with its
    own random push. Both programs run without the time of impact: it is the same code in both (the legs land
    through it, checked with the default options in ``test_reset_shapes_and_created_pose``) and about
    two thirds of each reset's compile."""
    light, full = envs.make("bipedal", continuous=False), envs.make("bipedal", light_reset=False, continuous=False)
    names = ["BipedalWalker", "Hardcore", "Insane", "PitGap", "Stairs", "Stump"]
    ps = [LEVELS[n](terrain_seed=i, fixed_terrain=True) for i, n in enumerate(names)]
    sampled = light.param_space.sample(jax.random.PRNGKey(5), (2,))
    params = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), stack(ps), sampled)
    keys = jax.random.split(jax.random.PRNGKey(6), len(names) + 2)
    out_l = jax.jit(jax.vmap(light.reset_env))(keys, params)
    out_f = jax.jit(jax.vmap(full.reset_env))(keys, params)
    for a, b in zip(jax.tree_util.tree_leaves(out_l), jax.tree_util.tree_leaves(out_f)):
        a, b = np.asarray(a), np.asarray(b)
        if a.dtype != np.float32:  # contact flags, keys, windows, times
            np.testing.assert_array_equal(a, b)
        else:  # two programs round the joints' arithmetic differently (5e-7 of 0.86 seen; op by op,
            # under jax.disable_jit, the two are bitwise equal)
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_parity_summary_splits_lengths_by_falls():
    """The harness's summary by hand: returns' mean and standard error, fall rate, and mean lengths
    over all episodes, those that fell and the others (None when a group is empty)."""
    from envs.bipedal.parity import summarize

    s = summarize([-100.0, -80.0, 20.0, 40.0], [100, 300, 2000, 1600], [True, True, False, False])
    assert s["episodes"] == 4 and s["mean"] == -30.0 and s["fall"] == 0.5
    assert abs(s["se"] - np.std([-100.0, -80.0, 20.0, 40.0]) / 2.0) < 1e-12
    assert (s["length"], s["length_fell"], s["length_other"]) == (1000.0, 200.0, 1800.0)
    assert summarize([1.0], [5], [False])["length_fell"] is None
