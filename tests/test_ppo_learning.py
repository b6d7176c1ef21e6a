"""A small CPU learning run that must succeed, and the same run with a sign-flipped policy
gradient that must fail -- proof that the learning test detects a broken update.

Threshold: CartPole's random policy scores ~20; the cartpole preset (16 envs x 64 steps) reaches a
stochastic-policy return of 150+ (of a maximum 500) within 40 updates = 40,960 env steps, while a
flipped policy gradient drives the return *down* (the policy learns to topple the pole, < 20).
One seed is not enough: single seeds end anywhere between 150 and 500 (64 seeds, two CPU ISAs), and
the rounding of another CPU moves a seed's result by up to ~100. So each run trains NUM_SEEDS
students at once (vmapped) and the test checks their mean, with a lower floor for every seed.
"""
import jax
import jax.numpy as jnp
import numpy as np

import envs
from shed_jax.student import PPOConfig, losses, make_student

THRESHOLD = 150.0  # on the mean over seeds
SEED_FLOOR = 100.0  # every seed
NUM_UPDATES = 40
NUM_SEEDS = 8


def _train_and_evaluate(seed=0):
    """NUM_SEEDS students trained from keys split off PRNGKey(seed): per-seed mean evaluation
    returns before and after training [NUM_SEEDS], and the training metrics [NUM_SEEDS, NUM_UPDATES]."""
    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole"))
    levels = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], env.default_params)

    @jax.jit
    @jax.vmap
    def run(key):
        k_init, k_train, k_eval0, k_eval1 = jax.random.split(key, 4)
        s = student.init(k_init)
        before = student.evaluate(s, k_eval0, levels, 16)
        s, m = student.train(s, k_train, levels, NUM_UPDATES)
        after = student.evaluate(s, k_eval1, levels, 16)
        return before.mean(), after.mean(), m

    before, after, m = run(jax.random.split(jax.random.PRNGKey(seed), NUM_SEEDS))
    return np.asarray(before), np.asarray(after), m


def test_cartpole_learns():
    before, after, m = _train_and_evaluate()
    assert before.max() < 50.0, before
    # 5 root keys x 8 seeds x 2 ISAs (default, AVX2): mean min 276 vs 150, seed min 126 vs 100, gain min 121 vs 50
    assert after.mean() >= THRESHOLD, (before, after)
    assert after.min() >= SEED_FLOOR, after
    ret = np.asarray(m["episode_return"])
    gain = np.nanmean(ret[:, -5:], axis=1) - np.nanmean(ret[:, :5], axis=1)
    assert np.all(gain > 50.0), gain  # training returns rise in every seed
    assert np.all(np.isfinite(np.asarray(m["loss"])))


def test_learning_test_fails_with_sign_flipped_policy_gradient(monkeypatch):
    original = losses.clipped_surrogate
    monkeypatch.setattr(losses, "clipped_surrogate", lambda *a: -original(*a))
    before, after, _ = _train_and_evaluate()
    # 5 root keys x 8 seeds x 2 ISAs: every seed ends at <= 9.75 (vs 100), below its start by >= 7.3
    assert after.mean() < THRESHOLD and after.max() < SEED_FLOOR, (before, after)
    assert np.all(after < before), (before, after)  # the broken update actively makes every policy worse
