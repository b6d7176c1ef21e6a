"""Walker env on MJX: reset/obs, per-env isolation in one vmapped batch, reward and termination
rules, auto-reset, validation, lidar geometry, MJX vs MuJoCo C parity, no NaN on Insane.

MJX compiles slowly on CPU, so every physics test reuses one jitted ``vmap(step)`` at batch 4.
"""
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import envs
from envs.walker import constants as C
from envs.walker import lidar as L
from envs.walker import terrain as T
from envs.walker.env import _SPEEDS
from envs.walker.levels import LEVELS
from envs.walker.params import make_params

B = 4
pytestmark = pytest.mark.xdist_group("walker_mjx")


def batch(p, n=B):
    return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(jnp.asarray(x), (n,) + jnp.shape(x)), p)


def stack(ps):
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *ps)


def take(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


@pytest.fixture(scope="module")
def sim():
    env = envs.make("walker")
    reset = jax.jit(jax.vmap(env.reset))
    step = jax.jit(jax.vmap(env.step))
    return env, reset, step


def rollout(step, s, params, actions, key=0):
    """Run steps on a batch; actions [T, B, 4]. Returns the per-step outputs (numpy)."""
    keys = jax.random.split(jax.random.PRNGKey(key), actions.shape[0])
    out = []
    for k, a in zip(keys, actions):
        o, s, r, d, info = step(jax.random.split(k, B), s, jnp.asarray(a, jnp.float32), params)
        out.append(jax.tree_util.tree_map(np.asarray, (o, s, r, d, info)))
    return s, out


def test_reset_observation_and_terrain_identity(sim):
    env, reset, _ = sim
    seeds = [5, 5, 6, 5]
    fixed = [True, True, True, False]
    params = stack([LEVELS["Stump"](terrain_seed=s, fixed_terrain=f) for s, f in zip(seeds, fixed)])
    keys = jax.random.split(jax.random.PRNGKey(1), B)
    obs, s = jax.tree_util.tree_map(np.asarray, reset(keys, params))
    assert obs.shape == (B, 24) and np.all(np.isfinite(obs))
    np.testing.assert_allclose(obs[:, 0], 0.0)  # hull angle
    np.testing.assert_allclose(obs[:, [4, 9]], [[-0.05, 0.05]] * B, atol=1e-6)  # hips
    np.testing.assert_allclose(obs[:, [6, 11]], 0.9, atol=1e-6)  # knee -0.1, +1
    np.testing.assert_allclose(obs[:, [8, 13]], 0.0)  # no contact at the start
    assert np.all(np.abs(obs[:, 2]) <= 0.12 * C.INITIAL_RANDOM * C.CONTROL_DT / 6.5 + 1e-6)  # tiny push
    # Flat start pad at y0 below the hull: the downward ray hits at (z - y0) / range.
    np.testing.assert_allclose(obs[:, 14], (s.qpos[:, 1] - C.TERRAIN_HEIGHT) / C.LIDAR_RANGE, atol=1e-5)
    # Same seed + fixed -> same terrain whatever the key; other seed or free terrain -> different.
    np.testing.assert_array_equal(s.profile[0], s.profile[1])
    assert np.abs(s.profile[0] - s.profile[2]).max() > 0.1
    obs2, s2 = reset(jax.random.split(jax.random.PRNGKey(2), B), params)
    np.testing.assert_array_equal(np.asarray(s2.profile[0]), s.profile[0])
    assert np.abs(np.asarray(s2.profile[3]) - s.profile[3]).max() > 0.1


def test_isolation_in_one_batch(sim):
    env, reset, step = sim
    p = batch(LEVELS["BipedalWalker"](terrain_seed=3, fixed_terrain=True))
    keys = jax.random.split(jax.random.PRNGKey(3), B)
    _, s = reset(keys, p)
    # Env 1 stands on ground 0.7 m higher (same level otherwise): the same drop lands higher.
    raised = s.replace(profile=s.profile.at[1].add(0.7), z_base=s.z_base.at[1].add(0.7), qpos=s.qpos.at[1, 1].add(0.7))
    acts = np.zeros((40, B, 4), np.float32)
    s_a, out_a = rollout(step, raised, p, acts)
    z = np.stack([o[1].qpos[:, 1] for o in out_a])
    assert not np.any(np.stack([o[3] for o in out_a]))
    np.testing.assert_allclose(z[-1, 1] - z[-1, 0], 0.7, atol=0.02)  # lands on its own ground
    assert z[0, 0] - z[-1, 0] > 0.2  # ... after a real drop onto the legs
    contact = np.stack([o[0][:, [8, 13]] for o in out_a])
    assert contact[-1].min() == 1.0
    # Changing env 2's level (params and terrain) changes nothing in the others.
    p2 = p.replace(roughness=p.roughness.at[2].set(7.0), terrain_seed=p.terrain_seed.at[2].set(99))
    _, s_b0 = reset(keys, p2)
    s_b0 = s_b0.replace(profile=s_b0.profile.at[1].add(0.7), z_base=s_b0.z_base.at[1].add(0.7), qpos=s_b0.qpos.at[1, 1].add(0.7))
    acts = np.asarray(jax.random.uniform(jax.random.PRNGKey(4), (20, B, 4), minval=-1, maxval=1))
    s_a, out_a = rollout(step, raised, p, acts)
    s_b, out_b = rollout(step, s_b0, p2, acts)
    for oa, ob in zip(out_a, out_b):
        np.testing.assert_array_equal(oa[0][[0, 1, 3]], ob[0][[0, 1, 3]])
        np.testing.assert_array_equal(oa[2][[0, 1, 3]], ob[2][[0, 1, 3]])
    assert np.abs(np.asarray(s_a.profile[2]) - np.asarray(s_b.profile[2])).max() > 0.1


def test_reset_profile_is_the_terrains_polyline(sim):
    """The profile reset rasterises, inside its own program, is the generated polyline at the grid:
    an unrolled search whose sample positions were computed in the program, rounded differently in
    its fused steps, once returned another segment's heights at samples on vertices (2.7 m off)."""
    env, reset, _ = sim
    # fixed terrains: the polyline depends on the level's seed alone, not on the key reset splits
    p = stack([LEVELS["Roughness"](terrain_seed=sd, fixed_terrain=True) for sd in (11, 12, 13, 14)])
    keys = jax.random.split(jax.random.PRNGKey(5), B)
    _, s = reset(keys, p)
    t = jax.jit(jax.vmap(env.terrain))(keys, p)
    xs = env.grid.x_min + env.grid.dx * np.arange(env.grid.n)
    for b in range(B):
        tx, ty = np.asarray(t.x[b], np.float64), np.asarray(t.y[b], np.float64)
        assert np.all(np.diff(tx) > 0) and not np.asarray(t.box_valid[b]).any()  # roughness alone: a function of x
        np.testing.assert_allclose(np.asarray(s.profile[b]), np.interp(xs, tx, ty), rtol=0, atol=1e-4)


def test_reward_rules_and_auto_reset(sim):
    env, reset, step = sim
    p = stack([LEVELS["Roughness"](terrain_seed=11, fixed_terrain=True)] * 2 + [LEVELS["Roughness"](terrain_seed=11)] * 2)
    _, s = reset(jax.random.split(jax.random.PRNGKey(5), B), p)
    s0 = jax.tree_util.tree_map(np.asarray, s)
    shaping = lambda q: C.SHAPING_X * q[:, 0] - C.SHAPING_ANGLE * np.abs(q[:, 2])  # noqa: E731
    acts = np.asarray(jax.random.uniform(jax.random.PRNGKey(6), (15, B, 4), minval=-1, maxval=1))
    prev = s0
    for a, out in zip(acts, rollout(step, s, p, acts)[1]):
        o, s1, r, d, info = out
        assert not d.any()
        # r = delta(130 x / 30 - 5 |angle|) - 0.028 sum |a|: no progress -> only the torque cost.
        expect = shaping(s1.qpos) - shaping(prev.qpos) - 0.028 * np.abs(a).sum(1)
        np.testing.assert_allclose(r, expect, atol=2e-5)
        prev = s1
    # Torque cost uses clip(|a|, 0, 1): an action of 2 costs like 1 (no progress -> only the cost).
    # (float32, not jnp.full's weakly typed default: a weak action would compile the step a second time)
    o, s1, r, d, info = jax.tree_util.tree_map(np.asarray, step(jax.random.split(jax.random.PRNGKey(6), B), s1,
                                                                jnp.full((B, 4), 2.0, jnp.float32), p))
    np.testing.assert_allclose(r, shaping(s1.qpos) - shaping(prev.qpos) - 0.028 * 4, atol=2e-5)
    s_rest = s1
    # x < 0 -> -100, terminated, and an auto-reset to a fresh episode of the same level.
    crash = jax.tree_util.tree_map(jnp.asarray, s_rest)
    crash = crash.replace(qpos=crash.qpos.at[:, 0].set(-0.5))
    o, s2, r, d, info = jax.tree_util.tree_map(np.asarray, step(jax.random.split(jax.random.PRNGKey(7), B), crash, jnp.zeros((B, 4)), p))
    np.testing.assert_array_equal(r, -100.0)
    assert d.all() and info["terminated"].all() and not info["truncated"].any()
    np.testing.assert_array_equal(s2.time, 0)
    np.testing.assert_allclose(s2.qpos[:, 0], C.TERRAIN_STEP * C.TERRAIN_STARTPAD / 2)
    # fixed: the same terrain again (from the step's auto-reset, another program than reset: equal up to
    # rounding; a fresh terrain differs by more than 0.1, below)
    np.testing.assert_allclose(s2.profile[:2], s0.profile[:2], rtol=0, atol=1e-5)
    assert np.abs(s2.profile[2:] - s0.profile[2:]).max() > 0.1  # free: a fresh terrain ...
    # ... of the same level (roughness 5 statistics: varied but bounded).
    assert 0.05 < s2.profile[2:].std() < 3.0
    np.testing.assert_array_equal(info["episode_length"], 17)
    # Past the finish line: done without the crash penalty.
    fin = jax.tree_util.tree_map(jnp.asarray, s_rest)
    fin = fin.replace(qpos=fin.qpos.at[:, 0].set(C.FINISH_X + 0.5).at[:, 1].add(20.0))
    _, _, r, d, info = step(jax.random.split(jax.random.PRNGKey(8), B), fin, jnp.zeros((B, 4)), p)
    assert np.asarray(d).all() and np.all(np.asarray(r) > -100) and np.asarray(info["finished"]).all()


def test_mjx_matches_mujoco_c(sim):
    """Same model, terrain, servo and solver in MuJoCo C (mj_step): 100 control steps agree."""
    env, reset, step = sim
    p = batch(LEVELS["BipedalWalker"](terrain_seed=2, fixed_terrain=True))
    _, s = reset(jax.random.split(jax.random.PRNGKey(9), B), p)
    t = np.arange(100)[:, None]
    gait = np.concatenate([np.sin(0.15 * t + [0.0, 1.0]), np.cos(0.15 * t + [0.0, 1.0])], 1)[:, [0, 2, 1, 3]] * 0.6
    gait[5:] = 0.0  # drive the joints briefly, then a passive collapse onto the knees (contacts, limits)
    acts = np.broadcast_to(gait[:, None, :], (100, B, 4)).astype(np.float32)
    _, out = rollout(step, s, p, acts)
    q_mjx = np.stack([o[1].qpos[0] for o in out])
    done = np.stack([o[3][0] for o in out])
    n = int(np.argmax(done)) if done.any() else len(done)  # compare the episode up to its end
    assert n >= 50, n

    m = env.mj_model
    s0 = take(jax.tree_util.tree_map(np.asarray, s), 0)
    data = np.clip((s0.profile - s0.z_base) / env.options.z_span, 0, 1)
    m.hfield_data[:] = np.concatenate([data, data])
    m.geom_pos[env._terrain_geom, 2] = s0.z_base
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = s0.qpos, s0.qvel
    q_c = []
    for a in acts[:, 0]:
        for _ in range(env.options.substeps):
            d.ctrl[:] = np.clip(env.options.kv * (_SPEEDS * np.sign(a) - d.qvel[3:]), -80 * np.abs(a), 80 * np.abs(a))
            mujoco.mj_step(m, d)
        q_c.append(d.qpos.copy())
    q_c = np.stack(q_c)[:n]
    err = np.abs(q_c - q_mjx[:n])
    print("max |q_C - q_MJX| over", n, "steps:", err.max(axis=0), "first 20:", err[:20].max())
    assert err[:20].max() < 0.01, err[:20].max(axis=0)
    assert err.max() < 0.05, err.max(axis=0)
    assert q_c[-1, 0] - q_c[0, 0] != 0.0  # it moved


@settings(max_examples=3, deadline=None)
@given(seed=st.integers(0, 2**30))
def test_insane_random_actions_stay_finite(sim, seed):
    env, reset, step = sim
    p = batch(LEVELS["Insane"]())
    _, s = reset(jax.random.split(jax.random.PRNGKey(seed), B), p)
    acts = np.asarray(jax.random.uniform(jax.random.PRNGKey(seed + 1), (60, B, 4), minval=-1, maxval=1))
    s, out = rollout(step, s, p, acts, key=seed)
    for o, st_, r, d, info in out:
        assert np.all(np.isfinite(o)) and np.all(np.isfinite(r))
        assert np.all(np.isfinite(st_.qpos)) and np.all(np.isfinite(st_.qvel))
        assert np.all((o[:, 14:] > 0) & (o[:, 14:] <= 1))


def test_validation():
    env = envs.make("walker")
    with pytest.raises(ValueError, match="roughness"):
        env.reset(jax.random.PRNGKey(0), make_params(roughness=11.0))
    with pytest.raises(ValueError, match="stair_steps"):
        env.reset(jax.random.PRNGKey(0), make_params(stair_steps=0.0))
    with pytest.raises(ValueError, match="unknown option"):
        envs.make("walker", substep=3)
    with pytest.raises(ValueError, match="substeps"):
        envs.make("walker", substeps=0)
    with pytest.raises(ValueError, match="no field"):
        make_params(rough=1.0)
    with pytest.raises(ValueError, match="matmul_precision"):
        envs.make("walker", matmul_precision="tf32")
    space = env.param_space
    assert space.names[0] == "roughness" and space.names[-1] == "stair_steps" and space.dim == 8
    v = space.from_vector(jnp.array([20.0, -1, 3, 1, 9, 0, 2, 0.0]))
    np.testing.assert_allclose(space.to_vector(v), [10, 0, 3, 1, 5, 0, 2, 1])
    d = env.default_params
    assert float(d.roughness) == 1.0 and float(d.pit_gap_high) == 0 and int(d.max_steps) == 2000


def test_lidar_and_hull_contact_on_hand_made_terrain():
    grid = T.make_grid(4)
    gx = grid.x_min + grid.dx * np.arange(grid.n)
    wall_x = 12.0
    prof = np.where(gx >= wall_x, 10.0, 0.0).astype(np.float32)  # ground 0, a 10 m wall at 12 m
    o = jnp.array([10.0, 2.0])
    frac = np.asarray(jax.jit(lambda p, o: L.lidar(p, grid, o))(jnp.asarray(prof), o))
    ang = 0.15 * np.arange(10)
    expect = []
    for a in ang:
        t_ground = 2.0 / np.cos(a)  # distance to the floor
        t_wall = (wall_x - grid.dx - 10.0) / np.sin(a) if a > 0 else np.inf  # face starts one cell before
        expect.append(min(t_ground, t_wall, C.LIDAR_RANGE) / C.LIDAR_RANGE)
    expect = np.array(expect)
    floor_hits = np.array([2.0 / np.cos(a) < (wall_x - grid.dx - 10.0) / max(np.sin(a), 1e-9) for a in ang])
    np.testing.assert_allclose(frac[floor_hits], expect[floor_hits], atol=1e-5)
    # Rays that reach the (one-cell-wide, near-vertical) face hit it within that cell.
    hit_x = 10.0 + frac[~floor_hits] * C.LIDAR_RANGE * np.sin(ang[~floor_hits])
    assert np.all((hit_x >= wall_x - grid.dx - 1e-4) & (hit_x <= wall_x + 1e-4))
    # Out of range: a hull high above the floor sees nothing.
    far = np.asarray(jax.jit(lambda p, o: L.lidar(p, grid, o))(jnp.zeros(grid.n), jnp.array([10.0, 50.0])))
    np.testing.assert_array_equal(far, 1.0)
    # Hull-ground test: clear at 1 m; touching when lowered (bottom at -8/30) or tilted (tail down).
    touch = jax.jit(jax.vmap(lambda x, z, a: L.hull_touches_ground(jnp.zeros(grid.n), grid, x, z, a)))
    got = np.asarray(touch(jnp.full(4, 10.0), jnp.array([1.0, 0.2, 0.6, 0.6]), jnp.array([0.0, 0.0, 0.8, 0.1])))
    np.testing.assert_array_equal(got, [False, True, True, False])


def _dot_precisions(env):
    """The precision attribute of every dot in one lowered (traced, not compiled) walker step."""
    import re

    s = jax.eval_shape(env.reset, jax.random.PRNGKey(0), env.default_params)[1]  # lowering needs only the shapes
    text = jax.jit(env.step).lower(jax.random.PRNGKey(1), s, jnp.zeros(4), env.default_params).as_text()
    return re.findall(r"dot_general.*?precision = \[(\w+), (\w+)\]", text)


def test_mjx_matrix_products_run_at_highest_precision_unless_asked_otherwise(sim):
    """On GPUs JAX's default float32 matmul is TF32, which changed walker contacts (docs/walker.md)."""
    found = _dot_precisions(sim[0])
    assert found and all(p == ("HIGHEST", "HIGHEST") for p in found), found[:5]
    fast = _dot_precisions(envs.make("walker", matmul_precision="default"))
    assert fast and all(p == ("DEFAULT", "DEFAULT") for p in fast), fast[:5]
