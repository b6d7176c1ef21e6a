"""Each environment's own UED data (``env.ued``) equals what the methods, presets and CLIs used to
look up by the environment's name (the literals below are the constants of dr.py, mutations.py,
shed.py, cli/eval.py and cli/run.py before they moved), and nothing reads the name any more."""
import types

import jax
import numpy as np
import pytest

import envs
from envs.core import ParamSpace
from shed_jax import eval_sets as es
from shed_jax import levels as L
from shed_jax.methods.mutations import table_for

# the former constants (shed_jax/methods/dr.py, mutations.py; shed_jax/cli/eval.py)
OLD_LANDER_THETA = ((-9.0, 0.01, 0.01), (-0.01, 12.0, 1.5))
OLD_LANDER_TRAIN_MAX_STEPS = 600
OLD_CODE_DR = ((-10.0, 1.0, -11.99, -0.01), (15.0, 1.0, 0.01, 19.99), (1.5, 0.5, 0.01, 1.99))
OLD_LANDER_TABLE = ((0.36, 0.48, 0.06), ("fixed",) * 3, (-7.0, 0.01, 0.01), (-3.0, 1.0, 0.1))
OLD_WALKER_TABLE = (
    (0.6, 0.4, 0.4, 0.2, 0.2, 0.2, 0.2, 1.0),
    ("uniform",) + ("fixed",) * 7,
    (0.0, 0.0, 0.8, 0.0, 0.4, 0.0, 0.4, 1.0),
    (0.6, 0.0, 0.8, 0.0, 0.4, 0.0, 0.4, 1.0),
)
OLD_WALKER_FULL = ((0, 0, 0, 0, 0, 0, 0, 1), (10, 10, 10, 5, 5, 5, 5, 9))
OLD_SOLVED = {"lander": 200.0, "lander-continuous": 200.0, "walker": 230.0, "cartpole": 475.0}
OLD_DCD_TEST_LEVELS = ["BipedalWalker", "Hardcore", "Stairs", "PitGap", "Stump", "Roughness"]


def _same(a, b):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert type(a) is type(b) and len(la) == len(lb)
    for x, y in zip(la, lb):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _table(t):
    return (t.steps, t.kinds, t.easy_low, t.easy_high)


@pytest.mark.parametrize("name", ["lander", "lander-continuous"])
def test_lander_ued_equals_the_former_constants(name):
    env = envs.make(name)
    space = L.teacher_space(env)
    np.testing.assert_array_equal(space.low, np.float32(OLD_LANDER_THETA[0]))
    np.testing.assert_array_equal(space.high, np.float32(OLD_LANDER_THETA[1]))
    # training levels: 600 steps, wind on; the rest of the default level unchanged
    base = env.default_params
    _same(space.base, base.replace(max_steps=np.int32(OLD_LANDER_TRAIN_MAX_STEPS), enable_wind=np.bool_(True)))
    assert env.ued.train_max_steps == OLD_LANDER_TRAIN_MAX_STEPS
    assert env.ued.code_dr == OLD_CODE_DR and env.ued.editor is None
    assert _table(table_for(env, space)) == OLD_LANDER_TABLE
    assert env.ued.solved_threshold == OLD_SOLVED[name]

    # SHED's evaluation sets (shed.py): official (default) and paper, 500-step cap from the set
    for kind, m, old in (("official", 10, es.official_lander_eval_set(10)), ("official", 20, es.official_lander_eval_set(20)),
                         ("paper", 10, es.lander_paper_eval_set(10)), ("paper", 30, es.lander_paper_eval_set(30))):
        params, cap = L.evaluation_set(env, kind, m)
        _same(params, old.to_params(base))
        assert cap == 500
    # the run's test set (cli/run.py test_levels) and its labels (cli/eval.py)
    params, labels = L.test_set(env, "lander-test")
    _same(params, es.lander_test_set().to_params(base))
    assert labels == [f"test-{i}" for i in range(10)]
    with pytest.raises(ValueError, match="unknown test set 'walker-test-b'; known: lander-test"):
        L.test_set(env, "walker-test-b")
    # named levels (cli/eval.py): the 10 official evaluation landers then the 10 test landers
    params, labels = L.named_levels(env)
    ev, te = es.official_lander_eval_set(), es.lander_test_set()
    old = es.LevelSet({k: np.concatenate([ev.fields[k], te.fields[k]]) for k in ev.fields})
    _same(params, old.to_params(base))
    assert labels == [f"eval-{i}" for i in range(10)] + [f"test-{i}" for i in range(10)]


def test_walker_ued_equals_the_former_constants():
    from envs.walker.levels import LEVELS, mutate

    env = envs.make("walker")
    base = env.default_params
    space = L.teacher_space(env)  # Θ = FULL, training levels keep the default 2,000-step limit
    np.testing.assert_array_equal(space.low, np.float32(OLD_WALKER_FULL[0]))
    np.testing.assert_array_equal(space.high, np.float32(OLD_WALKER_FULL[1]))
    _same(space.base, base)
    assert int(space.base.max_steps) == 2000 and env.ued.train_max_steps is None
    assert env.ued.code_dr is None and env.ued.editor is mutate
    assert _table(table_for(env, space)) == OLD_WALKER_TABLE
    assert env.ued.solved_threshold == OLD_SOLVED["walker"]

    for kind in ("official", "paper"):  # the walker has one evaluation set, the seed-92 ladder
        params, cap = L.evaluation_set(env, kind, 10)
        _same(params, es.walker_ladder_set(10, seed=92).to_params(base))
        assert cap is None
    params, cap = L.evaluation_set(env, "official", 20)
    _same(params, es.walker_ladder_set(20, seed=92).to_params(base))
    params, labels = L.test_set(env, "walker-test-b")
    _same(params, es.walker_ladder_set(10, seed=2024).to_params(base))
    assert labels == [f"ladder-{i}" for i in range(10)]
    params, labels = L.test_set(env, "walker-test-a")
    _same(params, es.walker_test_set_a(OLD_DCD_TEST_LEVELS, [1000 + i for i in range(6)]))
    assert labels == OLD_DCD_TEST_LEVELS
    params, labels = L.named_levels(env)
    _same(params, es.walker_test_set_a(tuple(LEVELS)))
    assert labels == list(LEVELS) and labels[:6] == OLD_DCD_TEST_LEVELS


def test_cartpole_ued_and_a_name_alone_means_nothing():
    cart = envs.make("cartpole")
    space = L.teacher_space(cart)  # no box of its own: the whole param_space, default level as base
    np.testing.assert_array_equal(space.low, cart.param_space.low)
    _same(space.base, cart.default_params)
    assert cart.ued.solved_threshold == OLD_SOLVED["cartpole"]
    params, labels = L.named_levels(cart)
    from envs.cartpole import LEVELS

    assert labels == list(LEVELS)
    _same(params, es.stack_params([build() for build in LEVELS.values()]))
    with pytest.raises(ValueError, match="no evaluation set"):
        L.evaluation_set(cart, "official", 10)

    # an object called "lander" without the lander's UED data gets nothing of the lander's
    lander = envs.make("lander")
    impostor = types.SimpleNamespace(name="lander", param_space=lander.param_space, default_params=lander.default_params)
    space = L.teacher_space(impostor)
    np.testing.assert_array_equal(space.low, lander.param_space.low)
    _same(space.base, lander.default_params)
    assert L.named_levels(impostor) is None and L.ued(impostor).solved_threshold is None
    assert table_for(impostor).steps == pytest.approx(0.04 * (lander.param_space.high - lander.param_space.low))
    with pytest.raises(ValueError, match="no evaluation set"):
        L.evaluation_set(impostor, "official", 10)


def test_theta_must_match_the_param_space():
    from envs.lander import levels as lander_levels

    space = ParamSpace(("a", "b"), [0.0, 0.0], [1.0, 1.0], None)
    env = types.SimpleNamespace(name="two", param_space=space, ued=lander_levels.UED)
    with pytest.raises(ValueError, match="Θ has 3 parameters, its param_space 2"):
        L.teacher_space(env)
    with pytest.raises(ValueError, match="both theta_low and theta_high"):
        type(lander_levels.UED)(theta_low=(0.0,))
