"""The outer loop: chunked runs equal one long run, episodes re-initialise the student, seeds vmap.

The method here is a minimal domain-randomisation teacher written for the test (one PPO update on
fresh uniform levels per budget step), so the loop's mechanics are checked independently of the
real methods, which have their own tests.
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from shed_jax.loop import LoopSpec, make_run
from shed_jax.methods.base import StepInfo
from shed_jax.student import PPOConfig, make_student


@dataclasses.dataclass(frozen=True)
class _UniformLevels:
    """One PPO update per budget step on `n` levels drawn uniformly from the env's box."""

    env: envs.Environment
    student: object
    n: int = 2
    name: str = "uniform"

    def init(self, key):
        return {"calls": jnp.zeros((), jnp.int32), "episodes": jnp.zeros((), jnp.int32)}

    def begin_episode(self, key, mstate, sstate):
        return {**mstate, "episodes": mstate["episodes"] + 1}, sstate

    def step(self, key, mstate, sstate):
        k_lv, k_tr = jax.random.split(key)
        vec = self.env.param_space.sample_vector(k_lv, (self.n,))
        levels = self.env.param_space.from_vector(vec)
        sstate, m = self.student.train(sstate, k_tr, levels, 1)
        info = StepInfo(
            levels=vec,
            env_steps_train=jnp.asarray(self.student.env_steps_per_update, jnp.int32),
            env_steps_eval=jnp.zeros((), jnp.int32),
            teacher_reward=jnp.asarray(jnp.nan, jnp.float32),
            num_new_levels=jnp.asarray(self.n, jnp.int32),
            extras={"update_step": sstate.update_step, "episodes": mstate["episodes"]},
        )
        return {**mstate, "calls": mstate["calls"] + 1}, sstate, info


def _cartpole_loop(spec: LoopSpec):
    """``init`` and the jitted ``run`` of the test method on a tiny cartpole student."""
    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole", num_envs=4, num_steps=8, update_epochs=1, num_minibatches=1))
    method = _UniformLevels(env, student)
    test_levels = env.param_space.sample(jax.random.PRNGKey(7), (2,))
    init, run = make_run(student, method, test_levels, spec)
    return jax.jit(init), jax.jit(run, static_argnums=1)


@pytest.fixture(scope="module")
def setup():
    return _cartpole_loop(LoopSpec(steps_per_episode=2, num_episodes=2, test_episodes=1, test_max_steps=20))


def _allclose_trees(a, b):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_chunks_equal_one_run_and_compile_once(setup):
    """Three chunks of 2 budget steps end where one scan of 6 does (the 6-step program is the one
    test_student_reinitialised_each_episode and the skipping test run), and one compile serves
    every 2-step chunk."""
    init, run = setup
    s0 = init(jax.random.PRNGKey(1))
    s_one, m_one = run(s0, 6, 0)
    s, ms = s0, []
    for done in (0, 2, 4):
        s, m = run(s, 2, done)
        ms.append(m)
        if done == 0:
            compiled = run._cache_size()
    assert run._cache_size() == compiled  # the later chunks reused the first one's program
    # two programs: XLA may order a float sum differently in each (bitwise equal on an AMD EPYC CPU)
    m_chunks = jax.tree_util.tree_map(lambda *x: np.concatenate(x), *ms)
    for a, b in zip(jax.tree_util.tree_leaves((s_one, m_one)), jax.tree_util.tree_leaves((s, m_chunks))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
    # the step counter and episode bookkeeping
    m_full = jax.tree_util.tree_map(np.asarray, m_one)
    np.testing.assert_array_equal(m_full["step"], [0, 1, 2, 3, 4, 5])
    np.testing.assert_array_equal(m_full["episode"], [0, 0, 1, 1, 2, 2])
    np.testing.assert_array_equal(m_full["step_in_episode"], [0, 1, 0, 1, 0, 1])


def test_student_reinitialised_each_episode(setup):
    init, run = setup
    # six steps in one scan: the program test_skipping_test_episodes_and_recording_one_level_change_only_the_records runs too
    _, m = run(init(jax.random.PRNGKey(1)), 6, 0)
    # one PPO update per step, counter restarts with the fresh student of each episode
    np.testing.assert_array_equal(np.asarray(m["info"].extras["update_step"]), [1, 2, 1, 2, 1, 2])
    np.testing.assert_array_equal(np.asarray(m["info"].extras["episodes"]), [1, 1, 2, 2, 3, 3])
    assert np.all(np.isfinite(np.asarray(m["test_return"])))
    assert np.all(np.asarray(m["test_return"]) >= 1.0)  # cartpole pays 1 per step


def test_vmapped_seeds_match_single_runs(setup):
    init, run = setup
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    run_batch = jax.jit(jax.vmap(run, in_axes=(0, None, None)), static_argnums=1)
    _, m_batch = run_batch(jax.jit(jax.vmap(init))(keys), 2, 0)
    for i in range(2):
        _, m_i = run(init(keys[i]), 2, 0)  # the fixture's init is jitted
        np.testing.assert_allclose(np.asarray(m_batch["test_return"][i]), np.asarray(m_i["test_return"]), rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(np.asarray(m_batch["info"].levels[i]), np.asarray(m_i["info"].levels))
    # different seeds do different things
    assert not np.array_equal(np.asarray(m_batch["info"].levels[0]), np.asarray(m_batch["info"].levels[1]))


def test_loop_spec_validation():
    with pytest.raises(ValueError, match="steps_per_episode"):
        LoopSpec(steps_per_episode=0, num_episodes=1)


def test_tests_at_schedule():
    """Test steps: every `test_every`-th step, in episodes 0, K, 2K, ... and always the last episode."""
    steps = np.arange(8)  # 4 episodes of 2 steps
    np.testing.assert_array_equal(LoopSpec(2, 4).tests_at(steps), [True] * 8)
    np.testing.assert_array_equal(LoopSpec(2, 4, test_episode_every=3).tests_at(steps),
                                  [True, True, False, False, False, False, True, True])  # episodes 0 and 3 (last)
    np.testing.assert_array_equal(LoopSpec(2, 4, test_episode_every=2).tests_at(steps),
                                  [True, True, False, False, True, True, True, True])  # 0, 2 and 3 (last)
    np.testing.assert_array_equal(LoopSpec(2, 4, test_every=2, test_episode_every=3).tests_at(steps),
                                  [False, True, False, False, False, False, False, True])
    # the same definition on traced values, as the compiled loop uses it
    traced = jax.jit(jax.vmap(LoopSpec(2, 4, test_episode_every=3).tests_at))(jnp.arange(8))
    np.testing.assert_array_equal(np.asarray(traced), LoopSpec(2, 4, test_episode_every=3).tests_at(steps))
    with pytest.raises(ValueError, match="test_episode_every"):
        LoopSpec(2, 4, test_episode_every=0)


def test_skipping_test_episodes_and_recording_one_level_change_only_the_records(setup):
    """Episodes without a test run give NaN test returns, a record of at most max_recorded_levels = 1 keeps
    each step's first level, and neither changes training. One loop with both switches (they touch
    different parts of a step's output: the test returns' cond and thin_levels on the record) against the
    fixture's loop, which tests at every step and records both of a step's levels (its
    max_recorded_levels, 64 by default, is above the 2 levels a step draws, so thin_levels returns the
    record itself, as None does; test_thin_levels_keeps_evenly_spaced_rows_and_aligned_extras)."""
    init_all, run_all = setup
    init, run = _cartpole_loop(LoopSpec(steps_per_episode=2, num_episodes=3, test_episodes=1, test_max_steps=20,
                                        test_episode_every=2, max_recorded_levels=1))
    key = jax.random.PRNGKey(5)
    s_all, m_all = run_all(init_all(key), 6, 0)  # the fixture's loop tests at every step
    s_skip, m_skip = run(init(key), 6, 0)
    ret_all, ret_skip = np.asarray(m_all["test_return"]), np.asarray(m_skip["test_return"])
    np.testing.assert_array_equal(np.isnan(ret_skip), [False, False, True, True, False, False])
    np.testing.assert_array_equal(ret_skip[[0, 1, 4, 5]], ret_all[[0, 1, 4, 5]])
    lv, lv_all = np.asarray(m_skip["info"].levels), np.asarray(m_all["info"].levels)
    assert lv.shape == (6, 1, lv_all.shape[-1]) and lv_all.shape[1] == 2
    np.testing.assert_array_equal(lv[:, 0], lv_all[:, 0])  # the kept row is the step's first level
    _allclose_trees(s_skip.student.params, s_all.student.params)  # training untouched, bit for bit
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="max_recorded_levels"):
            LoopSpec(steps_per_episode=1, num_episodes=1, max_recorded_levels=bad)


def test_thin_levels_keeps_evenly_spaced_rows_and_aligned_extras():
    from shed_jax.methods.base import thin_levels

    levels = jnp.arange(10 * 3, dtype=jnp.float32).reshape(10, 3)
    info = StepInfo(levels=levels, env_steps_train=jnp.int32(7), env_steps_eval=jnp.int32(0),
                    teacher_reward=jnp.float32(1.5), num_new_levels=jnp.int32(10),
                    extras={"levels_trained_mask": jnp.arange(10) % 2 == 0, "per_update": jnp.arange(10.0), "loss": jnp.float32(2.0)})
    thin = thin_levels(info, 4)
    rows = [0, 3, 6, 9]  # round(linspace(0, 9, 4)): first and last row of the step, evenly between
    np.testing.assert_array_equal(np.asarray(thin.levels), np.asarray(levels)[rows])
    np.testing.assert_array_equal(np.asarray(thin.extras["levels_trained_mask"]), [True, False, True, False])
    np.testing.assert_array_equal(np.asarray(thin.extras["per_update"]), np.arange(10.0))  # not a levels_ entry
    assert int(thin.num_new_levels) == 10 and int(thin.env_steps_train) == 7  # counts stay exact
    assert thin_levels(info, None) is info and thin_levels(info, 10) is info
    # jittable: the rows are static
    np.testing.assert_array_equal(np.asarray(jax.jit(lambda i: thin_levels(i, 4))(info).levels), np.asarray(levels)[rows])
