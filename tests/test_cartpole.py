"""CartPole: dynamics parity with Gymnasium CartPole-v1, time limit, auto-reset, level space."""
import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.cartpole import LEVELS, CartPole


def test_dynamics_match_gymnasium():
    env = envs.make("cartpole")
    params = env.default_params
    step = jax.jit(env.step_env)
    gym_env = gym.make("CartPole-v1").unwrapped
    rng = np.random.default_rng(0)
    for episode in range(3):
        gym_obs, _ = gym_env.reset(seed=episode)
        _, state = env.reset(jax.random.PRNGKey(episode), params)
        state = state.replace(**{k: jnp.float32(v) for k, v in zip(("x", "x_dot", "theta", "theta_dot"), gym_obs)})
        for t in range(200):
            a = int(rng.integers(2))
            gym_obs, gym_r, gym_term, _, _ = gym_env.step(a)
            obs, state, r, term, _ = step(jax.random.PRNGKey(t), state, jnp.int32(a), params)
            np.testing.assert_allclose(np.asarray(obs), gym_obs, rtol=1e-4, atol=1e-5)
            assert float(r) == gym_r == 1.0
            assert bool(term) == gym_term
            if gym_term:
                break
        assert gym_term, "random policy should topple the pole within 200 steps"


def test_time_limit_truncates_and_auto_resets():
    env = CartPole()
    params = env.level("default").replace(max_steps=jnp.int32(3), gravity=jnp.float32(0.0))
    obs, state = env.reset(jax.random.PRNGKey(0), params)
    step = jax.jit(env.step)
    for t in range(3):
        # alternate pushes keep the pole up (zero gravity): only the time limit can end the episode
        obs, state, r, done, info = step(jax.random.PRNGKey(t), state, jnp.int32(t % 2), params)
    assert bool(done) and bool(info["truncated"]) and not bool(info["terminated"])
    assert float(info["episode_return"]) == 3.0 and int(info["episode_length"]) == 3
    assert int(state.time) == 0 and float(state.episode_return) == 0.0  # fresh episode
    assert np.all(np.abs(np.asarray(obs)) <= 0.05)  # reset observation
    assert not np.allclose(np.asarray(info["final_obs"]), np.asarray(obs))


def test_param_space_and_levels():
    env = CartPole()
    space = env.param_space
    assert space.names == ("gravity", "length", "force_mag") and space.dim == 3
    vec = jnp.array([[3.0, 0.7, 12.0], [50.0, 0.1, 8.0]])
    levels = space.from_vector(vec)
    np.testing.assert_allclose(space.to_vector(levels), [[3.0, 0.7, 12.0], [20.0, 0.25, 8.0]], rtol=1e-6)  # clipped
    np.testing.assert_array_equal(levels.max_steps, [500, 500])
    obs, _ = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 2), levels)
    assert obs.shape == (2, 4)
    assert float(env.level("moon").gravity) == pytest.approx(1.62)
    assert set(LEVELS) >= {"default", "moon"}
    with pytest.raises(ValueError, match="gravity"):
        env.reset(jax.random.PRNGKey(0), env.default_params.replace(gravity=jnp.float32(-1.0)))
    with pytest.raises(ValueError, match="unknown level"):
        env.level("mars")
