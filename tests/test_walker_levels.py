"""Walker named levels, EASY/FULL samplers and DCD's edit operator (pure JAX, no physics)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.walker import levels as LV
from envs.walker.params import FULL_HIGH, FULL_LOW, PARAM_NAMES, WalkerParams, param_space


def vec(p):
    return np.asarray(param_space().to_vector(p))


def test_named_levels_are_data():
    assert set(LV.DCD_TEST_LEVELS) <= set(LV.LEVELS)
    for name in ["BipedalWalker", "Hardcore", "Stairs", "PitGap", "Stump", "Roughness", "High-Roughness", "High-Stump",
                 "High-Stairs", "Wide-PitGap", "Insane", "PoetRose-1a", "PoetRose-3b"]:
        p = LV.LEVELS[name]()
        assert isinstance(p, WalkerParams)
        v = vec(p)
        assert np.all(v >= FULL_LOW) and np.all(v <= FULL_HIGH), name
    np.testing.assert_allclose(vec(LV.LEVELS["Stairs"]()), [0, 0, 0, 0, 0, 2, 2, 5])
    np.testing.assert_allclose(vec(LV.LEVELS["Insane"]()), [9, 10, 10, 5, 5, 5, 5, 9])
    np.testing.assert_allclose(vec(LV.LEVELS["PoetRose-2b"]()), [5.76, 1.6, 7.2, 2.16, 2.76, 0, 0, 1], rtol=1e-6)
    assert int(LV.LEVELS["BipedalWalker"]().max_steps) == 1600 and int(LV.LEVELS["Stump"]().max_steps) == 2000
    p = LV.LEVELS["Stump"](terrain_seed=7, fixed_terrain=True)
    assert int(p.terrain_seed) == 7 and bool(p.fixed_terrain)
    batch = LV.stack_levels(LV.DCD_TEST_LEVELS)
    assert batch.roughness.shape == (6,) and list(np.asarray(batch.terrain_seed)) == list(range(6))


def test_samplers_ranges_and_shapes():
    e = LV.sample_easy(jax.random.PRNGKey(0), (500,))
    v = vec(e)
    assert v.shape == (500, 8)
    assert v[:, 0].min() >= 0 and v[:, 0].max() <= 0.6 and v[:, 0].std() > 0.1
    np.testing.assert_allclose(v[:, 1:], np.broadcast_to([0, 0.8, 0, 0.4, 0, 0.4, 1], (500, 7)), atol=1e-6)
    assert bool(jnp.all(e.fixed_terrain)) and len(np.unique(np.asarray(e.terrain_seed))) > 490
    f = vec(LV.sample_full(jax.random.PRNGKey(1), (2000,)))
    assert np.all(f >= FULL_LOW) and np.all(f <= FULL_HIGH)
    assert np.all(np.abs(f.mean(0) - (FULL_LOW + FULL_HIGH) / 2) < 0.06 * (FULL_HIGH - FULL_LOW))
    assert LV.sample_full(jax.random.PRNGKey(2), (3, 4)).roughness.shape == (3, 4)


def test_mutate_edit_steps_and_seed():
    base = LV.sample_easy(jax.random.PRNGKey(3), (4000,))
    one = jax.jit(lambda k, p: LV.mutate(k, p, num_edits=1))(jax.random.PRNGKey(4), base)
    d = vec(one) - vec(base)
    changed = np.abs(d) > 1e-6
    assert changed.sum(1).max() == 1  # one edit touches at most one parameter
    idx = np.argmax(changed, 1)[changed.any(1)]
    counts = np.bincount(idx, minlength=8)
    assert counts.min() > 0.5 * counts.mean()  # index uniform (clipping at 0 hides some -1 edits)
    steps = {1: 0.4, 2: 0.4, 3: 0.2, 4: 0.2, 5: 0.2, 6: 0.2, 7: 1.0}
    for j, s in steps.items():
        dj = d[changed[:, j], j]
        # |delta| is the step, or less where the FULL clip bites.
        assert np.all(np.abs(dj) <= s + 1e-5) and np.isclose(np.abs(dj), s, atol=1e-5).mean() > 0.3, PARAM_NAMES[j]
    dr = d[changed[:, 0], 0]
    assert np.all(np.abs(dr) <= 0.6 + 1e-6) and (dr > 0).any() and (dr < 0).any()
    # Directions in {-1, 0, +1}: about a third of edits change nothing.
    assert 0.2 < 1 - changed.any(1).mean() < 0.5
    # New terrain seed, other fields kept.
    assert np.mean(np.asarray(one.terrain_seed) != np.asarray(base.terrain_seed)) > 0.99
    np.testing.assert_array_equal(np.asarray(one.fixed_terrain), np.asarray(base.fixed_terrain))
    # Clipped into FULL after many edits.
    many = LV.mutate(jax.random.PRNGKey(5), LV.LEVELS["Insane"](), num_edits=50)
    v = vec(many)
    assert np.all(v >= FULL_LOW) and np.all(v <= FULL_HIGH)
    with pytest.raises(ValueError, match="num_edits"):
        LV.mutate(jax.random.PRNGKey(0), base, num_edits=-1)
