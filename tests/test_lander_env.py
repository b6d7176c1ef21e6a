"""Lunar lander: levels, spaces, bad input, engines, wind, observation, rewards, auto-reset, jit/vmap/scan.

One compiled batched step is shared by most tests (module-level cache) to keep CPU time low.
"""
import functools

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

import envs
from envs import physics2d

MASS = np.asarray([4.8166667, 0.0711111, 0.0711111])


def system_velocity(state):
    """Mass-weighted velocity of hull + legs (internal joint forces cancel in it)."""
    v = np.asarray(state.world.bodies.vel)
    return np.einsum("b,nbk->nk", MASS, v) / MASS.sum()
from envs.lander import heuristic, make_params
from envs.lander import model as M
from envs.lander.env import LanderParams, assign_reward, observation, shaping


@functools.lru_cache(maxsize=None)
def env(continuous=False):
    return envs.make("lander-continuous" if continuous else "lander")


@functools.lru_cache(maxsize=None)
def batched():
    """jit(vmap(reset)), jit(vmap(step)) for the discrete lander."""
    e = env(False)
    return jax.jit(jax.vmap(e.reset)), jax.jit(jax.vmap(e.step))


def levels(n, **kw):
    base = dict(max_steps=1000, gravity=-10.0, enable_wind=False, wind_power=15.0, turbulence_power=1.5)
    base.update(kw)
    return make_params(**{k: np.broadcast_to(np.asarray(v), (n,)) for k, v in base.items()})


def test_params_spaces_and_registry():
    e = env(False)
    assert e.name == "lander" and env(True).name == "lander-continuous"
    p = e.default_params
    assert isinstance(p, LanderParams)
    assert int(p.max_steps) == 1000 and float(p.gravity) == -10.0 and not bool(p.enable_wind)
    assert float(p.wind_power) == 15.0 and float(p.turbulence_power) == 1.5
    ps = e.param_space
    assert ps.names == ("gravity", "wind_power", "turbulence_power")
    np.testing.assert_allclose(ps.low, [-11.99, 0, 0])
    np.testing.assert_allclose(ps.high, [-0.01, 20, 2])
    assert e.observation_space().shape == (8,)
    assert e.action_space().n == 4 and env(True).action_space().shape == (2,)


@pytest.mark.parametrize("field,value", [("gravity", 0.0), ("gravity", -12.0), ("wind_power", 20.5),
                                         ("turbulence_power", -0.1)])
def test_out_of_range_params_raise_eagerly(field, value):
    e = env(False)
    bad = e.default_params.replace(**{field: jnp.float32(value)})
    with pytest.raises(ValueError, match=f"'{field}'"):
        e.reset(jax.random.PRNGKey(0), bad)


def test_from_vector_clips_into_the_box():
    p = env(False).param_space.from_vector(jnp.asarray([[-20.0, 30.0, -1.0], [-5.0, 3.0, 0.5]]))
    np.testing.assert_allclose(p.gravity, [-11.99, -5.0])
    np.testing.assert_allclose(p.wind_power, [20.0, 3.0])
    np.testing.assert_allclose(p.turbulence_power, [0.0, 0.5])
    assert p.max_steps.dtype == jnp.int32 and p.enable_wind.dtype == jnp.bool_


def test_wrong_actions_raise_at_trace_time():
    # traced only (jax.eval_shape), never run: the errors come while the step is traced
    obs, s = jax.eval_shape(env(False).reset, jax.random.PRNGKey(0))
    with pytest.raises(TypeError):
        jax.eval_shape(env(False).step, jax.random.PRNGKey(0), s, jnp.float32(1.0))
    with pytest.raises(ValueError):
        jax.eval_shape(env(False).step, jax.random.PRNGKey(0), s, jnp.zeros((2,), jnp.int32))
    obs, s = jax.eval_shape(env(True).reset, jax.random.PRNGKey(0))
    with pytest.raises(ValueError):
        jax.eval_shape(env(True).step, jax.random.PRNGKey(0), s, jnp.zeros((3,), jnp.float32))
    with pytest.raises(TypeError):
        jax.eval_shape(env(True).step, jax.random.PRNGKey(0), s, jnp.zeros((2,), jnp.int32))


def test_reset_statistics_and_observation_normalisation():
    reset, _ = batched()
    n = 64
    obs, s = reset(jax.random.split(jax.random.PRNGKey(1), n), levels(n))
    obs = np.asarray(obs)
    # docs/design.md §13.1 / docs/lander.md "Parity" post-reset probes (Gymnasium): x +-0.008, y in [1.40, 1.42], |vx| <= 0.80, no legs
    assert np.all(np.abs(obs[:, 0]) <= 0.0085) and np.all((obs[:, 1] > 1.395) & (obs[:, 1] < 1.425))
    assert np.all(np.abs(obs[:, 2]) <= 0.81) and np.all(obs[:, 6:] == 0)
    # Gymnasium's exact linear response of the first no-op step (measured, 200 seeds):
    # omega_obs = -0.2265 vx_obs, angle = -0.01144 vx_obs, y = 1.41092 + 0.0225 vy_obs
    np.testing.assert_allclose(obs[:, 5], -0.2265 * obs[:, 2], atol=2e-3)
    np.testing.assert_allclose(obs[:, 4], -0.01144 * obs[:, 2], atol=2e-4)
    np.testing.assert_allclose(obs[:, 1], 1.41092 + 0.0225 * obs[:, 3], atol=2e-4)
    # the observation formula from the state
    m = env(False).model
    o = jax.vmap(lambda w, c: observation(m, w, c))(s.world, s.leg_contact)
    origin = np.asarray(jax.vmap(lambda b: physics2d.body_origin(m, b))(s.world.bodies))[:, 0]
    np.testing.assert_allclose(o[:, 0], (origin[:, 0] - 10.0) / 10.0, rtol=1e-5)
    np.testing.assert_allclose(o[:, 1], (origin[:, 1] - (M.H / 4 + 0.6)) / (M.H / 2), rtol=1e-5)
    np.testing.assert_allclose(o[:, 2], np.asarray(s.world.bodies.vel)[:, 0, 0] * 0.2, rtol=1e-5)
    np.testing.assert_allclose(o[:, 3], np.asarray(s.world.bodies.vel)[:, 0, 1] * (M.H / 2) / 50, rtol=1e-5)
    np.testing.assert_allclose(o[:, 5], np.asarray(s.world.bodies.omega)[:, 0] * 0.4, rtol=1e-5)


def test_gravity_per_env_in_a_vmapped_batch():
    reset, step = batched()
    g = np.asarray([-0.5, -3.0, -10.0, -11.99])
    p = levels(4, gravity=g)
    keys = jax.random.split(jax.random.PRNGKey(2), 4)
    obs, s = reset(keys, p)
    vy = [system_velocity(s)[:, 1]]
    for t in range(5):
        obs, s, r, d, _ = step(jax.random.split(jax.random.PRNGKey(10 + t), 4), s, jnp.zeros(4, jnp.int32), p)
        vy.append(system_velocity(s)[:, 1])
    dv = np.diff(np.stack(vy), axis=0)  # free flight, no engines, no wind: exactly g dt per step
    np.testing.assert_allclose(dv, np.broadcast_to(g * 0.02, dv.shape), rtol=2e-3, atol=2e-5)


def test_engine_impulses_point_the_right_way():
    reset, step = batched()
    p = levels(4)
    k = jax.random.split(jax.random.PRNGKey(3), 4)
    obs, s = reset(jnp.stack([k[0]] * 4), p)  # four copies of one episode
    ks = jnp.stack([jax.random.PRNGKey(7)] * 4)  # same dispersion for every copy
    obs, s2, r, d, _ = step(ks, s, jnp.arange(4, dtype=jnp.int32), p)
    v = np.asarray(s2.world.bodies.vel)[:, 0]
    w = np.asarray(s2.world.bodies.omega)[:, 0]
    dv, dw = v - v[0], w - w[0]
    # main engine: up by about 13 * (4/30) / m_total (dispersion +-1/15 of the arm), little sideways
    total = 4.8167 + 2 * 0.0711
    assert 13 * (4 / 30 - 2 / 30) / total < dv[2, 1] < 13 * (4 / 30 + 2 / 30) / 4.8167
    assert abs(dv[2, 0]) < 0.05
    # action 1 (left orientation engine) pushes left and spins counter-clockwise; 3 the mirror image
    assert dv[1, 0] < 0 and dw[1] > 0 and dv[3, 0] > 0 and dw[3] < 0
    # fuel costs: 0.3 for the main engine, 0.03 for a side engine, on top of the shaping change
    sh = lambda o: float(shaping(o))
    for a, cost in [(0, 0.0), (2, 0.30), (1, 0.03), (3, 0.03)]:
        np.testing.assert_allclose(float(r[a]), sh(obs[a]) - float(s.prev_shaping[a]) - cost, atol=1e-3)


def test_wind_only_when_enabled_and_legs_off_the_ground():
    reset, step = batched()
    key = jax.random.PRNGKey(4)
    p = levels(4, enable_wind=np.asarray([False, False, True, True]), wind_power=np.asarray([0.0, 20.0, 0.0, 20.0]),
               turbulence_power=np.asarray([0.0, 2.0, 0.0, 2.0]))
    obs, s = reset(jnp.stack([key] * 4), p)
    s = s.replace(wind_idx=jnp.full((4,), 40, jnp.int32), torque_idx=jnp.full((4,), 40, jnp.int32))
    ks = jnp.stack([jax.random.PRNGKey(8)] * 4)
    obs2, s2, *_ = step(ks, s, jnp.zeros(4, jnp.int32), p)
    v = system_velocity(s2)[:, 0] - system_velocity(s)[:, 0]  # resets with wind on differ: use the change
    np.testing.assert_allclose(v[1], v[0], atol=1e-6)  # disabled: power is irrelevant
    np.testing.assert_allclose(v[2], v[0], atol=1e-6)  # enabled with zero power
    wave = np.tanh(np.sin(0.02 * 40) + np.sin(0.01 * np.pi * 40))
    expected = 20.0 * wave * 0.02 / MASS.sum()  # force on the hull moves the whole mechanism
    np.testing.assert_allclose(v[3] - v[0], expected, rtol=0.05)
    np.testing.assert_array_equal(np.asarray(s2.wind_idx), [40, 40, 41, 41])
    # a leg touched the ground on the previous step: no wind, indices frozen
    s_leg = s.replace(leg_contact=jnp.asarray([[True, False]] * 4))
    _, s3, *_ = step(ks, s_leg, jnp.zeros(4, jnp.int32), p)
    np.testing.assert_array_equal(np.asarray(s3.wind_idx), [40, 40, 40, 40])


def test_terminal_reward_rules():
    shaped = jnp.asarray([3.5, 3.5, 3.5, 3.5])
    crashed = jnp.asarray([False, True, False, True])
    asleep = jnp.asarray([False, False, True, True])
    r, t = assign_reward(shaped, crashed, asleep)
    np.testing.assert_allclose(r, [3.5, -100.0, 100.0, 100.0])  # sleep wins, terminal replaces shaping
    np.testing.assert_array_equal(t, [False, True, True, True])
    o = jnp.asarray([0.3, 0.4, 0.6, 0.8, -0.2, 0.0, 1.0, 0.0])
    np.testing.assert_allclose(shaping(o), -100 * 0.5 - 100 * 1.0 - 100 * 0.2 + 10, rtol=1e-6)


def test_crash_out_of_bounds_and_auto_reset_keep_the_level():
    reset, step = batched()  # a batch of 4, as the other tests' (one compile of each program)
    p = levels(4, gravity=np.asarray([-3.0, -7.0, -3.0, -7.0]))
    obs, s = reset(jax.random.split(jax.random.PRNGKey(5), 4), p)
    bodies = s.world.bodies
    # push envs 0 and 2 outside |x| >= 1 (x < 0) and sink envs 1 and 3's hulls into the ground
    shift = jnp.asarray([[[-10.5, 0.0]], [[0.0, -13.333 + 0.5]]] * 2)
    s_bad = s.replace(world=s.world.replace(bodies=bodies.replace(com=bodies.com + shift)))
    obs2, s2, r, d, info = step(jax.random.split(jax.random.PRNGKey(6), 4), s_bad, jnp.zeros(4, jnp.int32), p)
    np.testing.assert_allclose(r, [-100.0] * 4)
    assert np.all(np.asarray(d)) and np.all(np.asarray(info["terminated"]))
    # fresh episodes of the same levels: start pose, new terrain, time 0, same gravity
    assert np.all(np.abs(np.asarray(obs2)[:, 1] - 1.41) < 0.015) and np.all(np.asarray(s2.time) == 0)
    assert not np.any(np.all(np.isclose(np.asarray(s2.terrain_y), np.asarray(s.terrain_y)), axis=1))
    np.testing.assert_allclose(info["episode_return"], [-100.0] * 4)
    assert np.all(np.asarray(info["final_obs"])[::2, 0] <= -1.0)


def test_determinism_and_key_dependence():
    reset, step = batched()  # a batch of 4, as the other tests'
    p = levels(4)
    k = jnp.stack([jax.random.PRNGKey(9)] * 4)
    o1, s1 = reset(k, p)
    np.testing.assert_array_equal(o1[0], o1[3])
    np.testing.assert_array_equal(s1.terrain_y[0], s1.terrain_y[3])
    o2, s2 = reset(jax.random.split(jax.random.PRNGKey(9), 4), p)
    assert not np.allclose(s2.terrain_y[0], s2.terrain_y[1])
    a = jax.vmap(lambda o: heuristic(o, False))(o1)
    r1 = step(k, s1, a, p)
    r2 = step(k, s1, a, p)
    for x, y in zip(jax.tree_util.tree_leaves(r1), jax.tree_util.tree_leaves(r2)):
        np.testing.assert_array_equal(x, y)


def test_heuristic_hand_computed_cases():
    o = jnp.asarray([0.2, 0.5, 0.1, -0.3, 0.05, 0.02, 0.0, 0.0])
    # angle_targ = clip(0.1 + 0.1) = 0.2; hover_targ = 0.11; angle_todo = 0.5*(0.2-0.05) - 0.02 = 0.055
    # hover_todo = 0.5*(0.11-0.5) + 0.15 = -0.045 -> discrete: angle_todo > 0.05 -> 1
    assert int(heuristic(o, False)) == 1
    np.testing.assert_allclose(heuristic(o, True), [np.clip(20 * -0.045 - 1, -1, 1), -1.0], atol=1e-5)
    o = jnp.asarray([0.0, 0.2, 0.0, -0.5, 0.0, 0.0, 1.0, 0.0])  # leg down: hover_todo = 0.25 > 0.05 -> main
    assert int(heuristic(o, False)) == 2
    np.testing.assert_allclose(heuristic(o, True), [1.0, 0.0], atol=1e-6)
    batch = jnp.zeros((5, 8))
    assert jax.vmap(lambda x: heuristic(x, False))(batch).shape == (5,)


@settings(max_examples=3, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_random_levels_and_actions_stay_finite(seed):
    """256 envs x 32 steps per example of random levels (wind on for half) and random actions."""
    run = _random_rollout()
    obs, rew = run(jax.random.PRNGKey(seed))
    assert np.all(np.isfinite(np.asarray(obs))) and np.all(np.isfinite(np.asarray(rew)))
    assert np.all(np.abs(np.asarray(rew)) <= 100.0 + 1e-3 + 0 * np.asarray(rew))


@functools.lru_cache(maxsize=None)
def _random_rollout(n=256, t=32):
    e = env(False)

    def run(key):
        k_lv, k_r, k_s, k_a = jax.random.split(key, 4)
        p = e.param_space.sample(k_lv, (n,))
        p = p.replace(enable_wind=jax.random.bernoulli(k_lv, 0.5, (n,)), max_steps=jnp.full((n,), 20, jnp.int32))
        obs, s = jax.vmap(e.reset)(jax.random.split(k_r, n), p)

        def body(c, k):
            obs, s = c
            ka, ks = jax.random.split(k)
            a = jax.random.randint(ka, (n,), 0, 4)
            obs, s, r, d, _ = jax.vmap(e.step)(jax.random.split(ks, n), s, a, p)
            return (obs, s), (obs, r)

        _, (o, r) = jax.lax.scan(body, (obs, s), jax.random.split(k_s, t))
        return o, r

    return jax.jit(run)


def test_render_frame():
    e = env(False)
    reset, _ = batched()  # the shared compiled reset (batch 4), not an op-by-op one; its first state
    obs, s = reset(jnp.stack([jax.random.PRNGKey(0)] * 4), levels(4))
    f = e.render(jax.tree_util.tree_map(lambda x: x[0], s))
    assert f.shape == (400, 600, 3) and f.dtype == np.uint8
    assert (f == 0).all(-1).mean() > 0.05 and (f == 255).all(-1).mean() > 0.3  # ground and sky
    assert ((f[..., 0] == 128) & (f[..., 1] == 102)).sum() > 200  # the lander's colour
