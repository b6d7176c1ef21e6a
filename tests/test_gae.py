"""GAE against a hand-computed example (with a termination and a truncation) and a naive loop."""
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings, strategies as st

from shed_jax.student import losses


def test_gae_hand_computed_with_termination_and_truncation():
    # gamma 0.9, lambda 0.8. Step 1 terminates (bootstrap 0), step 2 is truncated by the time
    # limit (bootstrap V(final_obs) = 10), step 3 continues (bootstrap V(s_4) = 3).
    rewards = jnp.array([1.0, 2.0, 3.0, 4.0])
    values = jnp.array([0.5, 1.0, 1.5, 2.0])
    final_values = jnp.array([1.0, 7.0, 10.0, 3.0])  # 7.0 must be ignored: termination
    terminated = jnp.array([False, True, False, False])
    dones = jnp.array([False, True, True, False])
    next_values = losses.bootstrap_values(final_values, terminated)
    np.testing.assert_allclose(next_values, [1.0, 0.0, 10.0, 3.0])
    adv, targets = losses.gae(rewards, values, next_values, dones, 0.9, 0.8)
    # deltas: 1.4, 1.0, 10.5, 4.7; A3 = 4.7; A2 = 10.5 (cut); A1 = 1.0 (cut); A0 = 1.4 + 0.72 * 1.0
    np.testing.assert_allclose(adv, [2.12, 1.0, 10.5, 4.7], rtol=1e-6)
    np.testing.assert_allclose(targets, [2.62, 2.0, 12.0, 6.7], rtol=1e-6)


def test_gae_batched_over_envs_matches_per_env():
    rng = np.random.default_rng(0)
    T, E = 7, 3
    r, v, nv = (rng.normal(size=(T, E)).astype(np.float32) for _ in range(3))
    d = rng.random((T, E)) < 0.3
    adv, tgt = losses.gae(r, v, nv, d, 0.99, 0.95)
    for e in range(E):
        a_e, t_e = losses.gae(r[:, e], v[:, e], nv[:, e], d[:, e], 0.99, 0.95)
        np.testing.assert_allclose(adv[:, e], a_e, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(tgt[:, e], t_e, rtol=1e-5, atol=1e-6)


@settings(max_examples=10, deadline=None)
@given(
    st.integers(1, 6),
    st.floats(0.0, 1.0),
    st.floats(0.0, 1.0),
    st.integers(0, 2**31 - 1),
)
def test_gae_matches_naive_loop(T, gamma, lam, seed):
    rng = np.random.default_rng(seed)
    r, v, nv = (rng.normal(size=T) for _ in range(3))
    d = rng.random(T) < 0.3
    expected = np.zeros(T)
    last = 0.0
    for t in reversed(range(T)):
        delta = r[t] + gamma * nv[t] - v[t]
        last = delta + gamma * lam * (0.0 if d[t] else 1.0) * last
        expected[t] = last
    adv, tgt = losses.gae(jnp.asarray(r, jnp.float32), jnp.asarray(v, jnp.float32), jnp.asarray(nv, jnp.float32), jnp.asarray(d), gamma, lam)
    np.testing.assert_allclose(adv, expected, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(tgt, expected + v, rtol=1e-4, atol=1e-4)
