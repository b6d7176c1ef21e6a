"""Evaluation rollouts that stop early and fused evaluations: the same returns as the full-length
scan they replace, bit for bit (XLA:CPU), with the steps actually run reported.

The reference is the evaluation as it was written before the rollouts stopped early: one
``lax.scan`` of the full step limit per (level, episode) run, vmapped over the runs. Early stopping
keeps the batch's shape, so its equality is robust. A fused evaluation draws the same keys in a
larger batch; its float equality needs the backend to compute a row the same at both batch sizes,
which XLA:CPU does for cartpole and for the small lander batches below, not for every lander batch
(docs/running.md).
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from shed_jax.student import PPOConfig, make_student

SMALL = PPOConfig(num_envs=4, num_steps=32, update_epochs=2, num_minibatches=2, actor_hidden=(16,), critic_hidden=(16,))


def full_scan_evaluate(student, state, key, levels, num_episodes, max_steps=None, deterministic=False):
    """(returns [n, E], lengths [n, E]) of the full-length scan, keys drawn as `evaluate` draws them."""
    n = jax.tree_util.tree_leaves(levels)[0].shape[0]
    if max_steps is None:
        length = student.default_eval_steps
    else:
        length = int(max_steps)
        levels = levels.replace(max_steps=jnp.full_like(levels.max_steps, length))
    flat = jax.tree_util.tree_map(lambda x: jnp.repeat(x, num_episodes, axis=0), levels)
    env = student.env

    def one(k, level):
        k_reset, k_run = jax.random.split(k)
        obs, env_state = env.reset(k_reset, level)

        def body(c, kk):
            env_state, obs, ret, ep_len, finished = c
            k_act, k_step = jax.random.split(kk)
            action = student.act(state, k_act, obs.astype(jnp.float32), deterministic)
            obs, env_state, _, done, info = env.step(k_step, env_state, action, level)
            first = done & ~finished
            ret = jnp.where(first, info["episode_return"], ret)
            ep_len = jnp.where(first, info["episode_length"], ep_len)
            return (env_state, obs, ret, ep_len, finished | done), None

        c0 = (env_state, obs, jnp.zeros((), jnp.float32), jnp.zeros((), jnp.int32), jnp.zeros((), bool))
        (env_state, _, ret, ep_len, finished), _ = jax.lax.scan(body, c0, jax.random.split(k_run, length))
        return jnp.where(finished, ret, env_state.episode_return), jnp.where(finished, ep_len, env_state.time)

    rets, lens = jax.vmap(one)(jax.random.split(key, n * num_episodes), flat)
    return rets.reshape(n, num_episodes), lens.reshape(n, num_episodes)


def _levels(env, n, **fields):
    base = jax.tree_util.tree_map(lambda x: jnp.repeat(jnp.asarray(x)[None], n, 0), env.default_params)
    return base.replace(**{k: jnp.asarray(v, getattr(base, k).dtype) for k, v in fields.items()})


@pytest.fixture(scope="module")
def cart():
    env = envs.make("cartpole")
    student = make_student(env, SMALL)
    return env, student, jax.jit(student.init)(jax.random.PRNGKey(0))


def _eq(a, b):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_early_stop_equals_full_scan_and_runs_fewer_steps(cart):
    env, student, s = cart
    ev = jax.jit(student.evaluate_with_info, static_argnums=(3, 4, 5, 6))
    ref = jax.jit(lambda s, k, lv: full_scan_evaluate(student, s, k, lv, 4))
    levels = env.param_space.sample(jax.random.PRNGKey(3), (3,))  # own limits: 500 steps
    for seed in range(3):
        key = jax.random.PRNGKey(10 + seed)
        R, info = ev(s, key, levels, 4, None, False, 16)
        R_ref, L_ref = ref(s, key, levels)
        _eq(R, R_ref)
        _eq(info["lengths"], L_ref)
        # a random policy drops the pole within ~60 steps: the rollout stops at the first chunk
        # boundary after the last episode end, far below the 500-step limit
        longest = int(np.max(L_ref))
        assert longest < 200
        assert int(info["steps_run"]) == 16 * -(-longest // 16)
        assert info["env_steps"] == 3 * 4 * 500  # the nominal charge is unchanged
        for chunk in (1, 7, 64):  # results do not depend on the chunk; steps run round up to it
            R_c, info_c = ev(s, key, levels, 4, None, False, chunk)
            _eq(R_c, R_ref)
            _eq(info_c["lengths"], L_ref)
            assert int(info_c["steps_run"]) == min(500, chunk * -(-longest // chunk))


def test_an_episode_that_never_ends_runs_the_whole_limit(cart):
    env, student, s = cart
    # level 1 cannot fail (thresholds out of reach): its episodes last until the step limit
    thr = [2.4, 1e6, 2.4]
    ang = [0.2094, 1e6, 0.2094]
    levels = _levels(env, 3, x_threshold=thr, theta_threshold=ang)
    key = jax.random.PRNGKey(4)
    R, info = jax.jit(lambda s, k: student.evaluate_with_info(s, k, levels, 2))(s, key)
    R_ref, L_ref = jax.jit(lambda s, k: full_scan_evaluate(student, s, k, levels, 2))(s, key)
    _eq(R, R_ref)
    _eq(info["lengths"], L_ref)
    np.testing.assert_array_equal(np.asarray(info["lengths"])[1], [500, 500])
    assert int(info["steps_run"]) == 500
    # a step limit that is not a multiple of the chunk: the cut episode is recorded as the full scan's
    R, info = jax.jit(lambda s, k: student.evaluate_with_info(s, k, levels, 2, 37))(s, key)
    R_ref, L_ref = jax.jit(lambda s, k: full_scan_evaluate(student, s, k, levels, 2, 37))(s, key)
    _eq(R, R_ref)
    _eq(info["lengths"], L_ref)
    np.testing.assert_array_equal(np.asarray(info["lengths"])[1], [37, 37])
    assert int(info["steps_run"]) == 37


def test_traced_time_limit_beyond_the_scan_records_the_partial_episode(cart):
    env, student, s = cart
    # traced levels escape the eager check: level 0 never fails and has a 600-step limit > 500
    levels = _levels(env, 2, x_threshold=[1e6, 2.4], theta_threshold=[1e6, 0.2094], max_steps=[600, 500])
    key = jax.random.PRNGKey(5)
    R, info = jax.jit(lambda s, k, lv: student.evaluate_with_info(s, k, lv, 2))(s, key, levels)
    R_ref, L_ref = jax.jit(lambda s, k, lv: full_scan_evaluate(student, s, k, lv, 2))(s, key, levels)
    _eq(R, R_ref)
    _eq(info["lengths"], L_ref)
    np.testing.assert_array_equal(np.asarray(info["lengths"])[0], [500, 500])  # partial: cut by the scan
    assert int(info["steps_run"]) == 500


def test_fused_evaluation_equals_separate_ones(cart):
    env, student, s = cart
    a = env.param_space.sample(jax.random.PRNGKey(6), (3,))
    b = _levels(env, 2, x_threshold=[2.4, 1e6], theta_threshold=[0.2094, 1e6])  # b[1] runs to its limit
    ka, kb = jax.random.PRNGKey(7), jax.random.PRNGKey(8)

    @jax.jit
    def fused(s):
        return student.evaluate_many(s, [(ka, a, 4, None), (kb, b, 3, 40)])

    @jax.jit
    def separate(s):
        return student.evaluate_with_info(s, ka, a, 4), student.evaluate_with_info(s, kb, b, 3, 40)

    (Ra, ia), (Rb, ib) = fused(s)
    (Sa, ja), (Sb, jb) = separate(s)
    _eq(Ra, Sa)
    _eq(ia["lengths"], ja["lengths"])
    _eq(Rb, Sb)
    _eq(ib["lengths"], jb["lengths"])
    assert Ra.shape == (3, 4) and Rb.shape == (2, 3)
    assert (ia["env_steps"], ib["env_steps"]) == (ja["env_steps"], jb["env_steps"]) == (3 * 4 * 500, 2 * 3 * 40)
    np.testing.assert_array_equal(np.asarray(Rb)[1], 40.0)  # the level that cannot fail pays 1 per step to its limit
    # one rollout for both: as long as the longer of the two
    assert int(ia["steps_run"]) == int(ib["steps_run"]) == max(int(ja["steps_run"]), int(jb["steps_run"]))
    # and both equal the full scan
    R_ref, _ = full_scan_evaluate(student, s, kb, b, 3, 40)
    _eq(Rb, R_ref)


def test_an_inactive_request_records_nothing_and_ends_no_later(cart):
    """A request with ``active`` false (traced): its rows record nothing (returns and lengths 0) and the
    rollout ends when the active rows do; the active rows equal an active pair's rows, and with
    ``active`` true the fused results are the plain ones. One program for both."""
    env, student, s = cart
    a = env.param_space.sample(jax.random.PRNGKey(6), (3,))
    b = _levels(env, 2, x_threshold=[2.4, 1e6], theta_threshold=[0.2094, 1e6])  # b[1] runs to its 40-step limit
    ka, kb = jax.random.PRNGKey(7), jax.random.PRNGKey(8)
    short = _levels(env, 1, x_threshold=[2.4], theta_threshold=[0.2094])

    @jax.jit
    def fused(s, on):
        return student.evaluate_many(s, [(ka, short, 2, 8), (kb, b, 3, 40, on)])

    (Ra, ia), (Rb, ib) = fused(s, jnp.bool_(False))
    (Sa, ja), (Sb, jb) = fused(s, jnp.bool_(True))
    (Pa, pa), (Pb, pb) = jax.jit(lambda s: student.evaluate_many(s, [(ka, short, 2, 8), (kb, b, 3, 40)]))(s)
    np.testing.assert_array_equal(np.asarray(Rb), 0.0)
    np.testing.assert_array_equal(np.asarray(ib["lengths"]), 0)
    _eq(Ra, Sa)  # the active rows: the same batch, the same floats
    _eq(ia["lengths"], ja["lengths"])
    # one chunk of 16 steps covers the short request's 8; active, b[1] keeps it going to its limit of 40
    assert int(ia["steps_run"]) == 16 and int(ja["steps_run"]) == 40
    for x, y in ((Sa, Pa), (Sb, Pb), (ja["lengths"], pa["lengths"]), (jb["lengths"], pb["lengths"])):
        _eq(x, y)
    np.testing.assert_array_equal(np.asarray(Sb)[1], 40.0)


def test_vmapped_seeds_run_until_the_last_one_is_done(cart):
    env, student, s = cart
    states = jax.jit(jax.vmap(student.init))(jax.random.split(jax.random.PRNGKey(1), 3))  # one program, not op by op
    keys = jax.random.split(jax.random.PRNGKey(2), 3)
    levels = env.param_space.sample(jax.random.PRNGKey(3), (2,))
    R, info = jax.jit(jax.vmap(lambda s, k: student.evaluate_with_info(s, k, levels, 3)))(states, keys)
    ref = jax.jit(lambda s, k: full_scan_evaluate(student, s, k, levels, 3))  # one compile for the three seeds
    for i in range(3):
        s_i = jax.tree_util.tree_map(lambda x: x[i], states)
        R_ref, L_ref = ref(s_i, keys[i])
        _eq(R[i], R_ref)
        _eq(info["lengths"][i], L_ref)
        assert int(info["steps_run"][i]) == 16 * -(-int(np.max(L_ref)) // 16)  # each seed's own count


@pytest.mark.optimized  # bitwise: two programs
@pytest.mark.slow
def test_lander_early_stop_equals_the_full_scan():
    """Early stopping on the lander (a real physics step) equals the full-length scan. Fusion is
    checked exactly on cartpole above; on the lander it need not be bitwise, since XLA:CPU compiles
    batches of 80 and 180 runs to different reduction code (docs/running.md). One rollout pair
    only: each lander rollout adds about a minute of compile to the suite."""
    from shed_jax import eval_sets

    env = envs.make("lander")
    student = make_student(env, PPOConfig.for_env("lander", num_envs=4, num_steps=8, num_minibatches=1, update_epochs=1))
    s = jax.jit(student.init)(jax.random.PRNGKey(0))
    test = eval_sets.lander_test_set().to_params(env.default_params)
    heavy = jax.tree_util.tree_map(lambda x: x[jnp.array([7, 8])], test)  # g = -8.9, -6.0: crashes early
    ka = jax.random.PRNGKey(1)

    @jax.jit
    def run(s):
        return student.evaluate_with_info(s, ka, heavy, 2, 400), full_scan_evaluate(student, s, ka, heavy, 2, 400)

    (Ra, ia), (Ra_ref, La_ref) = run(s)
    _eq(Ra, Ra_ref)
    _eq(ia["lengths"], La_ref)
    longest = int(np.max(La_ref))
    assert longest < 400 and int(ia["steps_run"]) == 16 * -(-longest // 16)  # stopped early


# ------------------------------------------------------------------------------------------
# the loop: SHED's evaluation and the test set as one rollout
# ------------------------------------------------------------------------------------------


def _shed_loop(fused: bool, spec):
    """The h-MDP loop's ``init`` and ``run`` (vmapped over seeds, jitted) on a tiny cartpole student, with
    the test set fused into the teacher's evaluation or run after the step."""
    from shed_jax.loop import make_run
    from shed_jax.methods.hierarchical import HierarchicalTeacher, HMDPConfig

    class SeparateTests(HierarchicalTeacher):
        fuses_test_eval = False  # the loop evaluates the test set after the step, as before fusion

    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole", num_envs=4, num_steps=8, num_minibatches=1, update_epochs=1))
    cfg = HMDPConfig(updates_per_step=1, num_levels=2, num_eval_levels=3, num_eval_episodes=2, eval_max_steps=40,
                     budget_steps=2, ddpg_batch=4, real_capacity=16, ddpg_threshold=1)
    # h-MDP: the teacher without SHED's diffusion synthesiser (cheaper to compile), the same evaluation code
    method = (HierarchicalTeacher if fused else SeparateTests)(env, student, cfg, name="hmdp",
                                                               eval_levels=env.param_space.sample(jax.random.PRNGKey(42), (3,)))
    assert method.fuses_test_eval is fused
    init, run = make_run(student, method, env.param_space.sample(jax.random.PRNGKey(7), (2,)), spec)
    return jax.vmap(init), jax.jit(jax.vmap(run, in_axes=(0, None, None)), static_argnums=1)


@pytest.mark.optimized  # bitwise: two programs per comparison
def test_loop_fused_test_set_equals_separate_evaluation():
    """The loop with the test set fused into h-MDP's evaluation equals the loop that evaluates it after the
    step, bit for bit: every metric and the whole run state, with the static "always test"
    (test_episode_every 1) and with a traced schedule (test_episode_every 2, NaN where nothing was tested).

    Three programs, not four: the reference for both is the separate evaluation testing at every step.
    A schedule that skips test episodes leaves everything but the test metrics as they were, bit for bit
    (the loop's cond on ``tests_at``; test_loop.py::test_skipping_test_episodes_and_recording_one_level_change_only_the_records),
    so the separate run with the schedule is the always-testing one with NaN test metrics off the schedule."""
    from shed_jax.loop import LoopSpec

    def spec(every):
        return LoopSpec(steps_per_episode=2, num_episodes=3, test_episodes=3, test_max_steps=None, test_episode_every=every)

    def eq_trees(x, y):
        for a, b in zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y), strict=True):
            _eq(a, b)

    init, run_s = _shed_loop(False, spec(1))
    # one initial state for the three runs (the two methods' init is the same code: the class differs
    # only in fuses_test_eval)
    s0 = jax.jit(init)(jax.random.split(jax.random.PRNGKey(3), 2))
    out_s, m_s = run_s(s0, 6, 0)
    test_metrics = ("test_return", "test_return_per_level")
    for every in (1, 2):  # 1: static "always test"; 2: a traced schedule
        _, run_f = _shed_loop(True, spec(every))
        out_f, m_f = run_f(s0, 6, 0)
        eq_trees(out_f, out_s)  # the whole run state
        eq_trees({k: v for k, v in m_f.items() if k not in test_metrics}, {k: v for k, v in m_s.items() if k not in test_metrics})
        tested = spec(every).tests_at(np.arange(6))
        for k in test_metrics:  # the test metrics where tested, NaN elsewhere
            f, ref = np.asarray(m_f[k]), np.asarray(m_s[k])
            _eq(f[:, tested], ref[:, tested])
            assert np.all(np.isnan(f[:, ~tested])) and np.all(np.isfinite(ref))
        np.testing.assert_array_equal(np.isfinite(np.asarray(m_f["test_return"])), np.broadcast_to(tested, (2, 6)))
        assert np.all(np.asarray(m_f["test_return"])[:, tested] >= 1.0)  # cartpole pays 1 per step
    assert not spec(2).tests_at(np.arange(6)).all()  # the schedule skips some steps
