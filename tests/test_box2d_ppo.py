"""The host-env PPO of experiments/bipedal_box2d_ppo.py: the rollout step's two halves
(``PPOStudent.act_step``, ``record_step``) against hand-computed bootstraps, and the worker processes
against Gymnasium's own vector env stepped with the same seed and actions."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from shed_jax.student import PPOConfig, make_student


def test_record_step_bootstraps_truncation_not_termination():
    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole", num_envs=3, num_steps=2, num_minibatches=1, normalize_returns=False,
                                                   normalize_observations=False))
    state = student.init(jax.random.PRNGKey(0))
    obs = jnp.array([[0.1, 0.0, 0.0, 0.0], [0.0, 0.2, 0.0, 0.0], [0.0, 0.0, 0.05, 0.0]], jnp.float32)
    obs_norm, acted = student.act_step(state.params, state.obs_norm, jax.random.PRNGKey(1), obs)
    np.testing.assert_array_equal(acted[0], obs)  # no normalisation: the policy sees the raw observation
    np.testing.assert_allclose(acted[3], student.value(state.params, obs), rtol=1e-6)
    final = obs + 1.0
    info = {"final_obs": final, "terminated": jnp.array([True, False, False]),
            "truncated": jnp.array([False, True, False]), "episode_return": jnp.array([5.0, 7.0, 0.0]),
            "episode_length": jnp.array([5, 7, 0])}
    reward, done = jnp.array([1.0, 2.0, 3.0]), jnp.array([True, True, False])
    _, row = student.record_step(state.params, state.hparams, obs_norm, state.ret_norm, acted, reward, done, info)
    v_final = student.value(state.params, final)
    np.testing.assert_allclose(row.next_values, [0.0, v_final[1], v_final[2]], rtol=1e-6)
    np.testing.assert_array_equal(row.rewards, reward)  # no return normalisation: the env's reward
    np.testing.assert_array_equal(row.dones, done)


def test_host_workers_step_like_gymnasiums_vector_env():
    gym = pytest.importorskip("gymnasium")
    from gymnasium.vector import AutoresetMode

    from experiments.bipedal_box2d_ppo import GYM_ID, HostEnvs

    host = HostEnvs(4, 2, seed=3)  # two workers of two envs; worker w seeds its envs from 3 + 100003 w
    try:
        obs = host.reset()
        refs = [gym.vector.SyncVectorEnv([lambda: gym.make(GYM_ID) for _ in range(2)],
                                         autoreset_mode=AutoresetMode.SAME_STEP) for _ in range(2)]
        ref_obs = np.concatenate([r.reset(seed=3 + 100_003 * w)[0] for w, r in enumerate(refs)])
        np.testing.assert_allclose(obs, ref_obs, rtol=1e-6)
        rng = np.random.default_rng(0)
        for _ in range(20):
            a = rng.uniform(-1, 1, (4, 4)).astype(np.float32)
            o, r, term, trunc, final, ep_ret, ep_len = host.step(a)
            outs = [ref.step(a[2 * w:2 * w + 2]) for w, ref in enumerate(refs)]
            np.testing.assert_allclose(o, np.concatenate([x[0] for x in outs]), rtol=1e-6)
            np.testing.assert_allclose(r, np.concatenate([x[1] for x in outs]), rtol=1e-6)
            assert o.shape == final.shape == (4, 24) and ep_len.dtype == np.int32
            np.testing.assert_array_equal(ep_ret[~(term | trunc)], 0.0)
    finally:
        host.close()
