"""K students under one learning teacher (``students=K``, shed_jax/methods/parallel_students.py), on
the tiny CartPole setup of test_teacher_x.py: the K transitions a step stores, the students'
independence, student 0 against the one-student teacher, the pooled evaluation, and a resumed run."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from test_shed_method import TINY_TEACHER, _cartpole  # noqa: E402

from shed_jax.methods.learning_teacher import HMDPXConfig, LearningTeacher, SHEDXConfig, make_hmdp_x
from shed_jax.methods.parallel_students import ParallelStudents, StudentPool, pool_episodes, student_keys


def _build(k, **overrides):
    """hmdp-x with K students; evaluations of up to 40 steps, so that students' returns differ (CartPole's
    pole stays up for the 8 steps of TINY_TEACHER)."""
    env, student, eval_levels = _cartpole()
    config = HMDPXConfig(**{**TINY_TEACHER, "eval_max_steps": 40, "students": k, **overrides})
    return make_hmdp_x(env, student, config, eval_levels=eval_levels)


def _run(method, steps=3, new_student=None):
    """begin_episode, then ``steps`` steps; the teacher and student states before each step, the step keys."""
    new_student = new_student or method.pool.init

    @jax.jit
    def run(key):
        k_m, k_s, k_b, k_run = jax.random.split(key, 4)
        m, s = method.begin_episode(k_b, method.init(k_m), new_student(k_s))
        step_keys = jax.random.split(k_run, steps)

        def body(carry, k):
            m, s = carry
            m2, s2, info = method.step(k, m, s)
            return (m2, s2), (info, m, s)

        (m, s), (infos, ms, ss) = jax.lax.scan(body, (m, s), step_keys)
        return m, s, infos, ms, ss, step_keys

    return run(jax.random.PRNGKey(0))


def _at(tree, *index):
    return jax.tree_util.tree_map(lambda x: x[index], tree)


def test_students_config_and_builders():
    with pytest.raises(ValueError, match=r"^HMDPXConfig.students must be a positive int, got 0$"):
        HMDPXConfig(students=0)
    with pytest.raises(ValueError, match=r"^SHEDXConfig.students must be a positive int, got 2.0$"):
        SHEDXConfig(students=2.0)
    with pytest.raises(ValueError, match=r"^HMDPXConfig.students must be <= real_capacity \(16\)"):
        HMDPXConfig(real_capacity=16, ddpg_batch=4, students=17)
    one = _build(1)
    assert type(one) is LearningTeacher  # one student: the learning teacher itself, today's method
    four = _build(4)
    assert isinstance(four, ParallelStudents) and four.size == 4 and four.name == "hmdp-x"
    assert four.pool == StudentPool(four.base.student, 4) and four.config.students == 4
    assert four.hparam_names == one.hparam_names and four.fuses_test_eval
    # --set students=K reaches the config and the built experiment's student is the pool
    from shed_jax import experiment as xp
    from shed_jax.presets import build_experiment
    overrides = xp.route_method_overrides("hmdp-x", xp.parse_overrides(["students=3"]))
    xp.check_method_overrides("hmdp-x", overrides)
    exp = build_experiment("lander", "hmdp-x", "quick", method_overrides=overrides)
    assert exp.method_config.students == 3
    _, student, method, _ = xp.build(exp)
    assert isinstance(method, ParallelStudents) and student is method.pool


def test_student_keys_and_pooled_episodes():
    key = jax.random.PRNGKey(5)
    keys = np.asarray(student_keys(key, 3))
    np.testing.assert_array_equal(keys[0], np.asarray(key))  # student 0 draws as a lone student
    np.testing.assert_array_equal(keys[2], np.asarray(jax.random.fold_in(key, 2)))
    assert len({tuple(k) for k in keys}) == 3
    r = jnp.arange(2 * 3 * 4).reshape(2, 3, 4)  # [K=2, levels=3, episodes=4]
    np.testing.assert_array_equal(pool_episodes(r)[1], [4, 5, 6, 7, 16, 17, 18, 19])  # level 1: student 0's, then 1's


def test_pool_init_and_evaluate_are_each_students_own():
    env, student, levels = _cartpole()
    pool = StudentPool(student, 3)
    key = jax.random.PRNGKey(1)
    states = jax.jit(pool.init)(key)
    init_one = jax.jit(student.init)
    for i, k in enumerate(student_keys(key, 3)):
        one = init_one(k)
        for a, b in zip(jax.tree_util.tree_leaves(StudentPool.member(states, i)), jax.tree_util.tree_leaves(one)):
            np.testing.assert_array_equal(a, b)
    # a pool state's own (per-student) hyperparameters are taken per student
    hp = jax.tree_util.tree_map(lambda x: x * jnp.array([1.0, 2.0, 3.0], jnp.float32), states.hparams)
    again = jax.jit(pool.init)(jax.random.PRNGKey(2), hp)
    jax.tree_util.tree_map(np.testing.assert_array_equal, again.hparams, hp)
    # evaluation: student i with key i, episodes pooled per level
    lv = _at(levels, slice(0, 2))
    pooled = jax.jit(lambda s, k: pool.evaluate(s, k, lv, 2, 30))(states, key)
    assert pooled.shape == (2, 6) and np.ptp(np.asarray(pooled)) > 0
    one = jax.jit(lambda s, k: student.evaluate(s, k, lv, 2, 30))
    each = jnp.stack([one(StudentPool.member(states, i), k) for i, k in enumerate(student_keys(key, 3))])
    np.testing.assert_allclose(pooled, pool_episodes(each), rtol=1e-6)


def test_each_step_stores_one_transition_per_student():
    k, steps = 3, 3
    method = _build(k)
    base, cfg = method.base, method.config
    m, s, info, ms, ss, step_keys = _run(method, steps)
    real, ext = m.real, info.extras
    assert int(real.count) == k * steps and int(real.pos) == k * steps
    mdim = cfg.num_eval_levels
    for t in range(steps):
        k_act = jax.random.split(step_keys[t], 6)[0]
        for i, key_i in enumerate(student_keys(k_act, k)):
            row = t * k + i  # step after step, student after student
            ts = base.teacher_state(ms.s[t, i], t)
            np.testing.assert_allclose(real.data.s[row], ts, rtol=1e-6)
            np.testing.assert_allclose(real.data.s_next[row, :mdim], ext["teacher_state_per_student"][t, i], rtol=1e-6)
            assert float(real.data.s_next[row, -1]) == pytest.approx((t + 1) / cfg.budget_steps * cfg.state_scale)
            r = float(jnp.sum(ext["teacher_state_per_student"][t, i] - ms.s[t, i]) / cfg.reward_scale)
            assert float(real.data.r[row]) == pytest.approx(r, rel=1e-4, abs=1e-6)
            assert float(ext["teacher_reward_per_student"][t, i]) == float(real.data.r[row])
            assert float(real.data.done[row]) == float(t == cfg.budget_steps - 1)
            # the student's own action: the shared actor at its state plus its own exploration noise
            u = base.teacher.act(_at(ms.ddpg, t), ts, key_i, cfg.explore_sigma)
            np.testing.assert_allclose(real.data.u[row], u, rtol=1e-5, atol=1e-6)
            if t + 1 < steps:
                np.testing.assert_array_equal(ms.s[t + 1, i], ext["teacher_state_per_student"][t, i])
    # the untrained actor acts 0 everywhere (actor_out_init='zeros'): step 0's actions are the noise alone,
    # a different draw for each student
    u0 = np.asarray(real.data.u[:k])
    assert np.abs(u0).max() > 0 and all(not np.allclose(u0[a], u0[b]) for a in range(k) for b in range(a))
    # the record: the students' means, every student's levels, per-student entries
    np.testing.assert_allclose(info.teacher_reward, ext["teacher_reward_per_student"].mean(axis=1), rtol=1e-6)
    np.testing.assert_allclose(ext["teacher_state"], ext["teacher_state_per_student"].mean(axis=1), rtol=1e-6)
    e = method.pool.config.num_envs
    assert info.levels.shape == (steps, k * cfg.updates_per_step * e, base.codec.dim)
    np.testing.assert_array_equal(info.num_new_levels, ext["levels_trained_mask"].sum(axis=1))
    np.testing.assert_array_equal(info.env_steps_train, [cfg.updates_per_step * base.student.env_steps_per_update] * steps)
    assert np.isnan(ext["test_return_per_student"]).all() and ext["td_error_heldout"].shape == (steps,)
    np.testing.assert_array_equal(ext["real_size"], [k, 2 * k, 3 * k])
    # common random numbers per student: s' is the evaluation of that student with its own episode key
    assert len({tuple(np.asarray(x)) for x in m.eval_key}) == k
    for i in range(k):
        np.testing.assert_allclose(base.performance(m.eval_key[i], StudentPool.member(s, i))[0], m.s[i], rtol=1e-5)


def test_students_are_independent_and_student_0_is_the_lone_students_run():
    # no DDPG update within the run (ddpg_threshold above the transitions stored): the teacher is the
    # same for both runs, so student 0 of two must follow the one-student teacher's run
    cfg = dict(ddpg_threshold=15)
    two = _build(2, **cfg)
    one = _build(1, **cfg)
    m2, s2, info2, ms2, ss2, _ = _run(two, 3)
    m1, s1, info1, ms1, ss1, _ = _run(one, 3, new_student=one.student.init)
    assert int(m2.real.count) == 6 and int(m1.real.count) == 3
    np.testing.assert_allclose(m2.real.data.u[0:6:2], m1.real.data.u[:3], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(m2.real.data.s[0:6:2], m1.real.data.s[:3], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(m2.real.data.r[0:6:2], m1.real.data.r[:3], rtol=1e-4, atol=1e-4)
    for a, b in zip(jax.tree_util.tree_leaves(StudentPool.member(s2.params, 0)), jax.tree_util.tree_leaves(s1.params)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
    assert not np.allclose(m2.real.data.u[1], m2.real.data.u[0])
    # one step from the same teacher with student 1 replaced: student 0's step is unchanged, bit for bit
    m, s = _at(ms2, 1), _at(ss2, 1)
    other = StudentPool.member(two.pool.init(jax.random.PRNGKey(9)), 1)
    s_swapped = jax.tree_util.tree_map(lambda x, y: x.at[1].set(y), s, other)
    step = jax.jit(two.step)
    key = jax.random.PRNGKey(3)
    ma, sa, ia = step(key, m, s)
    mb, sb, ib = step(key, m, s_swapped)
    for a, b in zip(jax.tree_util.tree_leaves(StudentPool.member(sa, 0)), jax.tree_util.tree_leaves(StudentPool.member(sb, 0))):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ia.extras["teacher_state_per_student"][0], ib.extras["teacher_state_per_student"][0])
    assert not np.array_equal(ia.extras["teacher_state_per_student"][1], ib.extras["teacher_state_per_student"][1])
    pa, pb = (np.asarray(StudentPool.member(x.params, 1)["actor"]["MLP_0"]["Dense_0"]["kernel"]) for x in (sa, sb))
    assert not np.array_equal(pa, pb)
