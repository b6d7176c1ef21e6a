"""ACCEL edits: bounds, number of changed parameters, step sizes, EASY boxes, determinism."""
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import cartpole
from envs.core import ParamSpace
from envs.lander import levels as lander_levels
from envs.walker import levels as walker_levels
from shed_jax.levels import new_seeds
from shed_jax.methods.mutations import EditTable, Mutator, table_for

LANDER_TABLE, WALKER_TABLE = lander_levels.EDIT_TABLE, walker_levels.EDIT_TABLE
UED = {"lander": lander_levels.UED, "walker": walker_levels.UED, "cartpole": cartpole.UED}

LANDER_THETA = ParamSpace(("gravity", "wind_power", "turbulence_power"), [-9.0, 0.01, 0.01], [-0.01, 12.0, 1.5], None)
WALKER_FULL = ParamSpace(
    ("roughness", "pit_lo", "pit_hi", "stump_lo", "stump_hi", "stair_lo", "stair_hi", "stair_steps"),
    [0, 0, 0, 0, 0, 0, 0, 1],
    [10, 10, 10, 5, 5, 5, 5, 9],
    None,
)


def _env(name, space):
    """A stand-in with the real environment's UED data (edit table, editor) over ``space``."""
    return types.SimpleNamespace(name=name, param_space=space, ued=UED[name])


@pytest.mark.parametrize("name, space", [("lander", LANDER_THETA), ("walker", WALKER_FULL)])
def test_edits_stay_in_bounds_and_change_at_most_num_edits(name, space):
    m = Mutator.for_env(_env(name, space), num_edits=3)
    key_p, key_m = jax.random.split(jax.random.PRNGKey(0))
    parents = space.sample_vector(key_p, (2000,))
    parents = parents.at[:500].set(jnp.asarray(space.low)).at[500:1000].set(jnp.asarray(space.high))  # at the edges
    children = jax.jit(m.mutate_batch)(key_m, parents)
    c, p = np.asarray(children), np.asarray(parents)
    assert np.all(c >= space.low - 1e-6) and np.all(c <= space.high + 1e-6)
    changed = np.sum(~np.isclose(c, p, atol=0, rtol=0), axis=1)
    assert changed.max() <= 3
    assert np.mean(changed > 0) > 0.5  # most children differ (P(no change) = (1/3)^3 + clipping)


@pytest.mark.parametrize("name, space, table", [("lander", LANDER_THETA, LANDER_TABLE), ("walker", WALKER_FULL, WALKER_TABLE)])
def test_single_edit_moves_one_coordinate_by_its_step(name, space, table):
    m = Mutator.for_env(_env(name, space), num_edits=1)
    mid = jnp.asarray((space.low + space.high) / 2)  # far from the bounds: no clipping
    parents = jnp.broadcast_to(mid, (3000, space.dim))
    c = np.asarray(jax.jit(m.mutate_batch)(jax.random.PRNGKey(1), parents))
    delta = c - np.asarray(mid)
    assert np.all(np.sum(delta != 0, axis=1) <= 1)
    for i, (step, kind) in enumerate(zip(table.steps, table.kinds)):
        moved = np.abs(delta[:, i][delta[:, i] != 0])
        assert moved.size > 0, f"parameter {i} never edited"
        if kind == "fixed":
            np.testing.assert_allclose(moved, step, rtol=1e-4)
        else:
            assert moved.max() <= step + 1e-6 and moved.min() < 0.5 * step
    # direction: +1 and -1 equally likely, 0 about a third of the time
    frac_zero = np.mean(np.all(delta == 0, axis=1))
    assert abs(frac_zero - 1 / 3) < 0.04
    assert abs(np.mean(delta.sum(1) > 0) - 1 / 3) < 0.04


def test_easy_levels():
    m = Mutator.for_env(_env("lander", LANDER_THETA))
    e = np.asarray(m.sample_easy(jax.random.PRNGKey(2), 1000))
    assert e.shape == (1000, 3)
    assert np.all((e[:, 0] >= -7) & (e[:, 0] <= -3))
    assert np.all((e[:, 1] >= 0.01) & (e[:, 1] <= 1.0))
    assert np.all((e[:, 2] >= 0.01) & (e[:, 2] <= 0.1))
    w = np.asarray(Mutator.for_env(_env("walker", WALKER_FULL)).sample_easy(jax.random.PRNGKey(2), 100))
    assert np.all((w[:, 0] >= 0) & (w[:, 0] <= 0.6)) and np.ptp(w[:, 0]) > 0.3
    np.testing.assert_allclose(w[:, 1:], np.broadcast_to([0, 0.8, 0, 0.4, 0, 0.4, 1], (100, 7)))


def test_mutation_is_deterministic_per_key_and_differs_across_keys():
    m = Mutator.for_env(_env("lander", LANDER_THETA))
    parents = m.sample_easy(jax.random.PRNGKey(0), 64)
    a = m.mutate_batch(jax.random.PRNGKey(5), parents)
    b = m.mutate_batch(jax.random.PRNGKey(5), parents)
    c = m.mutate_batch(jax.random.PRNGKey(6), parents)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    s = new_seeds(jax.random.PRNGKey(0), 64)
    assert s.dtype == jnp.int32 and len(np.unique(np.asarray(s))) == 64 and np.all(np.asarray(s) >= 0)


def test_generic_table_and_validation():
    space = ParamSpace(("a", "b"), [0.0, -1.0], [1.0, 1.0], None)
    t = table_for(_env("cartpole", space))
    np.testing.assert_allclose(t.steps, [0.04, 0.08], rtol=1e-6)
    with pytest.raises(ValueError, match="param_space has 2"):
        table_for(_env("lander", space))
    with pytest.raises(ValueError, match="kinds"):
        EditTable(steps=(1.0,), kinds=("gauss",), easy_low=(0.0,), easy_high=(1.0,))
    with pytest.raises(ValueError, match="num_edits"):
        Mutator(LANDER_TABLE, LANDER_THETA.low, LANDER_THETA.high, num_edits=-1)


def test_walker_uses_the_walker_package_editor():
    from envs.walker.params import param_space

    space = param_space()
    m = Mutator.for_env(_env("walker", space), num_edits=3)
    assert m.external is not None  # envs.walker.levels.mutate
    parents = space.sample_vector(jax.random.PRNGKey(0), (500,))
    children = np.asarray(jax.jit(m.mutate_batch)(jax.random.PRNGKey(1), parents))
    assert np.all(children >= space.low) and np.all(children <= space.high)
    changed = np.sum(children != np.asarray(parents), axis=1)
    assert changed.max() <= 3 and np.mean(changed > 0) > 0.5
    # a sub-box Θ must clip at every edit, so it falls back to the vector editor
    sub = space.with_bounds(high=space.high / 2)
    assert Mutator.for_env(_env("walker", space), sub).external is None
