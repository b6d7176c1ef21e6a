"""The native baselines on whole episodes (level_switch="episode"): PLR⊥'s per-slot level switching,
scores accumulated across rollouts and robust (masked) PPO update, ACCEL's children, PAIRED's
per-level regret, and the sampler pieces they use."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from shed_jax.methods.level_sampler import LevelSampler, LevelSamplerConfig
from shed_jax.methods.plr import Slots, accumulate
from shed_jax.methods.registry import make_method
from shed_jax.student import PPOConfig, make_student


# small students: these tests check bookkeeping, not learning
SMALL = dict(num_envs=8, num_steps=16, update_epochs=1, num_minibatches=2, actor_hidden=(8,), critic_hidden=(8,))


def _episode_steps(name: str, config: dict, seed: int, steps: int):
    """``name`` on CartPole with whole episodes: yields ``(method, before, after)`` for each budget step,
    ``before`` = (method state, student state) and ``after`` = (method state, student state, StepInfo)."""
    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole", **SMALL))
    m = make_method(name, env, student, {"updates_per_step": 1, "level_switch": "episode", **config})
    key = jax.random.PRNGKey(seed)
    # init and begin_episode as one program (not op by op); the same calls on the same keys
    ms, s = jax.jit(lambda key: m.begin_episode(key, m.init(key), student.init(key)))(key)
    step = jax.jit(m.step)
    for i in range(steps):
        before = (ms, s)
        ms, s, info = step(jax.random.fold_in(key, i), ms, s)
        yield m, before, (ms, s, info)


def _slots(n):
    z = jnp.zeros((n,), jnp.float32)
    return Slots(vecs=jnp.zeros((n, 1)), seeds=jnp.zeros((n,), jnp.int32), idx=jnp.full((n,), -1, jnp.int32),
                 total=z, count=z, max_return=jnp.full((n,), -jnp.inf))


def test_an_episode_over_three_rollouts_scores_as_in_one():
    """Slot 0's episode runs 14 steps over rollouts of 6 (done at step 13); slot 1's ends at step 2 and
    its next level's at step 16. Sums carried across rollouts equal those of one 18-step rollout."""
    T, n = 6, 2
    rng = np.random.default_rng(0)
    terms = rng.integers(0, 9, (3 * T, n)).astype(np.float32)  # integers: sums are exact in any order
    targets = rng.integers(-5, 20, (3 * T, n)).astype(np.float32)
    dones = np.zeros((3 * T, n), bool)
    dones[13, 0] = dones[2, 1] = dones[16, 1] = True
    _, _, whole, _ = accumulate(_slots(n), jnp.asarray(terms), jnp.asarray(targets), jnp.asarray(dones))
    slots, ended_at = _slots(n), {}
    for r in range(3):
        sl = slice(r * T, (r + 1) * T)
        moved, old, ended, after = accumulate(slots, jnp.asarray(terms[sl]), jnp.asarray(targets[sl]), jnp.asarray(dones[sl]))
        for j in range(n):
            if moved[j] and j not in ended_at:
                ended_at[j] = tuple(float(e[j]) for e in ended)
        slots = slots.replace(total=after[0], count=after[1], max_return=after[2])
    for j in range(n):
        assert ended_at[j] == tuple(float(e[j]) for e in whole)
    assert ended_at[0] == (float(terms[:14, 0].sum()), 14.0, float(targets[:14, 0].max()))
    assert ended_at[1] == (float(terms[:3, 1].sum()), 3.0, float(targets[:3, 1].max()))
    # slot 1's second level: steps 3..16 inside the last rollout's pieces
    moved, old, ended, after = accumulate(_slots(n), jnp.asarray(terms[3:17]), jnp.asarray(targets[3:17]),
                                          jnp.asarray(dones[3:17]))
    assert float(ended[0][1]) == float(terms[3:17, 1].sum()) and float(ended[1][1]) == 14.0
    # the steps after a done belong to the next level; a slot without a done keeps everything
    moved, old, ended, after = accumulate(_slots(n), jnp.asarray(terms[12:18]), jnp.asarray(targets[12:18]),
                                          jnp.asarray(dones[12:18]))
    assert list(np.asarray(moved)) == [True, True]
    assert np.array_equal(np.asarray(old[:, 0]), [True, True, False, False, False, False])
    assert float(after[0][0]) == float(terms[14:18, 0].sum()) and float(after[1][0]) == 4.0


def _student(num_envs=4, num_steps=16):
    env = envs.make("cartpole")
    return env, make_student(env, PPOConfig.for_env("cartpole", num_envs=num_envs, num_steps=num_steps,
                                                    update_epochs=2, num_minibatches=2))


def test_masked_update_ignores_masked_transitions_and_all_true_is_the_plain_update():
    env, student = _student()
    key = jax.random.PRNGKey(0)
    s, traj = jax.jit(lambda key: student.rollout(student.init(key), key))(key)
    mask = jnp.zeros((16, 4), bool).at[:, :2].set(True)  # slots 0 and 1 trainable
    # changing what the masked-out slots did (their actions and old log-probs) changes nothing
    other = traj.replace(actions=traj.actions.at[:, 2:].set(1 - traj.actions[:, 2:]),
                         log_probs=traj.log_probs.at[:, 2:].add(-3.0))
    # jitted: two programs (masked, plain) for the five updates, not each update op by op
    masked = jax.jit(lambda traj, mask: student.update(s, key, traj, mask=mask))
    plain = jax.jit(lambda traj: student.update(s, key, traj))
    a, _ = masked(traj, mask)
    b, _ = masked(other, mask)
    for x, y in zip(jax.tree_util.tree_leaves(a.params), jax.tree_util.tree_leaves(b.params)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # ... while it does change the unmasked update
    c, _ = plain(other)
    assert any(not np.array_equal(np.asarray(x), np.asarray(y))
               for x, y in zip(jax.tree_util.tree_leaves(a.params), jax.tree_util.tree_leaves(c.params)))
    # an all-True mask is the plain update (to float rounding)
    d, md = masked(traj, jnp.ones((16, 4), bool))
    e, me = plain(traj)
    for x, y in zip(jax.tree_util.tree_leaves(d.params), jax.tree_util.tree_leaves(e.params)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(md["loss"]), float(me["loss"]), rtol=1e-5, atol=1e-6)


def test_sampler_draw_mark_and_masked_writes():
    sampler = LevelSampler(LevelSamplerConfig(capacity=4, min_fill=0.0, replay_prob=1.0))
    buf = sampler.init(1, extra_template=jnp.int32(0))
    buf, idx = sampler.insert_batch(buf, jnp.arange(3.0)[:, None], jnp.array([1.0, 2.0, 3.0]), jnp.arange(3, dtype=jnp.int32),
                                    mask=jnp.array([True, False, True]))
    assert list(np.asarray(idx)) == [0, -1, 1] and int(buf.size) == 2
    assert list(np.asarray(buf.levels[:2, 0])) == [0.0, 2.0]
    # draw is free of side effects; sample = draw + counting every draw
    idx2, lv, ex = sampler.draw(buf, jax.random.PRNGKey(1), 3)
    b1, i1, l1, e1 = sampler.sample(buf, jax.random.PRNGKey(1), 3)
    assert np.array_equal(np.asarray(idx2), np.asarray(i1)) and int(b1.episode_count) == int(buf.episode_count) + 3
    marked = sampler.mark_sampled(buf, idx2, jnp.ones(3, bool), jnp.ones(3, bool))
    np.testing.assert_array_equal(np.asarray(marked.timestamps), np.asarray(b1.timestamps))
    assert int(marked.episode_count) == int(b1.episode_count)
    # only the levels handed to a slot count: one replay used, one new level used, one draw unused
    m2 = sampler.mark_sampled(buf, jnp.array([0, 1, 1]), jnp.array([True, False, True]), jnp.array([True, True, False]))
    assert int(m2.episode_count) == int(buf.episode_count) + 2
    assert int(m2.timestamps[0]) == int(m2.episode_count) and int(m2.timestamps[1]) == int(buf.timestamps[1])
    # masked score writes
    b3 = sampler.update_scores(buf, jnp.array([0, 1]), jnp.array([9.0, 8.0]), mask=jnp.array([False, True]))
    assert list(np.asarray(b3.scores[:2])) == [1.0, 8.0]


def test_plr_whole_episodes_keeps_levels_until_episode_ends_and_trains_only_on_replays():
    seen_train = seen_new = seen_zero = 0
    sampler = {"capacity": 8, "min_fill": 0.25, "replay_prob": 0.5}
    for m, (prev_ms, prev_s), (ms, s, info) in _episode_steps("plr", {"sampler": sampler}, 3, 25):
        prev_slots, prev_time = prev_ms.slots, np.asarray(prev_s.env_state.time)
        # the slot records what the student plays
        np.testing.assert_array_equal(np.asarray(m.codec.space.to_vector(s.levels)), np.asarray(ms.slots.vecs))
        changed = np.any(np.asarray(ms.slots.vecs) != np.asarray(prev_slots.vecs), axis=-1)
        # a slot changes level only if an episode ended in this rollout (its episode clock restarted)
        time = np.asarray(s.env_state.time)
        assert np.all(time[changed] < 16)
        kept = ~changed & (prev_time + 16 == time)
        assert np.all(np.asarray(ms.slots.count)[kept] == np.asarray(prev_slots.count)[kept] + 16)
        n_train = int(info.env_steps_train)
        # steps trained on = steps played on replayed levels (old or new level of each slot)
        assert n_train + int(info.env_steps_eval) == 8 * 16
        prev_idx, idx = np.asarray(prev_slots.idx), np.asarray(ms.slots.idx)
        if np.all(prev_idx < 0) and np.all(idx < 0):  # only new levels played: no gradient at all
            assert n_train == 0
        if np.all(prev_idx >= 0) and not changed.any() and np.all(kept):  # only replayed levels played
            assert n_train == 8 * 16
        if n_train == 0:
            assert np.isnan(float(info.extras["ppo"]["loss"]))
        else:
            assert np.isfinite(float(info.extras["ppo"]["loss"]))
        seen_train += n_train > 0
        seen_zero += n_train == 0
        seen_new += int(info.num_new_levels)
        assert int(ms.buffer.size) <= 8
    assert seen_train > 0 and seen_new > 0
    assert seen_zero > 0  # the first steps (buffer below min_fill) play new levels only


def test_accel_whole_episodes_plays_a_child_after_each_replayed_level():
    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole", **SMALL))
    with pytest.raises(ValueError, match="parents='dcd_easy' picks parents from one rollout"):
        make_method("accel", env, student, {"level_switch": "episode", "parents": "dcd_easy"})
    children = 0
    sampler = {"capacity": 8, "min_fill": 0.25, "replay_prob": 0.9}
    for m, (prev_ms, _), (ms, s, info) in _episode_steps("accel", {"sampler": sampler}, 5, 20):
        prev = prev_ms.slots
        changed = np.any(np.asarray(ms.slots.vecs) != np.asarray(prev.vecs), axis=-1)
        after_replay = changed & (np.asarray(prev.idx) >= 0)
        # a slot that left a replayed level now plays a new level (its child), never a replay
        assert np.all(np.asarray(ms.slots.idx)[after_replay] == -1)
        children += int(after_replay.sum())
    assert children > 0


def test_paired_returns_on_the_newest_level_count_only_episodes_played_on_it():
    from types import SimpleNamespace

    from shed_jax.methods.paired import newest_level_returns

    dones = np.zeros((6, 3), bool)
    dones[1, 0] = dones[4, 0] = True  # slot 0: on the newest level from the start: both episodes count
    dones[2, 1] = dones[5, 1] = True  # slot 1: moves at step 2; only the episode ending at 5 counts
    dones[3, 2] = True  # slot 2: moves at step 3, no episode ends on the newest level
    rets = np.arange(18, dtype=np.float32).reshape(6, 3)
    traj = SimpleNamespace(dones=jnp.asarray(dones), episode_returns=jnp.asarray(rets))
    total, count, best = newest_level_returns(jnp.array([True, False, False]), traj)
    assert list(np.asarray(count)) == [2.0, 1.0, 0.0]
    assert list(np.asarray(total)) == [rets[1, 0] + rets[4, 0], rets[5, 1], 0.0]
    assert float(best[0]) == rets[4, 0] and float(best[1]) == rets[5, 1] and np.isneginf(float(best[2]))


def test_paired_whole_episodes_trains_the_adversary_on_completed_levels_only():
    proposed = 0
    steps = _episode_steps("paired", {"minibatches": 2, "epochs": 1}, 11, 15)
    for i, (m, (prev_ms, prev_s), (ms, s, info)) in enumerate(steps):
        if i == 0:  # begin_episode put both agents of every slot on its level
            assert np.all(np.asarray(prev_ms.slots.pro_on)) and np.all(np.asarray(prev_ms.slots.ant_on))
            np.testing.assert_array_equal(np.asarray(m.codec.space.to_vector(prev_s.levels)),
                                          np.asarray(prev_ms.slots.vecs))
        prev_slots, prev_adv = prev_ms.slots, prev_ms.adversary
        new = np.asarray(info.extras["levels_trained_mask"])
        proposed += int(new.sum())
        assert int(info.num_new_levels) == int(new.sum())
        # a slot whose level did not complete keeps its level and its statistics grow
        keep = ~new
        np.testing.assert_array_equal(np.asarray(ms.slots.vecs)[keep], np.asarray(prev_slots.vecs)[keep])
        assert np.all(np.asarray(ms.slots.pro_count)[keep] >= np.asarray(prev_slots.pro_count)[keep])
        # a new level starts with no agent on it and empty statistics
        assert not np.any(np.asarray(ms.slots.pro_on)[new]) and np.all(np.asarray(ms.slots.pro_count)[new] == 0)
        # the adversary moves only when some level completed
        moved = any(not np.array_equal(np.asarray(a), np.asarray(b)) for a, b in
                    zip(jax.tree_util.tree_leaves(ms.adversary.params), jax.tree_util.tree_leaves(prev_adv.params)))
        assert moved == bool(new.any())
        if new.any():
            assert np.isfinite(float(info.teacher_reward)) and float(info.teacher_reward) >= 0
            # the agents' returns on the completed levels: CartPole episodes score 1 per step, at most 500
            for k in ("antagonist_max_return", "protagonist_return"):
                assert 1.0 <= float(info.extras[k]) <= 500.0, (k, float(info.extras[k]))
    assert proposed > 0


def test_running_mean_std_masked_update_equals_the_update_on_the_kept_samples():
    from shed_jax.student.normalization import RunningMeanStd

    x = jnp.array([1.0, 5.0, -2.0, 7.0, 3.0])
    mask = jnp.array([True, False, True, True, False])
    rms = RunningMeanStd.create(()).update(jnp.array([0.5, 1.5]))
    a, b = rms.update(x, mask), rms.update(x[np.asarray(mask)])
    for u, v in ((a.mean, b.mean), (a.var, b.var), (a.count, b.count)):
        np.testing.assert_allclose(float(u), float(v), rtol=1e-6)
    none = rms.update(x, jnp.zeros(5, bool))  # nothing kept: unchanged
    np.testing.assert_allclose([float(none.mean), float(none.var), float(none.count)],
                               [float(rms.mean), float(rms.var), float(rms.count)], rtol=1e-6)
