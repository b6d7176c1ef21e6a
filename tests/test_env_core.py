"""envs.core: ParamSpace maps and validation, and the base class's auto-reset / episode bookkeeping.

Uses a tiny counter environment defined here so the tests compile in milliseconds.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from envs.core import Discrete, EnvParams, EnvState, Environment, ParamSpace


@struct.dataclass
class CounterParams(EnvParams):
    target: jax.Array = struct.field(default_factory=lambda: jnp.asarray(3.0, jnp.float32))
    scale: jax.Array = struct.field(default_factory=lambda: jnp.asarray(1.0, jnp.float32))


@struct.dataclass
class CounterState(EnvState):
    count: jax.Array
    start: jax.Array  # random draw made at reset (to see that resets are fresh)


class Counter(Environment):
    """Adds the action to a counter; terminates when it reaches ``target``; reward = scale * action."""

    name = "counter"

    @property
    def default_params(self):
        return CounterParams(max_steps=jnp.asarray(10, jnp.int32))

    @property
    def param_space(self):
        return ParamSpace(("target", "scale"), (1.0, 0.0), (5.0, 2.0), self.default_params)

    @property
    def param_bounds(self):
        return {"target": (0.0, 100.0, False, True)}

    def action_space(self, params=None):
        return Discrete(2)

    def reset_env(self, key, params):
        start = jax.random.uniform(key)
        st = CounterState(time=jnp.int32(0), episode_return=jnp.float32(0), count=jnp.float32(0), start=start)
        return jnp.stack([st.count, start]), st

    def step_env(self, key, state, action, params):
        count = state.count + action
        st = state.replace(count=count)
        return jnp.stack([count, state.start]), st, params.scale * action, count >= params.target, {}


def test_param_space_vector_roundtrip_and_clipping():
    env = Counter()
    ps = env.param_space
    vec = jnp.asarray([[2.0, 0.5], [9.0, -1.0]])
    p = ps.from_vector(vec)
    np.testing.assert_allclose(p.target, [2.0, 5.0])  # clipped to high
    np.testing.assert_allclose(p.scale, [0.5, 0.0])  # clipped to low
    assert p.max_steps.shape == (2,) and np.all(p.max_steps == 10)  # filled from base, broadcast
    np.testing.assert_allclose(ps.to_vector(p), [[2.0, 0.5], [5.0, 0.0]])


def test_from_vector_keeps_an_already_batched_base():
    ps = Counter().param_space
    base = ps.from_vector(jnp.asarray([[2.0, 0.5], [3.0, 1.5]]))
    base = base.replace(max_steps=jnp.asarray([7, 9], jnp.int32))
    p = ps.from_vector(jnp.asarray([[4.0, 1.0], [1.5, 0.25]]), base)
    assert p.max_steps.shape == (2,)  # not broadcast to (2, 2)
    np.testing.assert_array_equal(p.max_steps, [7, 9])  # per-level non-box fields kept
    np.testing.assert_allclose(ps.to_vector(p), [[4.0, 1.0], [1.5, 0.25]])


def test_param_space_unit_maps():
    ps = Counter().param_space
    np.testing.assert_allclose(ps.to_unit(jnp.asarray([1.0, 0.0])), [-1.0, -1.0])
    np.testing.assert_allclose(ps.to_unit(jnp.asarray([3.0, 1.5])), [0.0, 0.5])
    np.testing.assert_allclose(ps.from_unit(jnp.asarray([0.0, 0.5])), [3.0, 1.5])
    np.testing.assert_allclose(ps.from_unit(jnp.asarray([7.0, -7.0])), [5.0, 0.0])  # clipped


def test_param_space_sample_and_bounds():
    ps = Counter().param_space
    v = np.asarray(ps.sample_vector(jax.random.PRNGKey(0), (1000,)))
    assert v.shape == (1000, 2)
    assert np.all(v >= ps.low) and np.all(v <= ps.high)
    assert v[:, 0].std() > 0.5  # spread over the box, not constant
    sub = ps.with_bounds(low=(2.0, 0.5))
    np.testing.assert_allclose(sub.low, [2.0, 0.5])
    with pytest.raises(ValueError, match="leave the parameter space"):
        ps.with_bounds(high=(6.0, 2.0))
    with pytest.raises(ValueError, match="low > high"):
        ParamSpace(("a",), (1.0,), (0.0,), None)
    with pytest.raises(ValueError, match="last axis 2"):
        ps.from_vector(jnp.zeros((3,)))


def test_param_bounds_are_checked_eagerly():
    env = Counter()
    with pytest.raises(ValueError, match="'target'"):
        env.reset(jax.random.PRNGKey(0), env.default_params.replace(target=jnp.float32(-1.0)))


def test_auto_reset_and_episode_statistics():
    env = Counter()
    params = env.default_params  # target 3, scale 1
    obs, st = env.reset(jax.random.PRNGKey(0), params)
    step = jax.jit(env.step)
    rewards, dones = [], []
    for t in range(3):
        obs, st2, r, d, info = step(jax.random.PRNGKey(10 + t), st, jnp.int32(1), params)
        rewards.append(float(r))
        dones.append(bool(d))
        if t < 2:
            assert int(st2.time) == t + 1 and float(info["episode_return"]) == 0.0
        st_prev, st = st, st2
    assert dones == [False, False, True] and rewards == [1.0, 1.0, 1.0]
    assert bool(info["terminated"]) and not bool(info["truncated"])
    assert float(info["episode_return"]) == 3.0 and int(info["episode_length"]) == 3
    np.testing.assert_allclose(info["final_obs"][0], 3.0)  # pre-reset observation
    assert int(st.time) == 0 and float(st.episode_return) == 0.0 and float(st.count) == 0.0  # fresh episode
    assert float(st.start) != float(st_prev.start)  # a new random draw, not a cached state


def test_step_without_reset_equals_step_until_the_episode_ends_then_keeps_the_final_state():
    env = Counter()
    params = env.default_params  # target 3
    obs, st = env.reset(jax.random.PRNGKey(0), params)
    a, b = st, st
    for t in range(3):
        k = jax.random.PRNGKey(10 + t)
        oa, a, ra, da, ia = env.step(k, a, jnp.int32(1), params)
        ob, b, rb, db, ib = env.step_without_reset(k, b, jnp.int32(1), params)
        assert (float(ra), bool(da)) == (float(rb), bool(db))
        for key in ("episode_return", "episode_length", "terminated", "truncated", "final_obs"):
            np.testing.assert_array_equal(np.asarray(ia[key]), np.asarray(ib[key]))
        if t < 2:  # the episode goes on: identical obs and state
            np.testing.assert_array_equal(np.asarray(oa), np.asarray(ob))
            assert jax.tree_util.tree_all(jax.tree_util.tree_map(lambda x, y: bool(jnp.all(x == y)), a, b))
    # at the end: `step` has reset, `step_without_reset` holds the final state and obs
    assert int(a.time) == 0 and float(a.count) == 0.0
    assert int(b.time) == 3 and float(b.count) == 3.0 and float(b.episode_return) == 3.0
    np.testing.assert_array_equal(np.asarray(ob), np.asarray(ib["final_obs"]))


def test_truncation_at_max_steps():
    env = Counter()
    params = env.default_params.replace(max_steps=jnp.int32(4))
    obs, st = env.reset(jax.random.PRNGKey(0), params)
    for t in range(4):
        obs, st, r, d, info = env.step(jax.random.PRNGKey(t), st, jnp.int32(0), params)
    assert bool(d) and bool(info["truncated"]) and not bool(info["terminated"])
    assert int(info["episode_length"]) == 4


def test_action_checks_at_trace_time():
    env = Counter()
    obs, st = env.reset(jax.random.PRNGKey(0))
    with pytest.raises(TypeError, match="integer"):
        env.step(jax.random.PRNGKey(0), st, jnp.float32(1.0))
    with pytest.raises(ValueError, match="scalar"):
        env.step(jax.random.PRNGKey(0), st, jnp.zeros((2,), jnp.int32))
