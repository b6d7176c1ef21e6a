"""The UED baselines behind the method interface, on a tiny CartPole student.

Each method: two budget steps compiled once, levels inside Θ, budget accounting against the
schedule the configuration forces, determinism for a key. Method-specific checks: PLR⊥ takes no
gradient on new levels, ACCEL inserts edited children, ACCEL-NR's next levels are edits of the
current ones, PAIRED's regret sign and its adversary's gradient direction, the DR draws differ per
slot and per update, and the official-code DR distribution.
"""
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

import envs
from envs.core import EnvParams, ParamSpace
from envs.lander import LunarLander
from shed_jax.levels import slot_returns
from shed_jax.methods.accel import dcd_easy_parents, rank_probabilities
from shed_jax.methods.dr import DR, DRConfig
from shed_jax.methods.level_sampler import LevelSamplerConfig
from shed_jax.methods.paired import Adversary, PAIREDConfig, regret
from shed_jax.methods.registry import METHODS, make_method
from shed_jax.student import PPOConfig, make_student

E, S = 4, 8  # slots x rollout length of the tiny student


@pytest.fixture(scope="module")
def setup():
    env = envs.make("cartpole")
    cfg = PPOConfig.for_env(
        "cartpole", num_envs=E, num_steps=S, update_epochs=1, num_minibatches=2, actor_hidden=(8,), critic_hidden=(8,)
    )
    return env, make_student(env, cfg)


def _two_steps(method, student):
    """keys [B] -> (info 1, info 2, initial params, final params, method state, PPO updates after
    each step), all with a leading seed axis.

    Seeds are ``vmap``ped (the contract: vmappable over seeds) and ``step`` is jitted on its own
    and called twice, so each method compiles one step.
    """
    start = jax.jit(jax.vmap(lambda k_s, k_m, k_b: method.begin_episode(k_b, method.init(k_m), student.init(k_s))))
    step = jax.jit(jax.vmap(method.step))

    def run(keys):
        ks = jax.vmap(lambda k: jax.random.split(k, 5))(keys)
        m, s = start(ks[:, 0], ks[:, 1], ks[:, 2])
        params0 = s.params
        m, s, i1 = step(ks[:, 3], m, s)
        n1 = np.asarray(s.update_step)
        m, s, i2 = step(ks[:, 4], m, s)
        return i1, i2, params0, s.params, m, (n1, np.asarray(s.update_step))

    return run


def _seed(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def _changed(p0, p1):
    return any(not np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(p0), jax.tree_util.tree_leaves(p1)))


def _check_common(env, run, num_levels):
    """Run seeds (0, 0, 1) in one vmapped call; check levels in Θ and determinism; return seed 0."""
    space = env.param_space
    out = run(jnp.stack([jax.random.PRNGKey(0), jax.random.PRNGKey(0), jax.random.PRNGKey(1)]))
    first, again, other = (_seed(out[:5], i) for i in range(3))
    for info in (first[0], first[1], other[1]):
        lv = np.asarray(info.levels)
        assert lv.shape == (num_levels, space.dim)
        assert np.all(lv >= space.low - 1e-5) and np.all(lv <= space.high + 1e-5)
    for a, b in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(again)):
        np.testing.assert_array_equal(a, b)  # same key -> identical
    assert not np.array_equal(np.asarray(first[1].levels), np.asarray(other[1].levels))  # other key -> other levels
    updates = (int(out[5][0][0]), int(out[5][1][0]))
    return (*first, updates)


def test_registry_knows_every_method_and_validates(setup):
    env, student = setup
    assert set(METHODS) == {"shed", "hmdp", "dr", "plr", "accel", "accel-norevisit", "paired", "hmdp-x", "shed-x"}
    with pytest.raises(ValueError, match="unknown method 'pbt'"):
        make_method("pbt", env, student)
    with pytest.raises(ValueError, match=r"unknown config field\(s\) \['replay'\]"):
        make_method("plr", env, student, {"replay": 0.3})
    with pytest.raises(ValueError, match="updates_per_step"):
        make_method("dr", env, student, {"updates_per_step": 0})
    with pytest.raises(ValueError, match="hmdp"):
        make_method("hmdp", env, student)  # built by shed_jax.methods.hierarchical
    assert make_method("accel", env, student).config.sampler.replay_prob == 0.9
    assert make_method("plr", env, student).config.sampler.replay_prob == 0.5


def test_dr(setup):
    env, student = setup
    method = make_method("dr", env, student, {"level_switch": "rollout", "updates_per_step": 2})
    i1, i2, p0, p1, _, updates = _check_common(env, _two_steps(method, student), 2 * E)
    assert int(i1.env_steps_train) == 2 * E * S and int(i1.env_steps_eval) == 0
    assert int(i1.num_new_levels) == 2 * E and np.isnan(float(i1.teacher_reward))
    assert updates == (2, 4)
    lv = np.asarray(jnp.concatenate([i1.levels, i2.levels]))
    assert len(np.unique(lv, axis=0)) == len(lv)  # every slot of every update has its own draw
    assert _changed(p0, p1)


def test_dr_episode_level_switch_runs_episodes_across_rollouts(setup):
    """level_switch="episode": begin_episode puts DR levels on the fresh student's slots; a slot takes
    a new level only after an episode end, and otherwise keeps its level and its running episode."""
    env, student = setup
    method = make_method("dr", env, student, {"updates_per_step": 2, "level_switch": "episode"})
    k = jax.random.split(jax.random.PRNGKey(5), 4)
    m, s0 = jax.jit(lambda k: method.begin_episode(k[0], method.init(k[1]), student.init(k[2])))(k)  # one program, not op by op
    lo, hi = method.codec.space.low, method.codec.space.high
    start = np.asarray(method.codec.space.to_vector(s0.levels))
    assert np.all((start >= lo - 1e-6) & (start <= hi + 1e-6)) and len(np.unique(start, axis=0)) == E  # DR draws
    m, s1, info = jax.jit(method.step)(k[3], m, s0)
    used = np.asarray(info.extras["levels_trained_mask"]).reshape(2, E)  # [update, slot]: an episode ended
    assert int(info.num_new_levels) == used.sum() and int(info.env_steps_train) == 2 * E * S
    end = np.asarray(method.codec.space.to_vector(s1.levels))
    drawn = np.asarray(info.levels).reshape(2, E, -1)
    stayed = ~used.any(axis=0)
    assert stayed.any() and not stayed.all(), used  # this key gives both kinds of slot
    np.testing.assert_array_equal(end[stayed], start[stayed])
    np.testing.assert_array_equal(np.asarray(s1.env_state.time)[stayed], 2 * S)  # one episode, never reset
    last = np.where(used[1], 1, 0)  # a moved slot holds the level drawn in the last update it moved in
    moved = ~stayed
    np.testing.assert_array_equal(end[moved], drawn[last[moved], np.nonzero(moved)[0]])
    with pytest.raises(ValueError, match="level_switch"):
        make_method("dr", env, student, {"level_switch": "step"})


def test_plr_trains_only_on_replayed_levels(setup):
    env, student = setup
    # capacity = slots, replay certain once full: update 1 explores (fills), updates 2-3 replay
    cfg = {"level_switch": "rollout", "updates_per_step": 3, "sampler": LevelSamplerConfig(capacity=E, replay_prob=1.0, min_fill=1.0)}
    method = make_method("plr", env, student, cfg)
    i1, i2, p0, p1, m, updates = _check_common(env, _two_steps(method, student), 3 * E)
    np.testing.assert_array_equal(i1.extras["levels_trained_mask"], [False] * E + [True] * 2 * E)
    assert int(i1.env_steps_train) == 2 * E * S and int(i1.env_steps_eval) == E * S
    assert int(i1.num_new_levels) == E and int(i2.num_new_levels) == 0
    assert int(i2.env_steps_train) == 3 * E * S
    # every replayed level came from the buffer, which holds the explored levels
    held = {tuple(r) for r in np.asarray(m.buffer.levels)}
    assert held == {tuple(r) for r in np.asarray(i1.levels[:E])}
    assert all(tuple(r) in held for r in np.asarray(i2.levels))
    assert int(m.buffer.episode_count) == E + 5 * E  # clock: E new + 5 replays of E
    assert updates == (2, 5)  # PPO updates only on the replays: new levels are rolled out and scored only


def test_accel_inserts_edited_children(setup):
    env, student = setup
    cfg = {"level_switch": "rollout", "updates_per_step": 3, "sampler": LevelSamplerConfig(capacity=3 * E, replay_prob=1.0, min_fill=1 / 3)}
    method = make_method("accel", env, student, cfg)
    i1, i2, p0, p1, m, updates = _check_common(env, _two_steps(method, student), 3 * E)
    # update 1 explores (E new), updates 2, 3 replay and each adds E children scored without gradient
    np.testing.assert_array_equal(i1.extras["levels_trained_mask"], [False] * E + [True] * 2 * E)
    assert int(i1.env_steps_train) == 2 * E * S and int(i1.env_steps_eval) == 3 * E * S
    assert int(i1.num_new_levels) == 3 * E
    assert int(i2.num_new_levels) == 3 * E and int(i2.env_steps_eval) == 3 * E * S
    # every child differs from some step-1 parent in at most num_edits = 3 parameters (d = 3 here),
    # and children fill the buffer beyond the explored levels
    assert int(m.buffer.size) == 3 * E
    assert updates == (2, 5)  # children are scored without a gradient update


def test_accel_norevisit_children_of_previous_levels(setup):
    env, student = setup
    cfg = {"updates_per_step": 2, "num_levels": 2, "num_edits": 1}
    method = make_method("accel-norevisit", env, student, cfg)
    i1, i2, p0, p1, m, updates = _check_common(env, _two_steps(method, student), 2)
    assert int(i1.env_steps_train) == 2 * E * S and int(i1.num_new_levels) == 2
    assert updates == (2, 4)
    parents = np.asarray(i1.levels)[np.asarray(i1.extras["parents"])]
    diff = np.sum(~np.isclose(np.asarray(i2.levels), parents, rtol=0, atol=0), axis=1)
    assert np.all(diff <= 1)  # one edit each
    np.testing.assert_allclose(rank_probabilities(jnp.array([3.0, 1.0, 2.0])), [6 / 11, 2 / 11, 3 / 11], rtol=1e-6)


def test_paired_runs_and_accounts_antagonist(setup):
    env, student = setup
    cfg = {"level_switch": "rollout", "updates_per_step": 2, "minibatches": 2, "epochs": 2, "hidden": (8,)}
    method = make_method("paired", env, student, cfg)
    i1, i2, p0, p1, m, updates = _check_common(env, _two_steps(method, student), 2 * E)
    assert int(i1.env_steps_train) == 2 * E * S and int(i1.extras["env_steps_antagonist"]) == 2 * E * S
    assert updates == (2, 4)
    assert float(i1.teacher_reward) >= 0.0  # regret is clipped at 0
    assert _changed(p0, p1)
    assert _changed(p1, m.antagonist.params)  # the antagonist is a separate learner


def test_paired_regret_sign_and_slot_returns():
    np.testing.assert_allclose(regret(jnp.array([5.0, 1.0, 2.0]), jnp.array([2.0, 3.0, 2.0])), [3.0, 0.0, 0.0])
    # 3 steps x 2 slots: slot 0 finishes episodes with returns 4 and 10, slot 1 finishes none
    traj = types.SimpleNamespace(
        dones=jnp.array([[1, 0], [0, 0], [1, 0]]), episode_returns=jnp.array([[4.0, 0.0], [0.0, 0.0], [10.0, 0.0]])
    )
    mean, best = slot_returns(traj, jnp.array([99.0, 7.0]))
    np.testing.assert_allclose(mean, [7.0, 7.0])
    np.testing.assert_allclose(best, [10.0, 7.0])


def test_paired_adversary_gradient_follows_regret():
    """Toy problem: regret = u_0 - u_1 (+2 to keep it >= 0); adversary updates must raise u_0, lower u_1."""
    adv = Adversary(2, PAIREDConfig(minibatches=2, epochs=4, hidden=(16,), lr=3e-3))
    step = jax.jit(lambda a, k: _adv_iteration(adv, a, k))
    a = adv.init(jax.random.PRNGKey(0))
    means = []
    for i in range(30):
        a, mean_u = step(a, jax.random.PRNGKey(i + 1))
        means.append(np.asarray(mean_u))
    means = np.asarray(means)
    assert means[-5:, 0].mean() > means[:5, 0].mean() + 0.3  # pushed up the regret gradient
    assert means[-5:, 1].mean() < means[:5, 1].mean() - 0.3


def _adv_iteration(adv, a, key):
    k_z, k_act, k_upd = jax.random.split(key, 3)
    z = adv.observe(k_z, 64)
    x, logp, v, u = adv.act(a.params, k_act, z)
    a, _ = adv.update(a, k_upd, z, x, logp, v, u[:, 0] - u[:, 1] + 2.0)  # rewards >= 0 like a regret
    return a, u.mean(0)


@struct.dataclass
class _LanderLike(EnvParams):
    gravity: jax.Array = -10.0
    enable_wind: jax.Array = False
    wind_power: jax.Array = 15.0
    turbulence_power: jax.Array = 1.5


def test_dr_code_distribution_and_lander_theta():
    names = ("gravity", "wind_power", "turbulence_power")
    space = ParamSpace(names, [-11.99, 0.0, 0.0], [-0.01, 20.0, 2.0], _LanderLike(max_steps=jnp.int32(600), gravity=jnp.float32(-10.0), enable_wind=jnp.bool_(False), wind_power=jnp.float32(15.0), turbulence_power=jnp.float32(1.5)))
    env = types.SimpleNamespace(name="lander", param_space=space, ued=LunarLander.ued)
    uniform = DR(env, None, DRConfig())
    vecs, params = uniform.sample_levels(jax.random.PRNGKey(0), 4000)
    v = np.asarray(vecs)
    np.testing.assert_allclose(v.min(0), [-9.0, 0.01, 0.01], atol=0.05)  # docs/design.md §5 teacher box
    np.testing.assert_allclose(v.max(0), [-0.01, 12.0, 1.5], atol=0.05)
    assert np.all(np.asarray(params.enable_wind))  # wind on for every generated level
    assert np.all(np.asarray(params.max_steps) == 600)  # lander training time limit
    code = DR(env, None, DRConfig(distribution="code"))
    vecs, params = code.sample_levels(jax.random.PRNGKey(1), 4000)
    v = np.asarray(vecs)
    np.testing.assert_allclose(v.mean(0), [-10.0, 15.0, 1.5], atol=0.1)
    assert v[:, 0].max() <= -0.01 and v[:, 1].max() <= 19.99 and v[:, 2].min() >= 0.01
    assert abs(np.asarray(params.enable_wind).mean() - 0.5) < 0.04
    np.testing.assert_allclose(np.asarray(params.gravity), v[:, 0])
    with pytest.raises(ValueError, match="lander"):
        DR(types.SimpleNamespace(name="walker", param_space=space), None, DRConfig(distribution="code"))


def test_dcd_easy_parents_lowest_return_minus_value_loss():
    levels = jnp.arange(8.0)[:, None] * jnp.ones((1, 2))
    ret = jnp.array([5.0, 1.0, 9.0, 3.0, 0.0, 7.0, 2.0, 4.0])
    vloss = jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 10.0])  # level 7: 4 - 10 = -6, the lowest
    parents = np.asarray(dcd_easy_parents(levels, ret, vloss))
    np.testing.assert_array_equal(parents[:, 0], [7, 7, 4, 4, 1, 1, 6, 6])


def test_native_methods_warn_when_rollouts_cut_training_episodes():
    """level_switch="rollout" resets every slot each rollout: rollouts shorter than a training episode
    warn, with a rollout shape of the same update size that holds one; whole episodes (the default)
    and block mode never warn."""
    import warnings

    from shed_jax.methods.base import RolloutTruncationWarning

    lander = envs.make("lander")
    paper = make_student(lander, PPOConfig.for_env("lander"))  # 40 x 128; lander training episodes: 600
    for name in ("dr", "plr", "accel", "paired"):
        with pytest.warns(RolloutTruncationWarning, match=r"rollouts of 128 steps .* may last 600 steps") as rec:
            make_method(name, lander, paper, {"level_switch": "rollout"})
        assert "--ppo num_envs=8 --ppo num_steps=640 (the same 5,120 steps per update)" in str(rec[0].message)
    long = make_student(lander, PPOConfig.for_env("lander", num_envs=8, num_steps=640))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RolloutTruncationWarning)
        for name in ("dr", "plr", "accel", "paired"):
            make_method(name, lander, long, {"level_switch": "rollout"})
            make_method(name, lander, paper, None)  # whole episodes: nothing is cut
        make_method("accel-norevisit", lander, paper, None)  # block mode: episodes carry over rollouts
    odd = make_student(lander, PPOConfig.for_env("lander", num_envs=3, num_steps=100, num_minibatches=3))
    with pytest.warns(RolloutTruncationWarning) as rec:  # no rollout >= 600 divides 300 steps: no hint
        make_method("dr", lander, odd, {"level_switch": "rollout"})
    assert "e.g." not in str(rec[0].message)
