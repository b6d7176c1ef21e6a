"""Level sampler: replay probabilities against hand-computed values, insertion rules, dedup,
score updates, replay decisions, and jit/vmap over seeds."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from shed_jax.methods.level_sampler import LevelSampler, LevelSamplerConfig


def _buffer(sampler, scores, timestamps, clock, d=2):
    """A buffer whose first len(scores) rows hold levels [i, 10 i] with the given scores."""
    buf = sampler.init(d)
    n = len(scores)
    levels = jnp.stack([jnp.arange(n, dtype=jnp.float32), 10.0 * jnp.arange(n, dtype=jnp.float32)], -1)
    return buf.replace(
        levels=buf.levels.at[:n].set(levels),
        scores=buf.scores.at[:n].set(jnp.asarray(scores, jnp.float32)),
        timestamps=buf.timestamps.at[:n].set(jnp.asarray(timestamps, jnp.int32)),
        size=jnp.int32(n),
        episode_count=jnp.int32(clock),
    )


def test_rank_and_staleness_probabilities_hand_computed():
    s = LevelSampler(LevelSamplerConfig(capacity=4, temperature=1.0, staleness_coef=0.5))
    buf = _buffer(s, [3.0, 1.0, 2.0], [0, 2, 1], clock=4)
    # ranks 1, 3, 2 -> (1/rank)^1 = 1, 1/3, 1/2, sum 11/6
    np.testing.assert_allclose(s.score_weights(buf), [6 / 11, 2 / 11, 3 / 11, 0.0], rtol=1e-6)
    # staleness c - C_i = 4, 2, 3, sum 9
    np.testing.assert_allclose(s.staleness_weights(buf), [4 / 9, 2 / 9, 3 / 9, 0.0], rtol=1e-6)
    expected = 0.5 * np.array([6 / 11, 2 / 11, 3 / 11, 0]) + 0.5 * np.array([4 / 9, 2 / 9, 3 / 9, 0])
    np.testing.assert_allclose(s.replay_weights(buf), expected, rtol=1e-6)


def test_temperature_sharpens_rank_weights():
    s = LevelSampler(LevelSamplerConfig(capacity=4, temperature=0.5, staleness_coef=0.25))
    buf = _buffer(s, [3.0, 1.0, 2.0], [4, 4, 4], clock=4)
    # (1/rank)^2 = 1, 1/9, 1/4, sum 49/36; staleness all 0 -> P_C uniform over the 3 held levels
    ps = np.array([36 / 49, 4 / 49, 9 / 49, 0.0])
    np.testing.assert_allclose(s.score_weights(buf), ps, rtol=1e-6)
    np.testing.assert_allclose(s.staleness_weights(buf), [1 / 3, 1 / 3, 1 / 3, 0.0], rtol=1e-6)
    np.testing.assert_allclose(s.replay_weights(buf), 0.75 * ps + 0.25 * np.array([1 / 3, 1 / 3, 1 / 3, 0]), rtol=1e-6)


def test_default_temperature_does_not_underflow_on_full_buffer():
    s = LevelSampler(LevelSamplerConfig())  # capacity 1000, beta 0.1: weights down to 1000^-10
    buf = _buffer(s, np.linspace(0.0, 1.0, 1000), np.zeros(1000), clock=0)
    w = np.asarray(s.replay_weights(buf))
    assert np.all(np.isfinite(w)) and abs(w.sum() - 1.0) < 1e-5
    # highest score (last row) has rank 1: P_S = 1 / sum_k k^-10 = 1 / zeta(10)-ish
    zeta = np.sum(1.0 / np.arange(1, 1001) ** 10.0)
    np.testing.assert_allclose(w[-1], 0.5 / zeta + 0.5 / 1000, rtol=1e-5)


def test_sampling_frequencies_follow_weights_and_update_staleness():
    s = LevelSampler(LevelSamplerConfig(capacity=4, temperature=1.0, staleness_coef=0.5))
    buf = _buffer(s, [3.0, 1.0, 2.0], [0, 2, 1], clock=4)
    w = np.asarray(s.replay_weights(buf))
    new_buf, idx, levels, _ = jax.jit(lambda b, k: s.sample(b, k, 20000))(buf, jax.random.PRNGKey(0))
    freq = np.bincount(np.asarray(idx), minlength=4) / 20000
    np.testing.assert_allclose(freq, w, atol=0.015)
    assert freq[3] == 0.0  # never an empty row
    np.testing.assert_array_equal(np.asarray(levels)[:, 0], np.asarray(idx).astype(np.float32))
    assert int(new_buf.episode_count) == 4 + 20000
    assert np.all(np.asarray(new_buf.timestamps)[:3] == 4 + 20000)  # all three were sampled


def test_insert_until_full_then_replace_minimum_only_if_higher():
    s = LevelSampler(LevelSamplerConfig(capacity=3))
    buf = s.init(2)
    for i, sc in enumerate([5.0, 1.0, 3.0]):
        buf, idx = s.insert(buf, jnp.array([i, i], jnp.float32), sc)
        assert int(idx) == i
    assert int(buf.size) == 3
    # lower than the minimum (1.0): refused
    buf2, idx = s.insert(buf, jnp.array([9.0, 9.0]), 0.5)
    assert int(idx) == -1
    np.testing.assert_array_equal(buf2.levels, buf.levels)
    # higher than the minimum: replaces row 1 (score 1.0)
    buf3, idx = s.insert(buf, jnp.array([7.0, 7.0]), 2.0)
    assert int(idx) == 1 and int(buf3.size) == 3
    np.testing.assert_array_equal(buf3.levels[1], [7.0, 7.0])
    np.testing.assert_allclose(buf3.scores, [5.0, 2.0, 3.0])
    np.testing.assert_array_equal(np.asarray(buf3.levels)[[0, 2]], np.asarray(buf.levels)[[0, 2]])


def test_insert_batch_keeps_top_scores():
    s = LevelSampler(LevelSamplerConfig(capacity=5))
    scores = jax.random.normal(jax.random.PRNGKey(3), (40,))
    levels = jnp.stack([jnp.arange(40.0), jnp.zeros(40)], -1)
    buf, idx = jax.jit(s.insert_batch)(s.init(2), levels, scores)
    top5 = np.sort(np.asarray(scores))[-5:]
    np.testing.assert_allclose(np.sort(np.asarray(buf.scores)), top5, rtol=1e-6)
    # each held level is stored with its own score
    held = np.asarray(buf.levels[:, 0]).astype(int)
    np.testing.assert_allclose(np.asarray(buf.scores), np.asarray(scores)[held], rtol=1e-6)
    assert idx.shape == (40,)


def test_duplicate_check_never_holds_duplicates():
    s = LevelSampler(LevelSamplerConfig(capacity=16, duplicate_check=True))
    key_l, key_s = jax.random.split(jax.random.PRNGKey(1))
    levels = jax.random.randint(key_l, (200, 2), 0, 4).astype(jnp.float32)  # 16 distinct values, many repeats
    seeds = jnp.zeros(200, jnp.int32)
    scores = jax.random.uniform(key_s, (200,))
    buf = s.init(2, extra_template=jnp.int32(0))
    buf, _ = jax.jit(s.insert_batch)(buf, levels, scores, seeds)
    held = np.asarray(buf.levels[: int(buf.size)])
    assert len({tuple(r) for r in held}) == len(held)
    # without the check the same stream stores repeats
    s2 = LevelSampler(LevelSamplerConfig(capacity=16))
    buf2, _ = jax.jit(s2.insert_batch)(s2.init(2), levels, scores)
    assert len({tuple(r) for r in np.asarray(buf2.levels)}) < 16


def test_duplicate_refreshes_score_and_extra_distinguishes_levels():
    s = LevelSampler(LevelSamplerConfig(capacity=4, duplicate_check=True))
    buf = s.init(2, extra_template=jnp.int32(0))
    lv = jnp.array([1.0, 2.0])
    buf, i0 = s.insert(buf, lv, 1.0, jnp.int32(7))
    buf, i1 = s.insert(buf, lv, 4.0, jnp.int32(7))  # same vector and seed: refused, score refreshed
    assert int(i0) == int(i1) == 0 and int(buf.size) == 1
    assert float(buf.scores[0]) == 4.0
    buf, i2 = s.insert(buf, lv, 2.0, jnp.int32(8))  # same vector, other terrain seed: a new level
    assert int(i2) == 1 and int(buf.size) == 2 and int(buf.extra[1]) == 8


def test_update_scores_overwrites_and_averages_repeats():
    s = LevelSampler(LevelSamplerConfig(capacity=4))
    buf = _buffer(s, [3.0, 1.0, 2.0], [0, 0, 0], clock=0)
    buf = s.update_scores(buf, jnp.array([1, 1, 2]), jnp.array([10.0, 20.0, -1.0]))
    np.testing.assert_allclose(buf.scores[:3], [3.0, 15.0, -1.0])


def test_replay_decision_respects_min_fill_and_probability():
    cfg = LevelSamplerConfig(capacity=10, replay_prob=0.8, min_fill=0.5)
    s = LevelSampler(cfg)
    keys = jax.random.split(jax.random.PRNGKey(0), 4000)
    decide = jax.jit(jax.vmap(s.sample_replay_decision, in_axes=(None, 0)))
    low = _buffer(s, [1.0] * 4, [0] * 4, clock=0)  # 40 % full < 50 %
    assert not np.any(decide(low, keys))
    high = _buffer(s, [1.0] * 5, [0] * 5, clock=0)
    assert abs(float(np.mean(decide(high, keys))) - 0.8) < 0.03
    prop = LevelSampler(LevelSamplerConfig(capacity=10, replay_prob=0.8, min_fill=0.5, schedule="proportionate"))
    np.testing.assert_allclose(prop.replay_probability(high), 0.5)


def test_vmap_over_seeds_gives_different_draws():
    s = LevelSampler(LevelSamplerConfig(capacity=8, temperature=1.0))
    buf = _buffer(s, np.arange(8.0), np.zeros(8), clock=1)
    bufs = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), buf)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    _, idx, _, _ = jax.jit(jax.vmap(lambda b, k: s.sample(b, k, 16)))(bufs, keys)
    assert idx.shape == (2, 16) and not np.array_equal(idx[0], idx[1])
    _, idx_again, _, _ = jax.jit(jax.vmap(lambda b, k: s.sample(b, k, 16)))(bufs, keys)
    np.testing.assert_array_equal(idx, idx_again)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(capacity=0), "capacity"),
        (dict(replay_prob=1.5), "replay_prob"),
        (dict(temperature=0.0), "temperature"),
        (dict(schedule="linear"), "schedule"),
    ],
)
def test_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LevelSamplerConfig(**kwargs)
