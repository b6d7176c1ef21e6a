"""DDPG teacher: action bounds, target/critic arithmetic, soft updates, and a bandit it must solve."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from shed_jax.teacher.buffers import Transition
from shed_jax.teacher.ddpg import Actor, Critic, DDPGConfig, TwinCritic, make_ddpg

SMALL = dict(hidden=(32, 32))


def _batch(key, B=8, m=3, da=2, done=None):
    ks = jax.random.split(key, 4)
    return Transition(
        s=jax.random.normal(ks[0], (B, m)),
        u=jax.random.uniform(ks[1], (B, da), minval=-1, maxval=1),
        r=jax.random.normal(ks[2], (B,)),
        s_next=jax.random.normal(ks[3], (B, m)),
        done=jnp.zeros(B) if done is None else done,
    )


def test_network_shapes_and_action_bounds():
    cfg = DDPGConfig(state_dim=10, action_dim=15)  # the official sizes: 400-300
    agent = make_ddpg(cfg)
    st = jax.jit(agent.init)(jax.random.PRNGKey(0))
    shapes = jax.tree_util.tree_map(jnp.shape, st.actor_params)["params"]
    assert [shapes[f"Dense_{i}"]["kernel"] for i in range(3)] == [(10, 400), (400, 300), (300, 15)]
    cshapes = jax.tree_util.tree_map(jnp.shape, st.critic_params)["params"]
    assert [cshapes[f"Dense_{i}"]["kernel"] for i in range(3)] == [(25, 400), (400, 300), (300, 1)]
    s = 100 * jax.random.normal(jax.random.PRNGKey(1), (64, 10))
    act = jax.jit(agent.act)
    u_det = act(st, s)
    u_noisy = act(st, s, jax.random.PRNGKey(2))
    assert u_det.shape == (64, 15) and bool(jnp.all(jnp.abs(u_noisy) <= 1.0))
    assert not np.allclose(u_det, u_noisy)
    # sigma = 0 (official code) is deterministic even with a key; both sides jitted, so the bitwise
    # comparison does not depend on how the compiler fuses the saturated tanh
    zero = make_ddpg(DDPGConfig(10, 15, explore_sigma=0.0))
    np.testing.assert_array_equal(jax.jit(zero.act)(st, s, jax.random.PRNGKey(2)), u_det)
    # exploration noise has the configured scale where the actor is not saturated
    sm = make_ddpg(DDPGConfig(3, 2, explore_sigma=0.1, **SMALL))
    st2 = jax.jit(sm.init)(jax.random.PRNGKey(0))
    s0 = jnp.zeros((4000, 3))
    d = jax.jit(lambda st, k: sm.act(st, s0, k) - sm.act(st, s0))(st2, jax.random.PRNGKey(3))
    assert float(jnp.std(d)) == pytest.approx(0.1, rel=0.1)


def test_update_arithmetic_critic_target_and_soft_update():
    cfg = DDPGConfig(3, 2, tau=0.1, gamma=0.9, reward_norm=False, **SMALL)
    agent = make_ddpg(cfg)
    st = jax.jit(agent.init)(jax.random.PRNGKey(0))
    # make targets differ from the online nets so the soft update is visible
    st = st.replace(target_actor_params=jax.tree_util.tree_map(lambda x: x + 0.05, st.target_actor_params))
    done = jnp.array([0, 1, 0, 1, 0, 0, 1, 0], jnp.float32)
    b = _batch(jax.random.PRNGKey(1), done=done)
    new, metrics = jax.jit(agent.update)(st, b)
    actor, critic = Actor(2, (32, 32)), Critic((32, 32))
    q_next = critic.apply(st.target_critic_params, b.s_next, actor.apply(st.target_actor_params, b.s_next))
    y = np.asarray(b.r) + 0.9 * (1 - np.asarray(done)) * np.asarray(q_next)
    q = critic.apply(st.critic_params, b.s, b.u)
    assert float(metrics["critic_loss"]) == pytest.approx(float(np.mean((np.asarray(q) - y) ** 2)), rel=1e-5)
    assert float(metrics["target_mean"]) == pytest.approx(float(np.mean(y)), rel=1e-5)
    # actor loss uses the updated critic and the old actor
    a_loss = -np.mean(np.asarray(critic.apply(new.critic_params, b.s, actor.apply(st.actor_params, b.s))))
    assert float(metrics["actor_loss"]) == pytest.approx(a_loss, rel=1e-5)
    # soft update by hand: target' = tau * new_online + (1 - tau) * old_target, every leaf
    for tgt_new, online_new, tgt_old in (
        (new.target_actor_params, new.actor_params, st.target_actor_params),
        (new.target_critic_params, new.critic_params, st.target_critic_params),
    ):
        expect = jax.tree_util.tree_map(lambda o, t: 0.1 * o + 0.9 * t, online_new, tgt_old)
        jax.tree_util.tree_map(lambda a, e: np.testing.assert_allclose(a, e, rtol=1e-5, atol=1e-7), tgt_new, expect)
    assert int(new.num_updates) == 1
    # online params moved
    assert not np.allclose(new.critic_params["params"]["Dense_0"]["kernel"], st.critic_params["params"]["Dense_0"]["kernel"])


def test_reward_normalisation_per_part():
    agent = make_ddpg(DDPGConfig(3, 2, gamma=0.0, **SMALL))  # gamma 0: target = normalised reward
    st = jax.jit(agent.init)(jax.random.PRNGKey(0))
    b = _batch(jax.random.PRNGKey(1)).replace(r=jnp.array([1.0, 2.0, 3.0, 4.0, 100.0, 200.0, 300.0, 400.0]))
    _, m_all = jax.jit(agent.update)(st, b)
    _, m_mixed = jax.jit(agent.update)(st, b, jnp.arange(8) < 4)  # real items first, as buffers.sample_mixed lays out
    # targets are z-scores: mean zero either way; but per-part scaling changes the critic loss
    assert abs(float(m_all["target_mean"])) < 1e-5 and abs(float(m_mixed["target_mean"])) < 1e-5
    actor, critic = Actor(2, (32, 32)), Critic((32, 32))
    q = np.asarray(critic.apply(st.critic_params, b.s, b.u))
    z = np.concatenate([(np.arange(1, 5) - 2.5) / (np.sqrt(1.25) + 1e-6)] * 2)
    assert float(m_mixed["critic_loss"]) == pytest.approx(float(np.mean((q - z) ** 2)), rel=1e-4)


def test_learning_rates_come_from_the_config_and_may_be_traced():
    """Adam's first step moves a weight by lr * |g| / (|g| + eps), about lr: the config's learning
    rates set the step size; ``with_learning_rates`` swaps in traced ones, so a vmap over learning
    rates is one program whose rows equal agents built with those rates."""
    b = _batch(jax.random.PRNGKey(1))
    slow = make_ddpg(DDPGConfig(3, 2, **SMALL))  # 1e-3 both
    fast = make_ddpg(DDPGConfig(3, 2, actor_lr=1e-2, critic_lr=3e-2, **SMALL))
    st = jax.jit(slow.init)(jax.random.PRNGKey(0))
    st_fast = jax.jit(fast.init)(jax.random.PRNGKey(0))
    jax.tree_util.tree_map(np.testing.assert_array_equal, st.actor_params, st_fast.actor_params)  # lrs change no weights
    new_slow, new_fast = jax.jit(slow.update)(st, b)[0], jax.jit(fast.update)(st_fast, b)[0]

    def largest_step(new, old):
        return max(float(jnp.max(jnp.abs(a - o))) for a, o in zip(jax.tree_util.tree_leaves(new), jax.tree_util.tree_leaves(old)))

    for new, (lr_a, lr_c) in ((new_slow, (1e-3, 1e-3)), (new_fast, (1e-2, 3e-2))):
        assert largest_step(new.critic_params, st.critic_params) == pytest.approx(lr_c, rel=1e-3)
        assert largest_step(new.actor_params, st.actor_params) == pytest.approx(lr_a, rel=1e-3)
    lrs = lambda s: (float(s.actor_opt_state.hyperparams["learning_rate"]), float(s.critic_opt_state.hyperparams["learning_rate"]))
    assert lrs(st) == pytest.approx((1e-3, 1e-3)) and lrs(st_fast) == pytest.approx((1e-2, 3e-2))

    @jax.jit
    @jax.vmap
    def update_at(actor_lr, critic_lr):
        return slow.update(slow.with_learning_rates(st, actor_lr, critic_lr), b)[0]

    rows = update_at(jnp.array([1e-3, 1e-2]), jnp.array([1e-3, 3e-2]))
    for i, expect in enumerate((new_slow, new_fast)):
        for a, e in zip(jax.tree_util.tree_leaves(rows), jax.tree_util.tree_leaves(expect)):
            np.testing.assert_allclose(np.asarray(a)[i], np.asarray(e), rtol=1e-5, atol=1e-7)  # vmap: float32 rounding
    assert update_at._cache_size() == 1


def test_config_validation():
    with pytest.raises(ValueError, match="tau"):
        DDPGConfig(3, 2, tau=0.0)
    with pytest.raises(ValueError, match="gamma"):
        DDPGConfig(3, 2, gamma=1.5)
    with pytest.raises(ValueError, match="action_dim"):
        DDPGConfig(3, 0)
    with pytest.raises(ValueError, match="explore_sigma"):
        DDPGConfig(3, 2, explore_sigma=-0.1)
    with pytest.raises(ValueError, match="twin_critics must be True or False"):
        DDPGConfig(3, 2, twin_critics=1)
    with pytest.raises(ValueError, match="actor_delay must be an int >= 1"):
        DDPGConfig(3, 2, actor_delay=0)


def test_twin_critics_fit_both_to_the_smaller_target_and_the_actor_follows_q1():
    cfg = DDPGConfig(3, 2, tau=0.1, gamma=0.9, reward_norm=False, twin_critics=True, **SMALL)
    agent = make_ddpg(cfg)
    st = jax.jit(agent.init)(jax.random.PRNGKey(0))
    q1, q2 = st.critic_params["params"]["q1"], st.critic_params["params"]["q2"]
    assert not np.allclose(q1["Dense_0"]["kernel"], q2["Dense_0"]["kernel"])  # two independent inits
    done = jnp.array([0, 1, 0, 0, 0, 0, 1, 0], jnp.float32)
    b = _batch(jax.random.PRNGKey(1), done=done)
    new, metrics = jax.jit(agent.update)(st, b)
    actor, critic = Actor(2, (32, 32)), TwinCritic((32, 32))
    q_next = np.asarray(critic.apply(st.target_critic_params, b.s_next, actor.apply(st.target_actor_params, b.s_next)))
    assert q_next.shape == (2, 8) and not np.allclose(q_next[0], q_next[1])
    y = np.asarray(b.r) + 0.9 * (1 - np.asarray(done)) * q_next.min(axis=0)
    q = np.asarray(critic.apply(st.critic_params, b.s, b.u))
    assert float(metrics["target_mean"]) == pytest.approx(float(np.mean(y)), rel=1e-5)
    assert float(metrics["critic_loss"]) == pytest.approx(float(np.mean((q[0] - y) ** 2) + np.mean((q[1] - y) ** 2)), rel=1e-5)
    assert float(metrics["q_mean"]) == pytest.approx(float(np.mean(q[0])), rel=1e-5)
    a_loss = -np.mean(np.asarray(critic.apply(new.critic_params, b.s, actor.apply(st.actor_params, b.s)))[0])
    assert float(metrics["actor_loss"]) == pytest.approx(a_loss, rel=1e-5)
    # act and the TD-error diagnostic work on the twin state
    np.testing.assert_allclose(np.asarray(agent.q(st, b.s, b.u)), q[0], rtol=1e-6)
    assert agent.td_errors(st, b.replace(r=b.r)).shape == (8,)


def test_actor_delay_updates_the_actor_and_targets_every_kth_call_only():
    cfg = DDPGConfig(3, 2, tau=0.1, reward_norm=False, actor_delay=2, **SMALL)
    agent = make_ddpg(cfg)
    st0 = jax.jit(agent.init)(jax.random.PRNGKey(0))
    update = jax.jit(agent.update)
    st1, _ = update(st0, _batch(jax.random.PRNGKey(1)))
    st2, _ = update(st1, _batch(jax.random.PRNGKey(2)))
    same = lambda a, b: all(np.array_equal(x, y) for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))
    slow = ("actor_params", "target_actor_params", "target_critic_params", "actor_opt_state")
    assert not same(st1.critic_params, st0.critic_params)  # the critic learns on every call
    assert all(same(getattr(st1, k), getattr(st0, k)) for k in slow)  # call 1: held
    assert not same(st2.critic_params, st1.critic_params)
    assert not any(same(getattr(st2, k), getattr(st1, k)) for k in slow)  # call 2: moved
    # the delayed step is the plain step on the same state: actor_delay=1 from st1 gives the same actor
    plain, _ = jax.jit(make_ddpg(DDPGConfig(3, 2, tau=0.1, reward_norm=False, **SMALL)).update)(st1, _batch(jax.random.PRNGKey(2)))
    assert same(plain.actor_params, st2.actor_params) and same(plain.target_critic_params, st2.target_critic_params)
    assert int(st2.num_updates) == 2


BANDIT_SEEDS, BANDIT_STEPS = 8, 3000


def _bandit_errors(seed=0, **td3):
    """BANDIT_SEEDS seeds of DDPG trained (vmapped) on the bandit below from keys split off PRNGKey(seed):
    |actor - argmax| before and after training on 256 fixed test states [seeds, 256, 2], the final
    critic loss [seeds], and the test states."""
    cfg = DDPGConfig(2, 2, hidden=(64, 64), tau=0.05, reward_norm=False, **td3)
    agent = make_ddpg(cfg)
    W = jnp.array([[1.0, -0.5], [0.3, 0.8]])
    target = lambda s: 0.5 * jnp.tanh(s @ W)
    s_test = jax.random.normal(jax.random.PRNGKey(9), (256, 2))

    def step(st, key):
        ks, ku = jax.random.split(key)
        s = jax.random.normal(ks, (64, 2))
        u = jax.random.uniform(ku, (64, 2), minval=-1, maxval=1)  # uniform exploration of the action box
        r = -jnp.sum((u - target(s)) ** 2, -1)
        b = Transition(s=s, u=u, r=r, s_next=s, done=jnp.ones(64))
        return agent.update(st, b)

    @jax.jit
    @jax.vmap
    def train(key):
        st0 = agent.init(key)
        st, metrics = jax.lax.scan(step, st0, jax.random.split(key, BANDIT_STEPS))
        error = lambda st: jnp.abs(agent.act(st, s_test) - target(s_test))
        return error(st0), error(st), jnp.mean(metrics["critic_loss"][-100:])

    err0, err, critic_loss = train(jax.random.split(jax.random.PRNGKey(seed), BANDIT_SEEDS))
    return np.asarray(err0), np.asarray(err), np.asarray(critic_loss), np.asarray(s_test)


@pytest.mark.optimized  # a training run
def test_solves_one_step_quadratic_bandit():
    """r(s, u) = -||u - c(s)||^2 with c(s) = 0.5 * tanh(s W): the actor must output the argmax c(s).

    Eight seeds at once, 3000 steps: after the former 1500 steps a seed's mean error ranged
    0.045-0.081 and its largest error reached 0.38 (34 seeds), in 7 of 10 seeds at the test state
    farthest out (|s| = 3.6), where there is almost no training data. So the mean error is checked
    per seed and over seeds, and the largest error over the states with |s| <= 2.5 (249 of the 256).
    """
    err0, err, critic_loss, s_test = _bandit_errors()
    bulk = np.linalg.norm(s_test, axis=1) <= 2.5
    seed_mean = err.mean(axis=(1, 2))
    # 5 root keys x 8 seeds x 2 ISAs: err0 min 0.257 (> 0.2); mean err: over seeds max 0.053 (< 0.08), per seed
    # max 0.067 (< 0.1); bulk max 0.240 (< 0.3); critic loss max 0.0015 (< 0.02)
    assert err0.mean(axis=(1, 2)).min() > 0.2, err0.mean(axis=(1, 2))  # untrained actors are far off
    assert seed_mean.mean() < 0.08 and seed_mean.max() < 0.1, seed_mean
    assert err[:, bulk].max() < 0.3, err[:, bulk].max(axis=(1, 2))
    # the critic learnt the reward: small loss at the end
    assert critic_loss.max() < 0.02, critic_loss


@pytest.mark.optimized  # a training run
def test_td3_switches_still_solve_the_bandit():
    """Twin critics and a delayed actor (half the actor steps): the bandit is still solved. The
    critic loss is the sum of the two critics' losses. Measured over 5 root keys x 8 seeds, default and
    AVX2 ISAs: err0 min 0.257, mean err over seeds max 0.053, per seed max 0.060, critic loss max 0.0034."""
    err0, err, critic_loss, _ = _bandit_errors(twin_critics=True, actor_delay=2)
    seed_mean = err.mean(axis=(1, 2))
    assert err0.mean(axis=(1, 2)).min() > 0.2, err0.mean(axis=(1, 2))
    assert seed_mean.mean() < 0.1 and seed_mean.max() < 0.15, seed_mean
    assert critic_loss.max() < 0.04, critic_loss
