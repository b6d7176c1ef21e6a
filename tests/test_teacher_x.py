"""The learning teacher (hmdp-x, shed-x; shed_jax/methods/learning_teacher.py) and its DDPG options,
on the tiny CartPole setup of test_shed_method.py. Each switch is checked for what it must do."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from test_shed_method import TINY, TINY_TEACHER, _cartpole  # noqa: E402

from shed_jax.methods.hierarchical import at_bound_fraction
from shed_jax.methods.learning_teacher import HMDPXConfig, SHEDXConfig, make_hmdp_x, make_shed_x
from shed_jax.methods.registry import config_class, make_method
from shed_jax.teacher.buffers import Transition
from shed_jax.teacher.ddpg import Actor, DDPGConfig, ddpg_act, ddpg_init, ddpg_update


def _build(name, **overrides):
    env, student, eval_levels = _cartpole()
    if name == "shed-x":
        return make_shed_x(env, student, SHEDXConfig(**{**TINY, **overrides}), eval_levels=eval_levels)
    return make_hmdp_x(env, student, HMDPXConfig(**{**TINY_TEACHER, **overrides}), eval_levels=eval_levels)


def _run(method, steps=4):
    student = method.student

    @jax.jit
    def run(key):
        k_m, k_s, k_b, k_run = jax.random.split(key, 4)
        m, s = method.begin_episode(k_b, method.init(k_m), student.init(k_s))
        s0 = m.s

        def body(carry, k):
            m, s = carry
            m, s, info = method.step(k, m, s)
            return (m, s), (info, s)

        (m, s), (infos, students) = jax.lax.scan(body, (m, s), jax.random.split(k_run, steps))
        return m, s0, infos, students

    return run(jax.random.PRNGKey(0))


# ---- DDPG options --------------------------------------------------------------------------------


def _batch(b=6, m=3, da=2):
    k = jax.random.split(jax.random.PRNGKey(1), 3)
    return Transition(s=jax.random.normal(k[0], (b, m)), u=jax.random.uniform(k[1], (b, da), minval=-1, maxval=1),
                      r=jax.random.normal(k[2], (b,)), s_next=jax.random.normal(k[0], (b, m)) + 1.0, done=jnp.zeros((b,)))


def test_preact_penalty_adds_lambda_mean_z_squared_to_the_actor_loss():
    batch, lam = _batch(), 0.5
    plain, pen = DDPGConfig(3, 2), DDPGConfig(3, 2, preact_penalty=lam)
    st = ddpg_init(plain, jax.random.PRNGKey(0))
    # one jitted program for both updates (not op by op); the two updates' critic parts are the same
    # computation, the actor loss gains the term
    (_, m0), (_, m1) = jax.jit(lambda st, batch: (ddpg_update(plain, st, batch), ddpg_update(pen, st, batch)))(st, batch)
    _, z = Actor(2).apply(st.actor_params, batch.s, preact=True)
    assert float(m1["actor_loss"] - m0["actor_loss"]) == pytest.approx(lam * float(jnp.mean(z ** 2)), rel=1e-4)
    assert float(m1["critic_loss"]) == float(m0["critic_loss"])


def test_zero_actor_output_init_acts_zero_everywhere_and_still_learns():
    cfg = DDPGConfig(3, 2, actor_out_init="zeros")
    st = ddpg_init(cfg, jax.random.PRNGKey(0))
    np.testing.assert_array_equal(ddpg_act(cfg, st, jax.random.normal(jax.random.PRNGKey(2), (5, 3))), np.zeros((5, 2)))
    st2, _ = jax.jit(lambda st, batch: ddpg_update(cfg, st, batch))(st, _batch())  # one program, not op by op
    assert np.any(np.asarray(ddpg_act(cfg, st2, _batch().s)) != 0)
    # the default keeps flax's initialiser: nonzero actions
    d = DDPGConfig(3, 2)
    assert np.all(np.asarray(ddpg_act(d, ddpg_init(d, jax.random.PRNGKey(0)), _batch().s)) != 0)


def test_ddpg_option_errors():
    with pytest.raises(ValueError, match=r"^DDPGConfig.actor_out_init must be one of 'lecun', 'zeros', got 'ones'$"):
        DDPGConfig(3, 2, actor_out_init="ones")
    with pytest.raises(ValueError, match=r"^DDPGConfig.preact_penalty must be >= 0"):
        DDPGConfig(3, 2, preact_penalty=-1.0)


# ---- the method ------------------------------------------------------------------------------------


def test_config_errors_and_registry():
    for field, bad, allowed in (("action", "points", "'box', 'levels'"), ("level_switch", "rollout", "'episode', 'block'")):
        with pytest.raises(ValueError, match=rf"^HMDPXConfig.{field} must be one of {re_escape(allowed)}, got '{bad}'$"):
            HMDPXConfig(**{field: bad})
    with pytest.raises(ValueError, match=r"^SHEDXConfig.crn must be True or False"):
        SHEDXConfig(crn="yes")
    with pytest.raises(ValueError, match=r"^HMDPXConfig.reward_scale must be a finite number > 0"):
        HMDPXConfig(reward_scale=0)
    with pytest.raises(ValueError, match=r"^SHEDXConfig.syn_capacity must be a positive int"):
        SHEDXConfig(syn_capacity=0)
    with pytest.raises(ValueError, match=r"^HMDPXConfig.actor_delay must be a positive int"):
        HMDPXConfig(actor_delay=0)
    with pytest.raises(ValueError, match=r"^HMDPXConfig.twin_critics must be True or False"):
        HMDPXConfig(twin_critics="yes")
    td3 = _build("hmdp-x", twin_critics=True, actor_delay=2).teacher.ddpg.config  # the switches reach the DDPG
    assert (td3.twin_critics, td3.actor_delay) == (True, 2)
    assert config_class("hmdp-x") is HMDPXConfig and config_class("shed-x") is SHEDXConfig
    assert SHEDXConfig().real_capacity == 2048 and HMDPXConfig().real_capacity == 10000
    # the chosen teacher's defaults (the lander runs of docs/results.md); SHED's own stay the paper's
    for cfg in (HMDPXConfig(), SHEDXConfig()):
        assert (cfg.actor_lr, cfg.twin_critics, cfg.actor_delay) == (1e-5, True, 2)
    assert (SHEDXConfig().syn_action, SHEDXConfig().syn_threshold) == ("policy", 32)
    from shed_jax.methods.shed import SHEDConfig
    assert (SHEDConfig().syn_action, SHEDConfig().syn_threshold, SHEDConfig().actor_lr) == ("uniform", 500, 1e-3)
    import envs
    from shed_jax.student import make_student
    from shed_jax.student.config import PPOConfig
    lander = envs.make("lander")
    student = make_student(lander, PPOConfig.for_env("lander", num_envs=10, num_steps=4))
    assert make_method("hmdp-x", lander, student, {"num_levels": 5}).name == "hmdp-x"


def re_escape(s):
    import re
    return re.escape(s)


def test_box_action_hand_computed_and_untrained_teacher_is_uniform_over_theta():
    method = _build("hmdp-x")
    d = method.codec.dim
    assert (method.teacher.state_dim, method.teacher.action_dim) == (11, 2 * d)
    # centre 0.8, width exponent -1 (w = 0.5): [0.3, 1]; centre -0.5, exponent 1 (w = 2): the whole [-1, 1]
    u = jnp.array([0.8, -0.5, 0.0] + [-1.0, 1.0, 0.0])[: 2 * d] if d == 3 else None
    lo, hi = method.box(u)
    np.testing.assert_allclose(lo, [0.3, -1.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(hi, [1.0, 1.0, 1.0], atol=1e-6)
    # the untrained actor gives u = 0 for any state: the box is Θ, levels are U(Θ) (DR)
    m = method.init(jax.random.PRNGKey(0))
    u0 = method.teacher.act(m.ddpg, jnp.ones((11,)) * 37.0, None, 0.0)
    np.testing.assert_array_equal(u0, np.zeros(2 * d))
    vecs, _ = method.draw(jax.random.PRNGKey(3), u0, 4000)
    unit = np.asarray(method.codec.space.to_unit(vecs))
    assert unit.min() > -1.0 and unit.max() < 1.0
    np.testing.assert_allclose(unit.mean(axis=0), 0.0, atol=0.05)
    np.testing.assert_allclose(unit.var(axis=0), 1 / 3, atol=0.03)  # Var U(-1, 1) = 1/3
    assert float(at_bound_fraction(method.codec.space, vecs)) == pytest.approx(0.02, abs=0.006)
    # a box in the low corner: every drawn level lies in it
    ub = jnp.array([-1.0] * d + [-1.0] * d)
    vb = np.asarray(method.codec.space.to_unit(method.draw(jax.random.PRNGKey(4), ub, 500)[0]))
    assert vb.min() >= -1.0 - 1e-6 and vb.max() <= -0.5 + 1e-6


# hmdp-x runs with the reward-noise check on (and episodes long enough for CartPole's returns to vary),
# shed-x with it off; the check only adds evaluations, so the step test holds with it on and one compile
# serves both tests. shed-x runs with policy synthetic actions (its default) at syn_sigma 0: the noise is
# still drawn and scaled in the program (sigma is a constant of it, not a branch), none of the step test's
# checks reads the synthetic actions, and the one run also serves the synthetic-action test below
CHECKED = {"hmdp-x": dict(reward_noise_check=True, eval_max_steps=64), "shed-x": dict(syn_action="policy", syn_sigma=0.0)}


@functools.lru_cache(maxsize=None)
def _checked_run(name):
    method = _build(name, **CHECKED[name])
    return method, _run(method)


@pytest.mark.parametrize("name", ["hmdp-x", "shed-x"])
def test_step_episode_levels_crn_and_signed_fixed_scale_reward(name):
    method, (m, s0, info, students) = _checked_run(name)
    cfg, e = method.config, method.student.config.num_envs
    ext = info.extras
    # levels: C x num_envs draws per step from the box, played where the slot's episode ended
    assert info.levels.shape == (4, cfg.updates_per_step * e, method.codec.dim)
    np.testing.assert_array_equal(info.num_new_levels, ext["levels_trained_mask"].sum(axis=1))
    np.testing.assert_allclose(ext["at_bound_fraction"], [float(at_bound_fraction(method.codec.space, v, w))
                                                          for v, w in zip(info.levels, ext["levels_trained_mask"])])
    # reward: signed sum of the change, / 100, on the performance part; raw (no z-scoring) for the critic
    states = np.concatenate([np.asarray(s0)[None], np.asarray(ext["teacher_state"])])
    expect = (states[1:] - states[:-1]).sum(axis=1) / 100.0
    np.testing.assert_allclose(info.teacher_reward, expect, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(m.real.data.r[:4], expect, rtol=1e-4, atol=1e-6)
    assert method.teacher.ddpg.config.reward_norm is False
    np.testing.assert_allclose(m.real.data.s[:4, -1], np.array([0, 1, 2, 3]) / 2 * cfg.state_scale)  # t/T, T = 2
    # CRN: every s' is the evaluation of that step's student with the episode's one key
    last = jax.tree_util.tree_map(lambda x: x[-1], students)
    np.testing.assert_allclose(method.performance(m.eval_key, last)[0], states[-1], rtol=1e-5)
    # the s' evaluation's longest episode (its sequential steps), at most the step limit
    _, info_s = method.student.evaluate_with_info(last, m.eval_key, method.eval_params, cfg.num_eval_episodes, method.eval_max)
    limit = int(info_s["env_steps"]) // (cfg.num_eval_levels * cfg.num_eval_episodes)
    assert int(ext["eval_longest_episode"][-1]) == int(np.asarray(info_s["lengths"]).max())
    assert ext["eval_longest_episode"].shape == (4,) and np.all((ext["eval_longest_episode"] > 0) & (ext["eval_longest_episode"] <= limit))
    assert int(info_s["steps_run"]) >= int(ext["eval_longest_episode"][-1])  # the rollout ran at least that long
    if name == "shed-x":
        assert method.synthesiser.model.config.state_dim == 11 and int(ext["syn_size"][-1]) > 0
        assert all(np.all(np.isnan(ext[k])) for k in ("reward_again", "reward_crossed", "reward_crossed_back"))  # off


def test_reward_noise_check_rewards_the_same_students_again_with_a_second_key():
    method, (m, s0, info, students) = _checked_run("hmdp-x")
    ext = info.extras
    states = np.concatenate([np.asarray(s0)[None], np.asarray(ext["teacher_state"])])
    k2 = jax.random.fold_in(m.eval_key, 2)  # CRN: the step's key is the episode's; the check folds in 2
    performance = jax.jit(method.performance)  # one compile for the six evaluations below
    for t in range(1, 4):  # the student before step t's training is the one step t - 1 returned
        before, after = (jax.tree_util.tree_map(lambda x, i=i: x[i], students) for i in (t - 1, t))
        s2, s_next2 = performance(k2, before)[0], performance(k2, after)[0]
        np.testing.assert_allclose(ext["reward_again"][t], (s_next2 - s2).sum() / 100.0, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(ext["reward_crossed"][t], (s_next2 - states[t]).sum() / 100.0, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(ext["reward_crossed_back"][t], (states[t + 1] - s2).sum() / 100.0, rtol=1e-4, atol=1e-5)
    # the signed sum is linear: the two paired and the two crossed rewards have the same total
    np.testing.assert_allclose(info.teacher_reward + ext["reward_again"], ext["reward_crossed"] + ext["reward_crossed_back"],
                               rtol=1e-4, atol=1e-5)
    assert not np.allclose(info.teacher_reward, ext["reward_again"])  # another key, other episodes
    # three evaluations per step (s' and the two checks), and step 0 pays begin_episode's s_0
    per_eval = 10 * 1 * 64  # m levels x 1 episode x 64 steps
    np.testing.assert_array_equal(info.env_steps_eval, [4 * per_eval] + [3 * per_eval] * 3)


def test_crn_off_and_block_levels_are_h_mdp_like():
    method = _build("hmdp-x", crn=False, level_switch="block", action="levels", actor_out_init="lecun")
    m, s0, info, students = _run(method)
    n, d = method.config.num_levels, method.codec.dim
    assert method.teacher.action_dim == n * d and info.levels.shape == (4, n, d)
    np.testing.assert_array_equal(info.num_new_levels, [n] * 4)
    u = np.asarray(m.real.data.u[:4]).reshape(4, n, d)
    np.testing.assert_allclose(method.codec.space.from_unit(u), info.levels, rtol=1e-5, atol=1e-5)
    # without crn each evaluation takes the step's own key; with it, the teacher episode's key
    k = jax.random.PRNGKey(9)
    np.testing.assert_array_equal(np.asarray(method.evaluation_key(m, k)), np.asarray(k))
    crn = _build("hmdp-x", crn=True, level_switch="block", action="levels", actor_out_init="lecun")
    np.testing.assert_array_equal(np.asarray(crn.evaluation_key(m, k)), np.asarray(m.eval_key))
    assert not np.array_equal(np.asarray(m.eval_key), np.asarray(k))


# ---- shed-x's synthesiser switches ---------------------------------------------------------------


def _linear_buffer(key, n=128, m=3, da=2):
    """Transitions with a deterministic s' = s + 10 [a, 0], so a trained model predicts them well."""
    from shed_jax.teacher.buffers import buffer_add_many, buffer_init, make_transition
    k_s, k_a = jax.random.split(key)
    s = 100.0 + 20.0 * jax.random.normal(k_s, (n, m))
    a = jax.random.uniform(k_a, (n, da), minval=-1, maxval=1)
    s_next = s + 10.0 * jnp.pad(a, ((0, 0), (0, m - da)))
    tr = Transition(s=s, u=a, r=jnp.zeros((n,)), s_next=s_next, done=jnp.zeros((n,)))
    return tr, buffer_add_many(buffer_init(make_transition(m, da), n), tr)


def test_heldout_loss_is_the_training_loss_on_unseen_transitions_and_falls_with_training():
    from shed_jax.teacher.diffusion import DiffusionConfig, make_diffusion, normalize
    model = make_diffusion(DiffusionConfig(3, 2, hidden=32, batch_size=64))
    _, buf = _linear_buffer(jax.random.PRNGKey(0))
    fresh, _ = _linear_buffer(jax.random.PRNGKey(1), n=64)  # never trained on
    key = jax.random.PRNGKey(5)

    @jax.jit
    def run(key):
        st0 = model.refresh_norm(model.init(key), buf)
        st1, _ = model.train_steps(st0, jax.random.fold_in(key, 1), buf, 300)
        held = lambda st: model.heldout_loss(st, jax.random.fold_in(key, 2), fresh.s, fresh.u, fresh.s_next, 16)
        return st0, st1, held(st0), held(st1)

    st0, st1, before, after = run(key)
    # by hand: the mean of the training loss over the 16 draws, on the normalised batch
    s_n, sn_n = normalize(st1.norm, fresh.s), normalize(st1.norm, fresh.s_next)
    hand = np.mean([float(model.loss(st1.params, k, s_n, fresh.u, sn_n))
                    for k in jax.random.split(jax.random.fold_in(key, 2), 16)])
    assert float(after) == pytest.approx(hand, rel=1e-5)
    # s' is a deterministic function of (s, a): training must cut the loss on unseen transitions
    assert float(after) < 0.5 * float(before), (float(before), float(after))


def test_grow_passes_the_policy_with_syn_sigma_and_reports_the_heldout_loss_of_the_new_transitions():
    method = _build("shed-x", syn_action="policy", syn_sigma=0.3)
    synth = method.synthesiser
    m = jax.jit(method.init)(jax.random.PRNGKey(0))  # one program, not op by op
    tr, real = _linear_buffer(jax.random.PRNGKey(1), n=16, m=method.state_dim, da=method.action_dim)
    new = jax.tree_util.tree_map(lambda x: x[-2:], tr)  # the step's transitions, already in B_real
    policy = lambda k, s, sigma: jnp.full((s.shape[0], method.action_dim), sigma)  # marks the sigma it got
    rf = lambda s, a, s_next: jnp.sum(s_next - s)
    grow = jax.jit(lambda sst, real: synth.grow(jax.random.PRNGKey(2), sst, real, rf, new, policy))
    expect = jax.jit(lambda d: synth.model.heldout_loss(d, jax.random.fold_in(jax.random.PRNGKey(2), 1), new.s, new.u,
                                                        new.s_next, synth.heldout_draws))(m.synth.diffusion)
    sst, loss, held = grow(m.synth, real)
    n = synth.num_syn
    np.testing.assert_allclose(sst.syn.data.u[:n], 0.3)
    assert int(sst.syn.count) == n and np.isfinite(float(loss))
    assert float(held) == pytest.approx(float(expect), rel=1e-5)  # measured before the model trained on them
    # below the training threshold nothing trains and both losses are NaN
    _, loss, held = grow(m.synth, real.replace(count=jnp.int32(synth.train_threshold)))
    assert np.isnan(float(loss)) and np.isnan(float(held))


def test_syn_loss_bar_gates_mixed_updates_on_the_heldout_loss():
    from shed_jax.teacher.buffers import buffer_add_many, buffer_init, make_transition
    method = _build("shed-x", ddpg_batch=8, syn_threshold=3, syn_loss_bar=0.5)
    m = jax.jit(method.init)(jax.random.PRNGKey(0))  # one program, not op by op (as free's rule below)
    d, a = method.state_dim, method.action_dim
    fill = lambda n: buffer_add_many(buffer_init(make_transition(d, a), 16), make_transition(d, a, (n,)).replace(
        r=jnp.arange(n, dtype=jnp.float32), s_next=jnp.ones((n, d))))
    real, syn = fill(5), fill(4)
    synth = method.synthesiser
    rule = jax.jit(lambda held: synth.updates(jax.random.PRNGKey(3), method.teacher, m.ddpg, real,
                                              m.synth.replace(syn=syn), 0.75, held)[1])
    assert int(rule(0.4)) == 2  # below the bar: mixed
    assert int(rule(0.6)) == 1  # above it: real updates only
    assert int(rule(jnp.nan)) == 1  # no held-out loss yet: real only
    # without a bar (SHED's rule) the held-out loss is not read
    free = _build("shed-x", ddpg_batch=8, syn_threshold=3).synthesiser
    assert int(jax.jit(lambda held: free.updates(jax.random.PRNGKey(3), method.teacher, m.ddpg, real, m.synth.replace(syn=syn),
                                                 0.75, held)[1])(jnp.nan)) == 2


def test_policy_synthetic_actions_in_the_loop_come_from_the_actor_before_its_update():
    """syn_sigma 0: the first synthetic batch (step 2, before the first DDPG update) holds the untrained
    actor's actions, exactly 0 with the zero-initialised output layer (uniform ones are 0 with
    probability 0). The run is the step test's (``CHECKED``), so this test compiles nothing."""
    method, (m, _, info, _) = _checked_run("shed-x")
    assert (method.config.syn_action, method.config.syn_sigma) == ("policy", 0.0)
    n = method.synthesiser.num_syn
    np.testing.assert_array_equal(np.asarray(m.synth.syn.data.u[:n]), 0.0)
    held = np.asarray(info.extras["diffusion_heldout_loss"])
    assert np.isnan(held[0]) and np.all(np.isfinite(held[1:]))


def test_eval_length_refuses_a_folder_that_is_not_a_run(tmp_path, capsys):
    """experiments/eval_length.py: one line, exit 2, for a folder without a run's config."""
    from experiments import eval_length

    assert eval_length.main([str(tmp_path), "--out", str(tmp_path / "r.json")]) == 2
    assert "is not a run directory (no config.json)" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()
