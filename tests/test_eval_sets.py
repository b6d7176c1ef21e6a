"""Evaluation / test level sets: covering construction, official tables, walker ladder, params building."""
import jax.numpy as jnp
import numpy as np
import pytest

from envs.lander.env import LanderParams, make_params as lander_params
from envs.walker.params import WalkerParams
from shed_jax import eval_sets as es


def _LanderLike(**kw):
    return lander_params(**kw)


@pytest.mark.parametrize("m", [10, 20, 30, 40])
def test_binned_vectors_cover_every_bin(m):
    low, high = np.array([-9.99, 0.01, 0.01]), np.array([-0.01, 10.0, 1.5])
    v = es.binned_vectors(low, high, m, seed=92)
    assert v.shape == (m, 3) and np.all(v >= low - 1e-5) and np.all(v <= high + 1e-5)
    bins = np.floor((v - low) / (high - low) * m).clip(0, m - 1).astype(int)
    for j in range(3):  # every bin of every parameter holds exactly one level (Latin hypercube)
        np.testing.assert_array_equal(np.sort(bins[:, j]), np.arange(m))
    np.testing.assert_array_equal(v, es.binned_vectors(low, high, m, seed=92))  # deterministic
    assert not np.allclose(v, es.binned_vectors(low, high, m, seed=93))
    # fewer bins than levels: every bin still covered
    v4 = es.binned_vectors(low, high, m, seed=1, num_bins=4)
    b4 = np.floor((v4 - low) / (high - low) * 4).clip(0, 3).astype(int)
    for j in range(3):
        assert set(b4[:, j]) == {0, 1, 2, 3}
    with pytest.raises(ValueError, match="num_bins"):
        es.binned_vectors(low, high, m, seed=0, num_bins=m + 1)


def test_official_lander_generator_reproduces_the_table():
    rows = es.official_lander_generator(10)
    for got, want in zip(rows, es.LANDER_EVAL_10):
        assert got[1] == want[1]
        np.testing.assert_allclose([got[0], got[2], got[3]], [want[0], want[2], want[3]], atol=6e-4)
    # other m: x = 9i/(m-1) ladder, clipped ranges
    rows20 = np.array([(g, w, t) for g, _, w, t in es.official_lander_generator(20)])
    assert rows20.shape == (20, 3)
    assert np.all(rows20[:, 0] <= -0.01) and np.all(rows20[:, 0] >= -9.99) and np.all(rows20[:, 2] <= 1.5)


def test_lander_sets_to_params():
    ev = es.official_lander_eval_set()
    params = ev.to_params(_LanderLike())
    assert params.gravity.shape == (10,) and params.gravity.dtype == jnp.float32
    assert params.enable_wind.dtype == jnp.bool_ and params.max_steps.dtype == jnp.int32
    np.testing.assert_allclose(params.gravity, [r[0] for r in es.LANDER_EVAL_10], rtol=1e-6)
    np.testing.assert_array_equal(params.enable_wind, [r[1] for r in es.LANDER_EVAL_10])
    np.testing.assert_array_equal(params.max_steps, np.full(10, 500))
    test = es.lander_test_set().to_params(_LanderLike())
    np.testing.assert_allclose(test.wind_power, [1.0, 0.6, 2.1, 3.1, 4.2, 1.9, 5.8, 6.1, 7.1, 7.3], rtol=1e-6)
    np.testing.assert_allclose(test.turbulence_power[8], 0.99, rtol=1e-6)
    # values outside the teacher box are kept (no clipping): g = -9.457 < -9
    assert float(params.gravity[9]) == pytest.approx(-9.457)
    vec = ev.vectors(("gravity", "wind_power", "turbulence_power"))
    assert vec.shape == (10, 3) and vec[2, 1] == pytest.approx(1.919)
    with pytest.raises(KeyError, match="roughness"):
        ev.vectors(("roughness",))

    with pytest.raises(ValueError, match="gravity"):
        ev.to_params(WalkerParams())


@pytest.mark.parametrize("m", [10, 30])
def test_lander_paper_set_covers_bins(m):
    ps = es.lander_paper_eval_set(m)
    params = ps.to_params(_LanderLike())
    assert bool(jnp.all(params.enable_wind)) and params.gravity.shape == (m,)
    g = np.asarray(params.gravity)
    bins = np.floor((g - -9.99) / 9.98 * m).clip(0, m - 1).astype(int)
    np.testing.assert_array_equal(np.sort(bins), np.arange(m))


def test_walker_ladder_sets():
    ev, tb = es.walker_eval_set(), es.walker_test_set_b()
    for s in (ev, tb):
        v = s.vectors(es.WALKER_NAMES)
        assert v.shape == (10, 8)
        assert np.all(v >= np.array(es.WALKER_LOW)) and np.all(v <= np.array(es.WALKER_HIGH))
        for p in ("pit_gap", "stump_height", "stair_height"):
            lo, hi = s.fields[f"{p}_low"], s.fields[f"{p}_high"]
            assert np.all(lo <= hi)
            # below-threshold obstacles are removed entirely
            assert np.all((hi >= es.WALKER_THRESHOLDS[p]) | ((hi == 0) & (lo == 0)))
        steps = s.fields["stair_steps"]
        np.testing.assert_array_equal(steps, np.round(steps))
        assert np.all(s.fields["fixed_terrain"]) and len(set(s.fields["terrain_seed"].tolist())) == 10
    wp = ev.to_params(WalkerParams())
    assert wp.terrain_seed.dtype == jnp.int32 and wp.fixed_terrain.dtype == jnp.bool_ and wp.roughness.shape == (10,)
    np.testing.assert_array_equal(wp.max_steps, np.full(10, 2000))  # not in the set: from the base level
    # a difficulty ladder: the hardest level is rougher than the easiest
    assert ev.fields["roughness"][-1] > ev.fields["roughness"][0]
    assert np.mean(ev.fields["stair_steps"][5:]) > np.mean(ev.fields["stair_steps"][:5])
    # deterministic, and seeds 92 / 2024 differ
    np.testing.assert_array_equal(es.walker_eval_set().vectors(es.WALKER_NAMES), ev.vectors(es.WALKER_NAMES))
    assert not np.allclose(ev.vectors(es.WALKER_NAMES), tb.vectors(es.WALKER_NAMES))


def test_stack_params_and_levelset_validation():
    stacked = es.stack_params([_LanderLike(gravity=-1.0), _LanderLike(gravity=-2.0)])
    np.testing.assert_array_equal(stacked.gravity, [-1.0, -2.0])
    assert stacked.max_steps.shape == (2,) and isinstance(stacked, LanderParams)
    with pytest.raises(ValueError, match="1-D of one length"):
        es.LevelSet({"gravity": np.zeros(3), "wind_power": np.zeros(4)})


def test_walker_test_set_a_named_levels():
    a = es.walker_test_set_a()
    assert isinstance(a, WalkerParams) and a.roughness.shape == (6,)
    # DCD order: BipedalWalker, Hardcore, Stairs, PitGap, Stump, Roughness (docs/design.md §9.2)
    np.testing.assert_allclose(np.asarray(a.roughness)[[0, 5]], [1.0, 5.0])
    np.testing.assert_allclose(a.stair_height_high[2], 2.0)
    np.testing.assert_allclose(a.pit_gap_low[3], 5.0)
    np.testing.assert_allclose(a.stump_height_high[4], 2.0)
    assert bool(np.all(a.fixed_terrain)) and len(set(np.asarray(a.terrain_seed).tolist())) == 6
    with pytest.raises(KeyError, match="Moon"):
        es.walker_test_set_a(("Moon",))
