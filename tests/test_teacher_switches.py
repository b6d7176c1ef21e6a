"""The paper-faithful teacher's switches (t/T in the state, reward normalisation 'none') and the
per-budget-step diagnostics (parameters at a bound of Θ, held-out TD error, teacher-state noise),
on the tiny CartPole setup of test_shed_method.py."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from test_shed_method import _build, _cartpole, _run  # noqa: E402

from envs.core import ParamSpace
from shed_jax.methods.hierarchical import HMDPConfig, at_bound_fraction, buffer_zscore, noise_sd
from shed_jax.methods.shed import SHEDConfig
from shed_jax.teacher.buffers import Transition, buffer_add_many, buffer_init, make_transition
from shed_jax.teacher.reward import RewardConfig, teacher_reward


# h-MDP's run with t/T in the state also has the noise check on: the two switches touch different parts of
# a step (the stored state and the actor's input; a second evaluation of the same student), so one compiled
# run serves the time-in-state test and the diagnostics test below. Its four steps run on past T = 2 (the
# run calls begin_episode once, as the test_shed_method runs). SHED's run keeps the noise check off and its
# one teacher episode of T = 2.
TIMED = {"hmdp": dict(steps=4, time_in_state=True, state_noise_check=True), "shed": dict(steps=2, time_in_state=True)}


@pytest.mark.parametrize("name", ["hmdp", "shed"])
def test_time_in_state_appends_t_over_T_and_the_reward_ignores_it(name):
    method, (m, s0, info, _) = _run(name, **TIMED[name])
    scale = method.config.state_scale
    assert method.teacher.state_dim == 11 and m.s.shape == (10,)  # m = 10 evaluation levels + t/T
    if name == "shed":
        assert method.synthesiser.model.config.state_dim == 11
    # steps t = 0, 1, ... store t/T and (t + 1)/T, times state_scale (the networks see s / scale)
    n = TIMED[name]["steps"]
    np.testing.assert_allclose(m.real.data.s[:n, -1], np.arange(n) / 2 * scale, rtol=1e-6)
    np.testing.assert_allclose(m.real.data.s_next[:n, -1], np.arange(1, n + 1) / 2 * scale, rtol=1e-6)
    states = np.concatenate([np.asarray(s0)[None], np.asarray(info.extras["teacher_state"])])
    np.testing.assert_allclose(m.real.data.s[:n, :10], states[:-1], rtol=1e-6)
    expect = teacher_reward(RewardConfig(), states[:-1], None, states[1:])  # the performance part only
    np.testing.assert_allclose(m.real.data.r[:n], expect, rtol=1e-5)
    np.testing.assert_allclose(info.teacher_reward, expect, rtol=1e-5)
    # the actor acts on [s / scale, t/T]: the stored action of step 1 is mu of that input plus noise, so
    # the time entry must change what the deterministic actor gives
    x = np.asarray(m.real.data.s[1]) / scale
    mu = method.teacher.ddpg.act(m.ddpg, x)
    mu0 = method.teacher.ddpg.act(m.ddpg, np.concatenate([x[:10], [0.0]]))
    assert not np.allclose(mu, mu0)


def test_time_in_state_off_keeps_the_state_m_wide():
    # shapes only: a step traced after begin_episode (eval_shape; nothing is compiled or run)
    env, student, eval_levels = _cartpole()
    method = _build("hmdp", env, student, eval_levels)

    def step(key):
        m, s = method.begin_episode(key, method.init(key), student.init(key))
        return method.step(key, m, s)[0]

    m = jax.eval_shape(step, jax.random.PRNGKey(0))
    assert method.teacher.state_dim == 10 and m.real.data.s.shape == (16, 10) and m.s.shape == (10,)


def test_reward_norm_none_gives_the_critic_raw_rewards():
    """Done transitions with reward 5 everywhere: the target is r~, 0 when z-scored per batch, 5 raw."""
    targets = {}
    env, student, eval_levels = _cartpole()
    for norm in ("batch", "none"):
        method = _build("hmdp", env, student, eval_levels, reward_norm=norm)
        assert method.teacher.ddpg.config.reward_norm is (norm == "batch")
        b = 4
        batch = Transition(s=jnp.ones((b, 10)), u=jnp.zeros((b, 15)), r=jnp.full((b,), 5.0), s_next=jnp.ones((b, 10)),
                           done=jnp.ones((b,)))
        # the critic's target needs the update alone, not a run; jitted: one program, not op by op
        target = jax.jit(lambda key, batch: method.teacher.ddpg.update(method.init(key).ddpg, batch)[1]["target_mean"])
        targets[norm] = float(target(jax.random.PRNGKey(0), batch))
    assert targets["batch"] == pytest.approx(0.0, abs=1e-5)
    assert targets["none"] == pytest.approx(5.0)


def test_switch_errors_are_one_line_value_errors():
    with pytest.raises(ValueError, match=r"^HMDPConfig.reward_norm must be one of 'batch', 'none', got 'zscore'$"):
        HMDPConfig(reward_norm="zscore")
    with pytest.raises(ValueError, match=r"^SHEDConfig.time_in_state must be True or False, got 1$"):
        SHEDConfig(time_in_state=1)
    with pytest.raises(ValueError, match=r"^HMDPConfig.state_noise_check must be True or False"):
        HMDPConfig(state_noise_check="yes")


# ---- diagnostics ------------------------------------------------------------------------------


def test_at_bound_fraction_hand_computed():
    space = ParamSpace(("a", "b", "c"), np.array([0.0, -10.0, 1.0], np.float32), np.array([1.0, 10.0, 1.0], np.float32), None)
    vecs = jnp.array([[0.0, 0.0, 1.0],  # a at low: 1 of 2 (c has an empty range and is left out)
                      [0.995, 9.9, 1.0],  # both within 1 % of the range (0.01, 0.2) of high
                      [0.5, -9.85, 1.0]])  # b 0.15 above low: at a bound; a not
    assert float(at_bound_fraction(space, vecs)) == pytest.approx(4 / 6)
    assert float(at_bound_fraction(space, vecs, weights=jnp.array([1.0, 0.0, 1.0]))) == pytest.approx(2 / 4)
    assert float(at_bound_fraction(space, vecs[:, :] * 0 + jnp.array([0.5, 0.0, 1.0]))) == 0.0


def test_buffer_zscore_and_noise_sd():
    buf = buffer_init(make_transition(1, 1), 8)
    items = make_transition(1, 1, (4,)).replace(r=jnp.array([1.0, 2.0, 3.0, 4.0]))
    buf = buffer_add_many(buf, items)  # 4 of 8 valid: mean 2.5, population std sqrt(1.25)
    assert float(buffer_zscore(jnp.float32(5.0), buf)) == pytest.approx(2.5 / np.sqrt(1.25), rel=1e-5)
    assert float(noise_sd(jnp.array([1.0, 3.0]), jnp.array([3.0, 1.0]))) == pytest.approx(np.sqrt(2.0))


def test_diagnostics_are_logged_every_step():
    method, (m, s0, info, _) = _run("hmdp", **TIMED["hmdp"])  # the noise check on (and t/T in the state)
    ext = info.extras
    np.testing.assert_allclose(ext["at_bound_fraction"], [float(at_bound_fraction(method.codec.space, v)) for v in info.levels])
    assert ext["td_error_heldout"].shape == (4,) and np.all(np.isfinite(ext["td_error_heldout"]))
    # step 0's transition, held out: the TD error of the initial critic on it, its reward z-scored with B_real's
    # statistics (B_real holds that one transition then: r~ = 0)
    t0 = jax.tree_util.tree_map(lambda x: x[0], m.real.data)
    ddpg0 = method.init(jax.random.split(jax.random.PRNGKey(0), 4)[0]).ddpg
    expect = method.teacher.td_error(ddpg0, t0, 0.0)
    assert float(ext["td_error_heldout"][0]) == pytest.approx(float(expect), rel=1e-4)
    # the noise check: a second evaluation (10 levels x 1 episode x 8 steps) per step, and a finite SD
    np.testing.assert_array_equal(info.env_steps_eval, [240, 160, 160, 160])
    assert np.all(np.isfinite(ext["state_noise_sd"])) and np.all(ext["state_noise_sd"] >= 0)
    # with the check off (NaN, one evaluation per step): test_shed_method.py::test_hmdp_has_no_diffusion_and_two_real_updates,
    # on its plain h-MDP run, so this file compiles no plain run of its own
