"""A small CPU learning run that must succeed, and the same run with a sign-flipped policy
gradient that must fail -- proof that the learning test detects a broken update.

Threshold: CartPole's random policy scores ~20; the cartpole preset (16 envs x 64 steps) reaches a
stochastic-policy return of 150+ (of a maximum 500) within 40 updates = 40,960 env steps in our
runs, while a flipped policy gradient drives the return *down* (the policy learns to topple the
pole, < 20). 150 sits far from both, so the test is not flaky yet needs real learning.
"""
import jax
import jax.numpy as jnp
import numpy as np

import envs
from shed_jax.student import PPOConfig, losses, make_student

THRESHOLD = 150.0
NUM_UPDATES = 40


def _train_and_evaluate(seed=0):
    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole"))
    levels = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], env.default_params)

    @jax.jit
    def run(key):
        k_init, k_train, k_eval0, k_eval1 = jax.random.split(key, 4)
        s = student.init(k_init)
        before = student.evaluate(s, k_eval0, levels, 16)
        s, m = student.train(s, k_train, levels, NUM_UPDATES)
        after = student.evaluate(s, k_eval1, levels, 16)
        return before, after, m

    before, after, m = run(jax.random.PRNGKey(seed))
    return float(before.mean()), float(after.mean()), m


def test_cartpole_learns():
    before, after, m = _train_and_evaluate()
    assert before < 50.0, before
    assert after >= THRESHOLD, (before, after)
    ret = np.asarray(m["episode_return"])
    assert np.nanmean(ret[-5:]) > np.nanmean(ret[:5]) + 50.0
    assert np.all(np.isfinite(np.asarray(m["loss"])))


def test_learning_test_fails_with_sign_flipped_policy_gradient(monkeypatch):
    original = losses.clipped_surrogate
    monkeypatch.setattr(losses, "clipped_surrogate", lambda *a: -original(*a))
    before, after, _ = _train_and_evaluate()
    assert after < THRESHOLD, (before, after)
    assert after < before, (before, after)  # the broken update actively makes the policy worse
