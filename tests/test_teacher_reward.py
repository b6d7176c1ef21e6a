"""Teacher reward forms, cv guard/clip, and per-batch z-scoring, on hand-computed vectors."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from shed_jax.teacher.reward import (
    RewardConfig,
    code_cv,
    coefficient_of_variation,
    make_reward_fn,
    teacher_reward,
    zscore,
    zscore_mixed,
)

S = jnp.zeros(3)
UP = jnp.array([1.0, 2.0, 3.0])  # omega = [1, 2, 3]: mean 2, sample std 1 -> cv 0.5


def test_cv_hand_values():
    assert float(coefficient_of_variation(S, UP)) == pytest.approx(0.5, rel=1e-6)
    # same change pattern shifted by a baseline: cv depends on omega only
    assert float(coefficient_of_variation(S + 7.0, UP + 7.0)) == pytest.approx(0.5, rel=1e-6)
    # omega = [2, 4, 9]: mean 5, sample var ((9 + 1 + 16) / 2) = 13 -> cv = sqrt(13)/5
    assert float(coefficient_of_variation(S, jnp.array([2.0, 4.0, 9.0]))) == pytest.approx(math.sqrt(13) / 5, rel=1e-6)
    # a uniform improvement is perfectly fair
    assert float(coefficient_of_variation(S, jnp.full(3, 4.0))) == 0.0


def test_cv_guard_and_clip():
    # omega = [1, -1]: mean 0 -> denominator max(0, 1e-6); sqrt(2 / 1e-6) = 1414 -> clipped to 100
    assert float(coefficient_of_variation(jnp.zeros(2), jnp.array([1.0, -1.0]))) == 100.0
    # tiny mean just above the guard: omega = [0.0011, 0.0009], mean 1e-3, mean^2 = 1e-6, std = 1.414e-4
    cv = coefficient_of_variation(jnp.zeros(2), jnp.array([0.0011, 0.0009]))
    assert float(cv) == pytest.approx(math.sqrt(2e-8) / 1e-3, rel=1e-3)
    assert float(coefficient_of_variation(jnp.zeros(2), jnp.array([1.0, -1.0]), clip=5.0)) == 5.0
    with pytest.raises(ValueError, match="at least 2"):
        coefficient_of_variation(jnp.zeros(1), jnp.ones(1))


def test_paper_and_signed_forms():
    cfg = RewardConfig()  # paper_l1, eta 0.05
    assert float(teacher_reward(cfg, S, None, UP)) == pytest.approx(6.0 - 0.05 * 0.5, rel=1e-6)
    # L1 rewards a drop as much as a gain; signed_sum does not
    assert float(teacher_reward(cfg, S, None, -UP)) == pytest.approx(6.0 - 0.025, rel=1e-6)
    signed = RewardConfig(form="signed_sum", eta=10.0)
    assert float(teacher_reward(signed, S, None, -UP)) == pytest.approx(-6.0 - 10.0 * 0.5, rel=1e-6)
    assert float(teacher_reward(signed, S, None, UP)) == pytest.approx(6.0 - 5.0, rel=1e-6)


def test_code_mean_form_and_cv_term():
    s = jnp.array([1.0, 2.0, 3.0])
    s2 = jnp.array([4.0, 4.0, 4.0])
    assert float(teacher_reward(RewardConfig(form="code_mean"), s, None, s2)) == pytest.approx(2.0, rel=1e-6)
    # cv_c(s) = 100 * pop-std([1,2,3]) / 2 = 100 * sqrt(2/3) / 2; cv_c(s2) = 0
    cvc = 100 * math.sqrt(2 / 3) / 2
    assert float(code_cv(s)) == pytest.approx(cvc, rel=1e-6)
    r = teacher_reward(RewardConfig(form="code_mean", code_cv=True), s, None, s2)
    assert float(r) == pytest.approx(2.0 + 0.01 * cvc, rel=1e-6)
    # cv_c flips sign with a negative mean (documented behaviour of the official code)
    assert float(code_cv(-s)) == pytest.approx(-cvc, rel=1e-6)


def test_batched_and_jitted_match_single():
    key = jax.random.PRNGKey(0)
    s = 100 * jax.random.normal(key, (6, 10))
    s2 = s + 20 * jax.random.normal(jax.random.PRNGKey(1), (6, 10))
    fn = jax.jit(make_reward_fn(RewardConfig()))
    batched = fn(s, None, s2)
    single = jnp.stack([teacher_reward(RewardConfig(), s[i], None, s2[i]) for i in range(6)])
    np.testing.assert_allclose(batched, single, rtol=1e-5)
    np.testing.assert_allclose(jax.vmap(lambda a, b: fn(a, None, b))(s, s2), single, rtol=1e-5)


def test_zscore_hand_values():
    r = jnp.array([1.0, 2.0, 3.0, 4.0])
    std = math.sqrt(1.25)
    np.testing.assert_allclose(zscore(r), (np.array([1, 2, 3, 4]) - 2.5) / (std + 1e-6), rtol=1e-6)
    # mixed batch: real [1, 3] and synthetic [10, 20, 30] are normalised separately
    z = zscore_mixed(jnp.array([1.0, 3.0, 10.0, 20.0, 30.0]), jnp.arange(5) < 2)
    s_syn = math.sqrt(200 / 3)
    np.testing.assert_allclose(z, [-1 / (1 + 1e-6), 1 / (1 + 1e-6), -10 / (s_syn + 1e-6), 0.0, 10 / (s_syn + 1e-6)], rtol=1e-5)
    np.testing.assert_allclose(zscore_mixed(r, jnp.ones(4, bool)), zscore(r), rtol=1e-6)
    np.testing.assert_allclose(zscore_mixed(r, jnp.zeros(4, bool)), zscore(r), rtol=1e-6)
    # constant rewards map to zeros, not NaN
    np.testing.assert_array_equal(zscore(jnp.full(5, 3.0)), np.zeros(5))
    with pytest.raises(ValueError, match=r"real_mask \[B\] \(one flag per reward\), got shapes \(4,\) and \(5,\)"):
        zscore_mixed(r, jnp.ones(5, bool))


def test_config_validation():
    with pytest.raises(ValueError, match="form"):
        RewardConfig(form="l2")
    with pytest.raises(ValueError, match="eta"):
        RewardConfig(eta=-1.0)
    with pytest.raises(ValueError, match="code_cv"):
        RewardConfig(form="paper_l1", code_cv=True)
