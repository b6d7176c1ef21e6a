"""Named walker levels (DCD test levels, extras, POET Rose), the EASY/FULL samplers, DCD's edit and
the walker's UED data (``UED``: ACCEL's edit table, evaluation, test and named level sets).

``LEVELS[name](**overrides) -> WalkerParams``; the field values are plain data in ``LEVEL_FIELDS``.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from envs.core import FIXED, UNIFORM, EditTable, UEDSpec
from envs.walker.params import FULL_HIGH, FULL_LOW, PARAM_NAMES, WalkerParams, make_params, param_space
from shed_jax import eval_sets


def _lvl(roughness=0.0, pit=(0.0, 0.0), stump=(0.0, 0.0), stair=(0.0, 0.0), steps=1.0, max_steps=2000, gym_hardcore=False):
    return dict(
        max_steps=max_steps,
        gym_hardcore=gym_hardcore,
        roughness=roughness,
        pit_gap_low=pit[0],
        pit_gap_high=pit[1],
        stump_height_low=stump[0],
        stump_height_high=stump[1],
        stair_height_low=stair[0],
        stair_height_high=stair[1],
        stair_steps=steps,
    )


def _rose(r, stump_lo, stump_hi, pit_hi, pit_lo):
    return _lvl(roughness=r, stump=(stump_lo, stump_hi), pit=(pit_lo, pit_hi))


#: name -> WalkerParams fields (docs/design.md §13.2). Obstacle levels are flat (roughness 0) as in DCD.
LEVEL_FIELDS: dict[str, dict] = {
    "BipedalWalker": _lvl(roughness=1.0, max_steps=1600),
    # Gymnasium's own hardcore generator (gym_hardcore). The generator ignores the 8 values; they
    # are the closest DCD vector (stumps 1-2 steps high, stairs 1 step high, pits 3-4 steps between
    # walls), kept for whatever needs a level as a vector (plots, distances).
    "Hardcore": _lvl(roughness=1.0, pit=(2.0, 3.0), stump=(1.0, 2.0), stair=(1.0, 1.0), steps=5.0, gym_hardcore=True),
    "Stairs": _lvl(stair=(2.0, 2.0), steps=5.0),
    "PitGap": _lvl(pit=(5.0, 5.0)),
    "Stump": _lvl(stump=(2.0, 2.0)),
    "Roughness": _lvl(roughness=5.0),
    "High-Roughness": _lvl(roughness=9.0),
    "High-Stump": _lvl(stump=(5.0, 5.0)),
    "High-Stairs": _lvl(stair=(5.0, 5.0), steps=9.0),
    "Wide-PitGap": _lvl(pit=(10.0, 10.0)),
    "Insane": _lvl(roughness=9.0, pit=(10.0, 10.0), stump=(5.0, 5.0), stair=(5.0, 5.0), steps=9.0),
    "PoetRose-1a": _rose(5.6, 2.4, 2.82, 6.4, 4.48),
    "PoetRose-1b": _rose(5.44, 1.8, 2.82, 6.72, 4.48),
    "PoetRose-2a": _rose(7.2, 1.98, 2.82, 7.2, 5.6),
    "PoetRose-2b": _rose(5.76, 2.16, 2.76, 7.2, 1.6),
    "PoetRose-3a": _rose(5.28, 1.98, 2.76, 7.2, 4.8),
    "PoetRose-3b": _rose(4.8, 2.4, 2.76, 4.48, 4.8),
}

#: DCD's six standard test levels (test set A).
DCD_TEST_LEVELS = eval_sets.DCD_TEST_LEVELS  # DCD's six test levels, in the column order of its table


def _builder(fields):
    return functools.partial(make_params, **fields)


#: name -> builder(**overrides) -> WalkerParams (e.g. ``LEVELS["Stump"](terrain_seed=3, fixed_terrain=True)``).
LEVELS = {name: _builder(f) for name, f in LEVEL_FIELDS.items()}


def stack_levels(names, terrain_seeds=None, fixed_terrain=False) -> WalkerParams:
    """A batch (leading axis) of named levels, e.g. a fixed test set."""
    seeds = range(len(names)) if terrain_seeds is None else terrain_seeds
    ps = [LEVELS[n](terrain_seed=s, fixed_terrain=fixed_terrain) for n, s in zip(names, seeds)]
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *ps)


def _with_seeds(key, params: WalkerParams, shape) -> WalkerParams:
    seeds = jax.random.randint(key, shape, 0, 2**31 - 1, dtype=jnp.int32)
    return params.replace(terrain_seed=seeds, fixed_terrain=jnp.ones(shape, bool))


def sample_easy(key: jax.Array, shape: tuple = ()) -> WalkerParams:
    """ACCEL's base levels: roughness U[0, 0.6], pits (0, 0.8), stumps/stairs (0, 0.4), 1 step.

    Levels get their own terrain seed and ``fixed_terrain=True`` (a level is parameters + seed).
    """
    k_r, k_s = jax.random.split(key)
    vec = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.8, 0.0, 0.4, 0.0, 0.4, 1.0], jnp.float32), shape + (8,))
    vec = vec.at[..., 0].set(jax.random.uniform(k_r, shape, minval=0.0, maxval=0.6))
    return _with_seeds(k_s, param_space().from_vector(vec), shape)


def sample_full(key: jax.Array, shape: tuple = ()) -> WalkerParams:
    """Domain randomisation: every parameter uniform over its FULL range, own terrain seed."""
    k_v, k_s = jax.random.split(key)
    return _with_seeds(k_s, param_space().sample(k_v, shape), shape)


#: DCD edit step per parameter (roughness draws U(0, 0.6) instead).
EDIT_STEP = np.array([0.6, 0.4, 0.4, 0.2, 0.2, 0.2, 0.2, 1.0], np.float32)


def mutate(key: jax.Array, params: WalkerParams, num_edits: int = 3) -> WalkerParams:
    """DCD's edit operator, ``num_edits`` times: a uniform index, a direction in {-1, 0, +1}, a
    step (roughness U(0, 0.6), pits 0.4, stumps/stairs 0.2, steps 1), clip to FULL; then a new
    terrain seed. Works on any batch shape (leading axes of ``params``)."""
    if not isinstance(num_edits, int) or num_edits < 0:
        raise ValueError(f"mutate: num_edits must be a non-negative int, got {num_edits!r}")
    space = param_space()
    vec = space.to_vector(params)
    shape = vec.shape[:-1]
    keys = jax.random.split(key, num_edits + 1)
    for k in keys[:-1]:
        k_i, k_d, k_r = jax.random.split(k, 3)
        idx = jax.random.randint(k_i, shape, 0, len(PARAM_NAMES))
        direction = jax.random.randint(k_d, shape, -1, 2).astype(jnp.float32)
        size = jnp.where(idx == 0, jax.random.uniform(k_r, shape, maxval=0.6), jnp.asarray(EDIT_STEP)[idx])
        vec = vec + jax.nn.one_hot(idx, len(PARAM_NAMES)) * (direction * size)[..., None]
        vec = jnp.clip(vec, FULL_LOW, FULL_HIGH)
    # (ParamSpace.from_vector would broadcast an already-batched base again, so replace directly.)
    out = params.replace(**{n: vec[..., i].astype(jnp.asarray(getattr(params, n)).dtype) for i, n in enumerate(PARAM_NAMES)})
    seeds = jax.random.randint(keys[-1], shape, 0, 2**31 - 1, dtype=jnp.int32)
    return out.replace(terrain_seed=seeds)


# --------------------------------------------------------------------------------------------
# UED data (BipedalWalker.ued)
# --------------------------------------------------------------------------------------------

#: ACCEL's edit table on the 8-vector: the steps of ``mutate`` above and the ``sample_easy`` box [DCD].
EDIT_TABLE = EditTable(
    steps=(0.6, 0.4, 0.4, 0.2, 0.2, 0.2, 0.2, 1.0),
    kinds=(UNIFORM,) + (FIXED,) * 7,
    easy_low=(0.0, 0.0, 0.8, 0.0, 0.4, 0.0, 0.4, 1.0),
    easy_high=(0.6, 0.0, 0.8, 0.0, 0.4, 0.0, 0.4, 1.0),
)


def eval_set(kind: str, m: int):
    """The teacher's evaluation set: the docs/design.md §9.1 difficulty ladder (seed 92), whatever ``kind``."""

    return eval_sets.walker_eval_set(m)


def test_set_a(base):
    """DCD's six test levels (docs/design.md §9.2 set A), fixed terrains."""

    return eval_sets.walker_test_set_a(), list(eval_sets.DCD_TEST_LEVELS)


def test_set_b(base):
    """Ten ladder levels of seed 2024 (docs/design.md §9.2 set B), labelled ladder-i."""

    ls = eval_sets.walker_test_set_b()
    return ls.to_params(base), [f"ladder-{i}" for i in range(len(ls))]


def named_levels(base):
    """Every level of ``LEVELS`` (DCD's six first), fixed terrains of seeds 1000 + i."""

    names = tuple(LEVELS)
    return eval_sets.walker_test_set_a(names), list(names)


#: Θ is the whole FULL box and training levels keep their own 2,000-step limit (docs/design.md §13.2).
UED = UEDSpec(
    edit_table=EDIT_TABLE,
    editor=mutate,
    eval_set=eval_set,
    test_sets=(("walker-test-b", test_set_b), ("walker-test-a", test_set_a)),
    named_levels=named_levels,
    solved_threshold=230.0,  # docs/design.md §9.3 [DCD]
    final_eval="named",  # DCD's named levels with solved rates after every walker run
)
