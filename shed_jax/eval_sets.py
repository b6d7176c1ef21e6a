"""Evaluation (teacher state) and test level sets, as fixed data (docs/design.md §9.1, §9.2).

A set is a :class:`LevelSet`: named per-level columns (numpy, host data) holding both the
teacher-controllable box parameters and the non-box fields (``enable_wind``, ``max_steps``,
``terrain_seed``, ...). ``to_params(base)`` turns it into an env params pytree with a leading axis
(fields not in the set come from ``base``, e.g. ``env.default_params``); ``vectors(names)`` gives the
``[m, d]`` parameter vectors in a ParamSpace's order.

``to_params`` sets fields with ``base.replace`` rather than ``param_space.from_vector`` on purpose:
``from_vector`` clips into the teacher box, but evaluation sets may lie outside it (the official
lander eval set has g = -9.457 < -9, wind 9.5).

Sets here:
* ``binned_vectors`` / ``paper_eval_set``: the paper's construction for any m: each parameter range is
  cut into bins, one value is drawn uniformly inside each bin, and the per-parameter draws are
  combined by independent random permutations (a Latin hypercube), so every bin of every parameter
  is covered by some level. Deterministic for a seed.
* ``official_lander_eval_set``: the official code's 10 eval landers (hard-coded from the docs/design.md §9.1 table;
  other m via the same generator, numpy legacy RNG seed 92, with 9i/(m-1) in place of i).
* ``lander_test_set``: the official 10 test landers.
* ``walker_ladder_set`` (``walker_eval_set`` seed 92, ``walker_test_set_b`` seed 2024): the docs/design.md §9.1
  difficulty ladder over the DCD FULL ranges, each level with its own fixed terrain seed.
* ``walker_test_set_a``: DCD's named test levels, from ``envs.walker.levels.LEVELS`` (imported lazily).

All generation is host-side numpy (run once, at set-up); the result is fixed data. Each environment
points to its own sets (``env.ued``: ``envs/lander/levels.py``, ``envs/walker/levels.py``).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from envs.walker import constants as C
from envs.walker.params import FULL_HIGH, FULL_LOW
from envs.walker.params import PARAM_NAMES as WALKER_PARAM_NAMES


@dataclasses.dataclass(frozen=True)
class LevelSet:
    """A fixed set of m levels: ``fields`` maps params field names to ``[m]`` numpy arrays."""

    fields: dict
    labels: tuple = ()

    def __post_init__(self):
        fields = {k: np.asarray(v) for k, v in self.fields.items()}
        sizes = {k: v.shape for k, v in fields.items()}
        m = {s[0] if len(s) == 1 else None for s in sizes.values()}
        if len(m) != 1 or None in m:
            raise ValueError(f"LevelSet fields must all be 1-D of one length, got shapes {sizes}")
        if self.labels and len(self.labels) != m.pop():
            raise ValueError(f"LevelSet has {len(self.labels)} labels for {len(self)} levels")
        object.__setattr__(self, "fields", fields)
        object.__setattr__(self, "labels", tuple(self.labels))

    def __len__(self) -> int:
        return len(next(iter(self.fields.values())))

    def vectors(self, names: Sequence[str]) -> np.ndarray:
        """``[m, d]`` float32 vectors of the named parameters (e.g. ``env.param_space.names``)."""
        missing = [n for n in names if n not in self.fields]
        if missing:
            raise KeyError(f"LevelSet has no field(s) {missing}; it has {sorted(self.fields)}")
        return np.stack([self.fields[n].astype(np.float32) for n in names], axis=-1)

    def to_params(self, base):
        """Params pytree with leading axis m: ``base`` broadcast, then this set's fields replaced."""
        m = len(self)
        for name in self.fields:
            if not hasattr(base, name):
                raise ValueError(f"params class {type(base).__name__} has no field {name!r}")
        base = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(jnp.asarray(x), (m,) + jnp.shape(x)), base)
        new = {n: jnp.asarray(v, jnp.asarray(getattr(base, n)).dtype) for n, v in self.fields.items()}
        return base.replace(**new)


def concat_sets(sets: Sequence[LevelSet]) -> LevelSet:
    """The levels of ``sets`` one after another (the first set's fields; every set must have them)."""
    keys = list(sets[0].fields)
    return LevelSet({k: np.concatenate([s.fields[k] for s in sets]) for k in keys})


# --------------------------------------------------------------------------------------------
# The paper's covering construction
# --------------------------------------------------------------------------------------------


def binned_vectors(low, high, m: int, seed: int, num_bins: int | None = None) -> np.ndarray:
    """``[m, d]`` vectors covering every bin of every parameter (the paper's construction).

    Each range [low_j, high_j] is cut into ``num_bins`` (default m, must be <= m) equal bins; level i
    gets bin ``perm_j[i] % num_bins`` of parameter j, with an independent random permutation per
    parameter, and a value uniform inside that bin. Every bin is used at least floor(m/num_bins) times.
    """
    low = np.asarray(low, np.float64)
    high = np.asarray(high, np.float64)
    if low.ndim != 1 or low.shape != high.shape or np.any(low > high):
        raise ValueError(f"binned_vectors needs 1-D low <= high of one shape, got {low} and {high}")
    num_bins = m if num_bins is None else int(num_bins)
    if m < 1 or not 1 <= num_bins <= m:
        raise ValueError(f"binned_vectors needs m >= 1 and 1 <= num_bins <= m, got m={m}, num_bins={num_bins}")
    rng = np.random.default_rng(seed)
    d = low.shape[0]
    bins = np.stack([rng.permutation(m) % num_bins for _ in range(d)], axis=-1)  # [m, d]
    frac = (bins + rng.uniform(size=(m, d))) / num_bins
    return (low + frac * (high - low)).astype(np.float32)


def paper_eval_set(names: Sequence[str], low, high, m: int, seed: int = 92, num_bins=None, **extra) -> LevelSet:
    """A covering eval set over the box [low, high] of ``names``; ``extra`` sets non-box fields
    (scalars broadcast to m, e.g. ``enable_wind=True, max_steps=500`` for the lander)."""
    vec = binned_vectors(low, high, m, seed, num_bins)
    fields = {n: vec[:, j] for j, n in enumerate(names)}
    fields.update({k: np.broadcast_to(np.asarray(v), (m,)).copy() for k, v in extra.items()})
    return LevelSet(fields)


# --------------------------------------------------------------------------------------------
# Lander
# --------------------------------------------------------------------------------------------

# (gravity, enable_wind, wind_power, turbulence_power), max_steps 500 [official code, docs/design.md §9.1]
LANDER_EVAL_10 = (
    (-0.01, False, 0.616, 0.01),
    (-1.70, True, 0.01, 0.01),
    (-1.543, False, 1.919, 1.5),
    (-1.649, True, 0.01, 0.01),
    (-1.008, True, 1.963, 0.268),
    (-0.01, True, 3.24, 0.646),
    (-2.422, True, 3.551, 1.126),
    (-4.526, True, 4.015, 0.985),
    (-6.331, True, 9.541, 0.288),
    (-9.457, False, 8.899, 0.745),
)

# [official code, docs/design.md §9.2]
LANDER_TEST_10 = (
    (-2.0, True, 1.0, 0.2),
    (-2.9, False, 0.6, 0.9),
    (-1.1, True, 2.1, 0.3),
    (-1.9, False, 3.1, 0.4),
    (-4.9, True, 4.2, 0.5),
    (-4.2, False, 1.9, 0.6),
    (-7.9, True, 5.8, 0.7),
    (-8.9, False, 6.1, 0.8),
    (-6.0, True, 7.1, 0.99),
    (-6.3, False, 7.3, 0.22),
)

LANDER_MAX_STEPS = 500


def _lander_set(rows) -> LevelSet:
    g, on, w, t = (np.asarray(c) for c in zip(*rows))
    return LevelSet(
        {
            "gravity": g.astype(np.float32),
            "enable_wind": on.astype(bool),
            "wind_power": w.astype(np.float32),
            "turbulence_power": t.astype(np.float32),
            "max_steps": np.full(len(rows), LANDER_MAX_STEPS, np.int32),
        }
    )


def official_lander_generator(m: int, seed: int = 92) -> list:
    """The official eval-env generator (numpy legacy RNG), rows (g, wind_on, wind, turb).

    For level i: g = clip(N(-0.9 x, 2), -9.99, -0.01); wind_on = choice{T, F};
    wind = clip(N(0.7 x, 2), 0.01, 10); turb = clip(N(0.1 x, 1), 0.01, 1.5), with x = i for m = 10
    and x = 9 i / (m - 1) otherwise (docs/design.md §9.1), drawn in this order.
    """
    if m < 2:
        raise ValueError(f"the official lander generator needs m >= 2, got {m}")
    rng = np.random.RandomState(seed)
    rows = []
    for i in range(m):
        x = i if m == 10 else 9.0 * i / (m - 1)
        g = float(np.clip(rng.normal(-0.9 * x, 2), -9.99, -0.01))
        on = bool(rng.choice([True, False]))
        w = float(np.clip(rng.normal(0.7 * x, 2), 0.01, 10))
        t = float(np.clip(rng.normal(0.1 * x, 1), 0.01, 1.5))
        rows.append((g, on, w, t))
    return rows


def official_lander_eval_set(m: int = 10) -> LevelSet:
    """The official evaluation landers: the hard-coded table for m = 10, else the generator."""
    return _lander_set(LANDER_EVAL_10 if m == 10 else official_lander_generator(m))


def lander_test_set() -> LevelSet:
    """The official 10 test landers (docs/design.md §9.2)."""
    return _lander_set(LANDER_TEST_10)


# Lander box used by the paper construction: the official generator's clip ranges.
LANDER_EVAL_LOW = (-9.99, 0.01, 0.01)
LANDER_EVAL_HIGH = (-0.01, 10.0, 1.5)
LANDER_NAMES = ("gravity", "wind_power", "turbulence_power")


def lander_paper_eval_set(m: int, seed: int = 92) -> LevelSet:
    """The paper's covering construction for the lander (m in {10, 20, 30, 40}); wind on, 500 steps."""
    return paper_eval_set(
        LANDER_NAMES, LANDER_EVAL_LOW, LANDER_EVAL_HIGH, m, seed, enable_wind=True, max_steps=np.int32(LANDER_MAX_STEPS)
    )


# --------------------------------------------------------------------------------------------
# Walker
# --------------------------------------------------------------------------------------------

# DCD FULL ranges of the 8-d level vector and the obstacle thresholds: the walker's own (envs/walker)
WALKER_NAMES = WALKER_PARAM_NAMES
WALKER_LOW = tuple(float(x) for x in FULL_LOW)
WALKER_HIGH = tuple(float(x) for x in FULL_HIGH)
# obstacle present only if its pair's high value reaches the threshold (docs/design.md §13.2)
WALKER_THRESHOLDS = {"pit_gap": C.PIT_THRESHOLD, "stump_height": C.STUMP_THRESHOLD, "stair_height": C.STAIR_THRESHOLD}
DCD_TEST_LEVELS = ("BipedalWalker", "Hardcore", "Stairs", "PitGap", "Stump", "Roughness")


def walker_ladder_set(m: int = 10, seed: int = 92) -> LevelSet:
    """The docs/design.md §9.1 ladder: level i has difficulty f_i = i/(m-1).

    Draws (numpy Generator(seed), per level in this order): the 7 continuous FULL parameters
    clip(N(lo + 0.6 f (hi - lo), 0.1 (hi - lo)), lo, hi); steps clip(round(N(1 + 4.8 f, 1)), 1, 9);
    a terrain seed in [0, 2^31). Then each (low, high) pair is sorted and an obstacle whose high
    value is below its threshold is removed (pair set to 0), as the env would ignore it anyway.
    Levels use a fixed terrain (``fixed_terrain=True``).
    """
    if m < 2:
        raise ValueError(f"walker ladder needs m >= 2, got {m}")
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(WALKER_LOW), np.asarray(WALKER_HIGH)
    vecs, seeds = [], []
    for i in range(m):
        f = i / (m - 1)
        v = np.empty(8)
        for j in range(7):
            v[j] = np.clip(rng.normal(lo[j] + 0.6 * f * (hi[j] - lo[j]), 0.1 * (hi[j] - lo[j])), lo[j], hi[j])
        v[7] = np.clip(np.round(rng.normal(1 + 4.8 * f, 1)), 1, 9)
        seeds.append(int(rng.integers(0, 2**31 - 1)))
        vecs.append(v)
    vec = np.asarray(vecs)
    fields = {n: vec[:, j].astype(np.float32) for j, n in enumerate(WALKER_NAMES)}
    for prefix, thr in WALKER_THRESHOLDS.items():
        a, b = fields[f"{prefix}_low"], fields[f"{prefix}_high"]
        low, high = np.minimum(a, b), np.maximum(a, b)
        present = high >= thr
        fields[f"{prefix}_low"] = np.where(present, low, 0.0).astype(np.float32)
        fields[f"{prefix}_high"] = np.where(present, high, 0.0).astype(np.float32)
    fields["terrain_seed"] = np.asarray(seeds, np.int32)
    fields["fixed_terrain"] = np.ones(m, bool)
    return LevelSet(fields)


def walker_eval_set(m: int = 10) -> LevelSet:
    return walker_ladder_set(m, seed=92)


def walker_test_set_b(m: int = 10) -> LevelSet:
    return walker_ladder_set(m, seed=2024)


def stack_params(levels: Sequence):
    """Stack unbatched params pytrees into one with a leading axis."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *levels)


def walker_test_set_a(names: Sequence[str] = DCD_TEST_LEVELS, terrain_seeds: Sequence[int] | None = None):
    """DCD's named test levels as one stacked WalkerParams (from ``envs.walker.levels.LEVELS``).

    Each level gets a fixed terrain (``fixed_terrain=True``) from a fixed seed list (default
    1000 + i; DCD seeds test terrains from the wall clock, docs/design.md §9.2 fixes them).
    """
    from envs.walker.levels import LEVELS  # lazy: envs.walker.levels imports this module

    missing = [n for n in names if n not in LEVELS]
    if missing:
        raise KeyError(f"unknown walker test level(s) {missing}; known: {sorted(LEVELS)}")
    seeds = [1000 + i for i in range(len(names))] if terrain_seeds is None else list(terrain_seeds)
    if len(seeds) != len(names):
        raise ValueError(f"walker_test_set_a got {len(seeds)} terrain seeds for {len(names)} levels")
    return stack_params([LEVELS[n](terrain_seed=s, fixed_terrain=True) for n, s in zip(names, seeds)])
