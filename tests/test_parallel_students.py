"""K students under one learning teacher (``students=K``, shed_jax/methods/parallel_students.py), on
the tiny CartPole setup of test_teacher_x.py: the K transitions a step stores, the students'
independence, student 0 against the one-student teacher, test returns and evaluations pooled over
the students, and a run state with the students' axis saved and restored."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from test_shed_method import TINY_TEACHER, _cartpole  # noqa: E402

from shed_jax.methods.base import EvalRequest
from shed_jax.methods.learning_teacher import HMDPXConfig, LearningTeacher, SHEDXConfig, make_hmdp_x
from shed_jax.methods.parallel_students import ParallelStudents, StudentPool, pool_episodes, student_keys
from shed_jax.student.config import PPOHyperparams


def _build(k, **overrides):
    """hmdp-x with K students; evaluations of up to 40 steps, so that students' returns differ (CartPole's
    pole stays up for the 8 steps of TINY_TEACHER)."""
    env, student, eval_levels = _cartpole()
    config = HMDPXConfig(**{**TINY_TEACHER, "eval_max_steps": 40, "students": k, **overrides})
    return make_hmdp_x(env, student, config, eval_levels=eval_levels)


TEST_EPISODES = 2


def _runner(method, steps=3):
    """Jitted ``run(key, students)``: begin_episode on the given fresh students, then ``steps`` steps with
    the test set (2 evaluation levels, as the loop's fused test) -> (final teacher and student states,
    records, test returns, the states before each step, the step keys)."""
    tests = _at(getattr(method, "base", method).eval_params, slice(0, 2))

    @jax.jit
    def run(key, students):
        k_m, k_b, k_run = jax.random.split(key, 3)
        m, s = method.begin_episode(k_b, method.init(k_m), students)
        step_keys = jax.random.split(k_run, steps)

        def body(carry, k):
            m, s = carry
            test = EvalRequest(jax.random.fold_in(k, 7), tests, TEST_EPISODES, 20)
            m2, s2, info, test_returns = method.step_with_test(k, m, s, test)
            return (m2, s2), (info, test_returns, m, s)

        (m, s), (infos, test_returns, ms, ss) = jax.lax.scan(body, (m, s), step_keys)
        return m, s, infos, test_returns, ms, ss, step_keys

    return run


# no DDPG update within these runs (ddpg_threshold above the 6 transitions stored), so the teacher stays
# the same and student 0 of two can be compared with the lone student; the untrained actor is flax's
# (not zeros), so actions depend on the state
SAME_TEACHER = dict(ddpg_threshold=15, actor_out_init="lecun")
KEY, STUDENT_KEY = jax.random.PRNGKey(0), jax.random.PRNGKey(11)


@pytest.fixture(scope="module")
def two():
    method = _build(2, **SAME_TEACHER)
    run = _runner(method)
    return method, run, run(KEY, method.pool.init(STUDENT_KEY))


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


def test_the_ddpg_teacher_stores_and_scores_a_batch_as_its_transitions_one_by_one():
    from shed_jax.teacher.buffers import Transition
    from shed_jax.teacher.ddpg import DDPGConfig, make_ddpg
    from shed_jax.teacher.ddpg_teacher import DDPGTeacher

    teacher = DDPGTeacher(make_ddpg(DDPGConfig(3, 2, hidden=(8, 8))), capacity=4, batch_size=2)
    st, buf = jax.jit(teacher.init)(jax.random.PRNGKey(0))
    # jitted: one program per call shape, not op by op (a store copies values, so the bitwise checks hold)
    store, td_error = jax.jit(teacher.store), jax.jit(teacher.td_error)
    k = jax.random.split(jax.random.PRNGKey(1), 3)
    batch = Transition(s=jax.random.normal(k[0], (3, 3)) * 50, u=jax.random.uniform(k[1], (3, 2), minval=-1),
                       r=jnp.array([1.0, -2.0, 0.5]), s_next=jax.random.normal(k[2], (3, 3)) * 50, done=jnp.array([0.0, 0.0, 1.0]))
    item = lambda i: jax.tree_util.tree_map(lambda x: x[i], batch)
    one_by_one = buf
    for i in range(3):
        one_by_one = store(one_by_one, item(i))
    at_once = store(store(buf, item(0)), jax.tree_util.tree_map(lambda x: x[1:], batch))
    jax.tree_util.tree_map(np.testing.assert_array_equal, at_once, one_by_one)
    both = store(at_once, jax.tree_util.tree_map(lambda x: x[:2], batch))  # wraps round: FIFO
    np.testing.assert_array_equal(both.data.r, [-2.0, -2.0, 0.5, 1.0])
    assert int(both.count) == 4 and int(both.pos) == 1
    td = td_error(st, batch, batch.r)
    assert td.shape == (3,)
    np.testing.assert_allclose(td, [td_error(st, item(i), batch.r[i]) for i in range(3)], rtol=1e-5)


def test_pool_init_and_evaluate_per_student():
    env, student, levels = _cartpole()
    pool = StudentPool(student, 3)
    key = jax.random.PRNGKey(1)
    # one set of hyperparameters per student (as a pool state's own) is taken per student; student i
    # comes from key i (student 0 is checked against a lone student below)
    hp = PPOHyperparams.stack([student.config.hparams] * 3)
    hp = jax.tree_util.tree_map(lambda x: x * jnp.array([1.0, 2.0, 3.0], jnp.float32), hp)
    states = jax.jit(pool.init)(key, hp)
    assert states.obs.shape[0] == 3
    jax.tree_util.tree_map(np.testing.assert_array_equal, states.hparams, hp)
    # evaluation: student i with key i, episodes pooled per level
    lv = _at(levels, slice(0, 2))
    pooled = jax.jit(lambda s, k: pool.evaluate(s, k, lv, 2, 30))(states, key)
    assert pooled.shape == (2, 6) and np.ptp(np.asarray(pooled)) > 0
    one = jax.jit(lambda s, k: student.evaluate(s, k, lv, 2, 30))
    each = jnp.stack([one(StudentPool.member(states, i), k) for i, k in enumerate(student_keys(key, 3))])
    np.testing.assert_allclose(pooled, pool_episodes(each), rtol=1e-6)


def test_each_step_stores_one_transition_per_student(two):
    method, _, (m, s, info, test_returns, ms, ss, step_keys) = two
    k, steps = 2, 3
    base, cfg = method.base, method.config
    real, ext = m.real, info.extras
    assert int(real.count) == k * steps and int(real.pos) == k * steps
    mdim = cfg.num_eval_levels
    act, performance = jax.jit(base.teacher.act), jax.jit(base.performance)  # one compile each for the calls below
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
            # the student's own action: the shared actor at its own state plus its own exploration noise
            u = act(_at(ms.ddpg, t), ts, key_i, cfg.explore_sigma)
            np.testing.assert_allclose(real.data.u[row], u, rtol=1e-5, atol=1e-6)
            if t + 1 < steps:
                np.testing.assert_array_equal(ms.s[t + 1, i], ext["teacher_state_per_student"][t, i])
    # the students' states, rewards and exploration noise differ
    assert not np.allclose(ms.s[1, 0], ms.s[1, 1]) and real.data.r[2] != real.data.r[3]
    noise = [real.data.u[i] - base.teacher.act(_at(ms.ddpg, 0), real.data.s[i], None, 0.0) for i in range(k)]
    assert np.abs(noise[0]).max() > 0 and not np.allclose(noise[0], noise[1])
    # the record: the students' means, every student's levels, per-student entries
    np.testing.assert_allclose(info.teacher_reward, ext["teacher_reward_per_student"].mean(axis=1), rtol=1e-6)
    np.testing.assert_allclose(ext["teacher_state"], ext["teacher_state_per_student"].mean(axis=1), rtol=1e-6)
    e = method.pool.config.num_envs
    assert info.levels.shape == (steps, k * cfg.updates_per_step * e, base.codec.dim)
    np.testing.assert_array_equal(info.num_new_levels, ext["levels_trained_mask"].sum(axis=1))
    np.testing.assert_array_equal(info.env_steps_train, [cfg.updates_per_step * base.student.env_steps_per_update] * steps)
    assert ext["td_error_heldout"].shape == (steps,)
    # the test returns: both students' episodes per level, student 0's first; their mean is the mean of the
    # students' own means (the loop's test_return)
    assert test_returns.shape == (steps, 2, k * TEST_EPISODES)
    per_student = test_returns.reshape(steps, 2, k, TEST_EPISODES).mean(axis=(1, 3))
    np.testing.assert_allclose(ext["test_return_per_student"], per_student, rtol=1e-6)
    np.testing.assert_allclose(test_returns.mean(axis=(1, 2)), per_student.mean(axis=1), rtol=1e-5)
    np.testing.assert_array_equal(ext["real_size"], [k, 2 * k, 3 * k])
    # common random numbers per student: s' is the evaluation of that student with its own episode key
    assert not np.array_equal(m.eval_key[0], m.eval_key[1])
    for i in range(k):
        np.testing.assert_allclose(performance(m.eval_key[i], StudentPool.member(s, i))[0], m.s[i], rtol=1e-5)


def test_students_are_independent_and_student_0_is_the_lone_students_run(two):
    method, run, (m2, s2, info2, test2, _, _, _) = two
    # student 1 started from other weights: student 0's whole run is the same, bit for bit
    other = StudentPool.member(method.pool.init(jax.random.PRNGKey(12)), 1)
    students = jax.tree_util.tree_map(lambda x, y: x.at[1].set(y), method.pool.init(STUDENT_KEY), other)
    m3, s3, info3, test3, _, _, _ = run(KEY, students)
    for a, b in zip(jax.tree_util.tree_leaves(StudentPool.member(s2, 0)), jax.tree_util.tree_leaves(StudentPool.member(s3, 0))):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(m2.real.data.u[0:6:2], m3.real.data.u[0:6:2])
    np.testing.assert_array_equal(test2[..., :TEST_EPISODES], test3[..., :TEST_EPISODES])
    np.testing.assert_array_equal(info2.extras["teacher_state_per_student"][:, 0], info3.extras["teacher_state_per_student"][:, 0])
    assert not np.array_equal(info2.extras["teacher_state_per_student"][:, 1], info3.extras["teacher_state_per_student"][:, 1])
    kernel = lambda s: np.asarray(StudentPool.member(s.params, 1)["actor"]["MLP_0"]["Dense_0"]["kernel"])
    assert not np.array_equal(kernel(s2), kernel(s3))
    # the lone student's teacher (students=1) with the same keys: student 0 follows it (the same keys;
    # vmapped arithmetic may differ in the last bits)
    one = _build(1, **SAME_TEACHER)
    m1, s1, info1, test1, _, _, _ = _runner(one)(KEY, one.student.init(STUDENT_KEY))
    np.testing.assert_allclose(test2[..., :TEST_EPISODES], test1, rtol=1e-4, atol=1e-4)
    assert int(m1.real.count) == 3
    np.testing.assert_allclose(m2.real.data.u[0:6:2], m1.real.data.u[:3], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(m2.real.data.s[0:6:2], m1.real.data.s[:3], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(m2.real.data.r[0:6:2], m1.real.data.r[:3], rtol=1e-4, atol=1e-4)
    for a, b in zip(jax.tree_util.tree_leaves(StudentPool.member(s2.params, 0)), jax.tree_util.tree_leaves(s1.params)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


# ---- the run state of K students: built by experiment.build, saved and restored -----------------------


def test_a_run_state_of_two_students_saves_and_restores(tmp_path):
    from test_checkpoint import cartpole_test_levels, leaves_equal, restore, target_for

    from shed_jax import checkpoint as ck
    from shed_jax import evaluation
    from shed_jax import experiment as xp
    from shed_jax.loop import LoopSpec, make_run
    from shed_jax.methods import hierarchical
    from shed_jax.presets import Experiment
    from shed_jax.student import PPOConfig

    _, _, eval_levels = _cartpole()
    ppo = PPOConfig.for_env("cartpole", num_envs=5, num_steps=4, num_minibatches=1, update_epochs=1)
    exp = Experiment(env="cartpole", method="hmdp-x", preset="tiny", ppo=ppo,
                     method_config={**TINY_TEACHER, "eval_max_steps": 30, "students": 2},
                     loop=LoopSpec(steps_per_episode=2, num_episodes=2, test_episodes=1, test_max_steps=20),
                     test_set="cartpole-test")
    original = xp.test_levels
    with pytest.MonkeyPatch.context() as mp:  # CartPole has no evaluation set of its own
        mp.setattr(xp, "test_levels", lambda name, env: cartpole_test_levels(env) if name == "cartpole-test" else original(name, env))
        mp.setattr(hierarchical, "_evaluation_levels", lambda env, config: (eval_levels, None))
        _, student, method, tests = xp.build(exp)
        assert isinstance(method, ParallelStudents) and student is method.pool
        init = make_run(student, method, tests, exp.loop)[0]
        state = jax.jit(jax.vmap(init))(xp.seed_keys(0, 2))
        assert state.student.obs.shape[:2] == (2, 2) and state.method.s.shape == (2, 2, 10)  # [seeds, students, ...]
        assert not np.array_equal(state.student.params["actor"]["MLP_0"]["Dense_0"]["kernel"][:, 0],
                                  state.student.params["actor"]["MLP_0"]["Dense_0"]["kernel"][:, 1])
        config = {"experiment": exp.to_dict(), "seeds": 2, "root_seed": 0}
        with ck.RunCheckpointer(tmp_path, create=True) as writer:
            writer.save(1, state, {"step": np.zeros((2, 1), np.int32)}, config)
        leaves_equal(restore(tmp_path, target_for(exp)).state, state)
        _, _, pool, _, seeds, step, students = evaluation.restore_students(tmp_path)  # what eval --run reads
        assert isinstance(pool, StudentPool) and (seeds, step) == (2, 1)
        leaves_equal(students, state.student)


def test_pooled_record_keeps_the_longest_evaluation_episode_of_all(two):
    """The K students' evaluations run as one vmapped rollout, which lasts as long as its longest
    episode: the pooled ``eval_longest_episode`` is the students' maximum; other extras are means."""
    import types

    from shed_jax.methods.base import StepInfo

    method = two[0]
    infos = StepInfo(levels=jnp.zeros((2, 1, 3)), env_steps_train=jnp.array([4, 4]), env_steps_eval=jnp.array([8, 8]),
                     teacher_reward=jnp.array([1.0, 3.0]), num_new_levels=jnp.array([1, 2]),
                     extras={"eval_longest_episode": jnp.array([120, 500], jnp.int32), "td_error_heldout": jnp.array([1.0, 3.0])})
    exp = types.SimpleNamespace(transition=types.SimpleNamespace(r=jnp.array([1.0, 3.0])), s_next=jnp.zeros((2, 4)))
    info = method.pooled_info(infos, exp, None)
    assert int(info.extras["eval_longest_episode"]) == 500 and info.extras["eval_longest_episode"].dtype == jnp.int32
    assert float(info.extras["td_error_heldout"]) == 2.0 and float(info.teacher_reward) == 2.0
