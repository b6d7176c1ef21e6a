"""SHED / h-MDP method: one jitted scan of budget steps on a tiny CartPole student (cheap to
compile; the lander/walker evaluation sets are tested in test_eval_sets.py), checking the official
schedule (buffer growth, diffusion/synthesis threshold, DDPG branch), rewards and accounting, and
the composition (h-MDP: the DDPG teacher alone; SHED: plus the diffusion synthesiser)."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from shed_jax.methods.hierarchical import HMDPConfig, TeacherHyperparams, make_hmdp
from shed_jax.methods.registry import make_method
from shed_jax.methods.shed import SHEDConfig, SHEDHyperparams, make_shed
from shed_jax.student import make_student
from shed_jax.student.config import PPOConfig
from shed_jax.teacher.buffers import buffer_add_many, buffer_init, make_transition, sample_mixed
from shed_jax.teacher.reward import RewardConfig, teacher_reward

TINY_TEACHER = dict(
    updates_per_step=1, num_eval_episodes=1, eval_max_steps=8, budget_steps=2, ddpg_batch=4, real_capacity=16, ddpg_threshold=1,
)
TINY = dict(**TINY_TEACHER, syn_capacity=16, diffusion_threshold=1, diffusion_steps=2, num_syn=2, syn_threshold=2)


def _build(name, env, student, eval_levels, **overrides):
    """SHED or h-MDP with the tiny settings (h-MDP takes the teacher's only)."""
    if name == "shed":
        return make_shed(env, student, SHEDConfig(**{**TINY, **overrides}), eval_levels=eval_levels)
    return make_hmdp(env, student, HMDPConfig(**{**TINY_TEACHER, **overrides}), eval_levels=eval_levels)


def _cartpole():
    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole", num_envs=5, num_steps=4, num_minibatches=1, update_epochs=1))
    eval_levels = env.param_space.sample(jax.random.PRNGKey(42), (10,))
    return env, student, eval_levels


@functools.lru_cache(maxsize=None)  # one compile per configuration in a worker; tests only read the results
def _run(name, steps=4, **overrides):
    env, student, eval_levels = _cartpole()
    method = _build(name, env, student, eval_levels, **overrides)

    @jax.jit
    def run(key):
        k_m, k_s, k_b, k_run = jax.random.split(key, 4)
        m = method.init(k_m)
        s = student.init(k_s)
        m, s = method.begin_episode(k_b, m, s)
        s0 = m.s

        def body(carry, k):
            m, s = carry
            m, s, info = method.step(k, m, s)
            return (m, s), info

        (m, s), infos = jax.lax.scan(body, (m, s), jax.random.split(k_run, steps))
        return m, s0, infos, s

    return method, run(jax.random.PRNGKey(0))


def test_shed_schedule_rewards_and_accounting():
    method, (m, s0, info, _) = _run("shed")
    ext = info.extras
    np.testing.assert_array_equal(ext["real_size"], [1, 2, 3, 4])
    # D trains and synthesises 2 once |B_real| > 1: after steps 2, 3, 4
    np.testing.assert_array_equal(ext["syn_size"], [0, 2, 4, 6])
    assert np.isnan(ext["diffusion_loss"][0]) and np.all(np.isfinite(ext["diffusion_loss"][1:]))
    # DDPG: none (|B_real| = 1), real-only (|B_syn| = 2 not > 2), then mixed twice
    np.testing.assert_array_equal(ext["ddpg_branch"], [0, 1, 2, 2])
    assert int(m.ddpg.num_updates) == 0 + 3 + 2 + 2
    # levels: n = 5 per step, inside the lander box Θ
    lv = np.asarray(info.levels)
    assert lv.shape == (4, 5, 3)
    space = method.codec.space
    assert np.all(lv >= space.low - 1e-5) and np.all(lv <= space.high + 1e-5)
    # the stored transitions chain s_0 -> s_1 -> ... and the reward is the paper's R on them
    states = np.concatenate([np.asarray(s0)[None], np.asarray(ext["teacher_state"])])
    np.testing.assert_allclose(m.real.data.s[:4], states[:-1], rtol=1e-6)
    np.testing.assert_allclose(m.real.data.s_next[:4], states[1:], rtol=1e-6)
    expect = teacher_reward(RewardConfig(), states[:-1], None, states[1:])
    np.testing.assert_allclose(info.teacher_reward, expect, rtol=1e-5)
    np.testing.assert_allclose(m.real.data.r[:4], expect, rtol=1e-5)
    np.testing.assert_array_equal(m.real.data.done[:4], [0, 1, 0, 0])  # T = 2
    # stored actions are u in [-1, 1] and map to the levels
    u = np.asarray(m.real.data.u[:4]).reshape(4, 5, 3)
    assert np.all(np.abs(u) <= 1.0)
    np.testing.assert_allclose(method.codec.space.from_unit(u), lv, rtol=1e-5, atol=1e-5)
    # accounting: 5 envs x 4 steps per PPO update; eval 10 levels x 1 episode x 8 steps (+ s_0's on step 1)
    np.testing.assert_array_equal(info.env_steps_train, [20] * 4)
    np.testing.assert_array_equal(info.env_steps_eval, [160, 80, 80, 80])
    np.testing.assert_array_equal(info.num_new_levels, [5] * 4)


def test_hmdp_has_no_diffusion_and_two_real_updates():
    method, (m, s0, info, _) = _run("hmdp")
    assert m.synth is None and method.synthesiser is None
    np.testing.assert_array_equal(info.extras["ddpg_branch"], [0, 1, 1, 1])
    np.testing.assert_array_equal(info.extras["syn_size"], [0] * 4)  # recorded as 0, as SHED's keys
    assert int(m.ddpg.num_updates) == 6
    assert method.teacher.capacity == 16
    # the state-noise check off (the default; test_teacher_switches.py's diagnostics test turns it on):
    # NaN, and one evaluation per step
    assert np.all(np.isnan(info.extras["state_noise_sd"]))
    np.testing.assert_array_equal(info.env_steps_eval, [160, 80, 80, 80])


def test_shed_and_hmdp_are_one_process_until_the_teacher_learns():
    """Until the teacher's first update (at the end of step 2, once |B_real| > 1) SHED and h-MDP must
    draw the same keys for the same things: equal levels, teacher states (the students'
    evaluations), rewards and accounting, bit for bit on one backend; SHED's first synthesis (also
    at the end of step 2) changes nothing before it. Paired seeds across the two methods rely on
    this. The runs are the two tests' above (cached), so this test compiles nothing."""
    _, (_, s0_a, info_a, _) = _run("shed")
    _, (_, s0_b, info_b, _) = _run("hmdp")
    np.testing.assert_array_equal(info_a.extras["ddpg_branch"][:2], [0, 1])  # the first update: step 2
    np.testing.assert_array_equal(info_b.extras["ddpg_branch"][:2], [0, 1])
    np.testing.assert_array_equal(s0_a, s0_b)
    for field in ("levels", "teacher_reward", "env_steps_train", "env_steps_eval"):
        np.testing.assert_array_equal(getattr(info_a, field)[:2], getattr(info_b, field)[:2], err_msg=field)
    np.testing.assert_array_equal(info_a.extras["teacher_state"][:2], info_b.extras["teacher_state"][:2])
    assert len(np.unique(np.asarray(info_a.levels)[:2].reshape(2, -1), axis=0)) == 2  # the levels change per step
    # after the update they part: SHED ran three real updates at step 2, h-MDP two
    assert not np.array_equal(info_a.levels[2], info_b.levels[2])


def test_config_errors():
    env, student, eval_levels = _cartpole()
    with pytest.raises(ValueError, match="evaluation levels"):
        make_shed(env, student, SHEDConfig(**TINY, num_eval_levels=5), eval_levels=eval_levels)
    with pytest.raises(ValueError, match="no evaluation set"):
        make_method("shed", env, student, TINY)
    env = envs.make("lander")
    student = make_student(env, PPOConfig.for_env("lander", num_envs=5, num_steps=4, num_minibatches=1, update_epochs=1))
    assert make_method("hmdp", env, student).teacher.capacity == 10000 and make_method("shed", env, student).teacher.capacity == 2048
    with pytest.raises(ValueError, match="unknown config field"):
        make_method("shed", env, student, {"bogus": 1})
    with pytest.raises(ValueError, match=r"method 'hmdp': unknown config field\(s\) \['psi', 'syn_capacity'\]"):
        make_method("hmdp", env, student, {"psi": 0.5, "syn_capacity": 10})  # h-MDP has no synthesiser
    with pytest.raises(TypeError, match="config must be None, a dict or a HMDPConfig, got SHEDConfig"):
        make_method("hmdp", env, student, SHEDConfig())
    # the reward's fields (eta, form, ...) live one level down; the error says where
    with pytest.raises(ValueError, match=r"'eta' is a field of 'reward', given inside it: reward=\{\"eta\": <value>\}"):
        make_method("shed", env, student, {"eta": 10})
    with pytest.raises(ValueError, match="eval_set"):
        make_method("shed", env, student, {"eval_set": "random"})
    with pytest.raises(ValueError, match="multiple of num_levels"):
        make_method("shed", env, student, {"num_levels": 3})


def test_composition_hmdp_is_the_teacher_alone_and_shed_mixes_floor_psi_b_real_items():
    """h-MDP: no synthesiser, no synthetic state, no psi. SHED: its mixed-update rule runs
    ``num_mixed_updates`` DDPG updates on batches of floor(psi * B) real items then synthetic ones,
    psi taken from the hyperparameters; below the synthetic threshold it runs 3 real updates."""
    env, student, eval_levels = _cartpole()
    hmdp = _build("hmdp", env, student, eval_levels)
    m = jax.eval_shape(hmdp.init, jax.random.PRNGKey(0))  # what it holds, not its values: traced only
    assert m.synth is None and type(m.hparams) is TeacherHyperparams and hmdp.hparam_names == (
        "eta", "actor_lr", "critic_lr", "explore_sigma")
    with pytest.raises(TypeError, match="hparams must be a TeacherHyperparams, got SHEDHyperparams"):
        hmdp.init(jax.random.PRNGKey(0), SHEDHyperparams())

    shed = _build("shed", env, student, eval_levels, ddpg_batch=8, syn_threshold=3)
    m = jax.jit(shed.init)(jax.random.PRNGKey(0), SHEDHyperparams(psi=0.4))  # jitted: one program, not op by op
    assert "psi" in shed.hparam_names and float(m.hparams.psi) == pytest.approx(0.4)
    assert int(m.synth.syn.count) == 0 and m.synth.syn.capacity == 16
    ex = make_transition(shed.state_dim, shed.action_dim)
    fill = lambda r, n: buffer_add_many(buffer_init(ex, 16), make_transition(shed.state_dim, shed.action_dim, (n,)).replace(
        r=jnp.arange(n, dtype=jnp.float32) * r, s_next=jnp.ones((n, shed.state_dim))))
    real, syn = fill(1.0, 5), fill(-3.0, 4)
    synth, teacher, key = shed.synthesiser, shed.teacher, jax.random.PRNGKey(3)
    rule = jax.jit(lambda st, syn, psi: synth.updates(key, teacher, st, real, m.synth.replace(syn=syn), psi))

    st, branch = rule(m.ddpg, syn, 0.4)
    assert int(branch) == 2 and int(st.num_updates) == 2
    expect = m.ddpg

    @jax.jit
    def by_hand(st, k):
        batch, mask = sample_mixed(real, syn, k, 8, 0.4)
        return teacher.update(st, batch, mask), batch, mask

    for k in jax.random.split(key, 2):  # by hand: floor(0.4 * 8) = 3 real items, 5 synthetic
        expect, batch, mask = by_hand(expect, k)
        np.testing.assert_array_equal(mask, [True] * 3 + [False] * 5)
        assert np.all(np.asarray(batch.r[3:]) <= 0) and np.all(np.asarray(batch.r[:3]) >= 0)
    for a, b in zip(jax.tree_util.tree_leaves(st), jax.tree_util.tree_leaves(expect)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)

    st, branch = rule(m.ddpg, fill(-3.0, 3), 0.4)  # |B_syn| = 3, not > 3: real updates only
    assert int(branch) == 1 and int(st.num_updates) == 3
