"""ACCEL's level editor and EASY base-level sampler, on parameter vectors.

A level is a float vector in ``env.param_space`` order, so one editor serves every environment; only
a per-environment table of edit steps (and the EASY box) differs. One edit (docs/design.md §8.5, §13.2):

    i ~ U{0..d-1},  dir ~ U{-1, 0, +1},  v_i <- clip(v_i + dir * step_i, low_i, high_i)

where ``step_i`` is a constant (``fixed``) or drawn from U(0, step_i) (``uniform``, the walker's
roughness). ``num_edits`` edits are applied in sequence (3 [DCD]), so at most ``num_edits``
coordinates change. Environments whose level also holds a terrain seed draw a fresh seed per child
(``shed_jax.levels.new_seeds``), as DCD does.

Each environment's table is its ``env.ued.edit_table`` [docs/design.md §8.5, §13.1 / §13.2]:

* lander (gravity, wind_power, turbulence_power; ``envs/lander/levels.py``): steps 0.36 / 0.48 / 0.06
  (4 % of the teacher box Θ), clipped to Θ; EASY g ~ U[-7, -3], wind ~ U[0.01, 1], turb ~ U[0.01, 0.1]
  [our choice].
* walker (roughness, pit lo/hi, stump lo/hi, stair lo/hi, stair steps; ``envs/walker/levels.py``):
  steps U(0, 0.6), 0.4, 0.4, 0.2, 0.2, 0.2, 0.2, 1, clipped to FULL; EASY roughness ~ U[0, 0.6], pits
  0/0.8, stumps 0/0.4, stairs 0/0.4, steps 1 [DCD].

Environments without a table get :func:`generic_table`. An environment may also have its own editor
on params (``env.ued.editor``; the walker's is DCD's ``envs.walker.levels.mutate``), which
:meth:`Mutator.for_env` uses on the whole box (through a vector <-> params round trip), so there is
one walker editor in the project; the table is the same operator on vectors, used for every other
environment and for a sub-box Θ.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from envs.core import FIXED, UNIFORM, EditTable
from shed_jax.levels import ued


def generic_table(low, high, step_fraction: float = 0.04) -> EditTable:
    """Fallback for environments without a table: steps of ``step_fraction`` of the box width and
    EASY = the whole box. Used for the small test environments (e.g. cartpole)."""
    low = np.asarray(low, np.float64)
    high = np.asarray(high, np.float64)
    d = low.shape[0]
    return EditTable(
        steps=tuple(float(x) for x in step_fraction * (high - low)),
        kinds=(FIXED,) * d,
        easy_low=tuple(float(x) for x in low),
        easy_high=tuple(float(x) for x in high),
    )


def table_for(env, space=None) -> EditTable:
    """The edit table of ``env`` (``env.ued.edit_table``), validated against its parameter space."""
    space = env.param_space if space is None else space
    table = ued(env).edit_table
    if table is None:
        return generic_table(space.low, space.high)
    if table.dim != space.dim:
        raise ValueError(f"edit table for {env.name!r} has {table.dim} parameters but its param_space has {space.dim} ({space.names})")
    return table


@dataclasses.dataclass(frozen=True)
class Mutator:
    """ACCEL's edit operator and EASY sampler over ``[d]`` vectors in the box [low, high]."""

    table: EditTable
    low: np.ndarray
    high: np.ndarray
    num_edits: int = 3
    # optional environment editor on params: (key, params, num_edits) -> params, with ``space`` to
    # convert vectors; used for the walker (envs.walker.levels.mutate)
    external: Callable | None = None
    space: object = None

    def __post_init__(self):
        if self.external is not None and self.space is None:
            raise ValueError("Mutator: an external editor needs the ParamSpace to convert vectors")
        low = np.asarray(self.low, np.float32)
        high = np.asarray(self.high, np.float32)
        if low.shape != (self.table.dim,) or high.shape != low.shape:
            raise ValueError(f"Mutator bounds must have shape ({self.table.dim},), got {low.shape} and {high.shape}")
        if not isinstance(self.num_edits, int) or self.num_edits < 0:
            raise ValueError(f"Mutator.num_edits must be a non-negative int, got {self.num_edits!r}")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)

    @classmethod
    def for_env(cls, env, space=None, num_edits: int = 3) -> "Mutator":
        """Editor clipping to ``space`` (the teacher box Θ; default ``env.param_space``)."""
        space = env.param_space if space is None else space
        table = table_for(env, space)
        external = _env_editor(env, space)
        return cls(table, space.low, space.high, num_edits, external, space if external else None)

    def edit(self, key: jax.Array, vec: jax.Array) -> jax.Array:
        """One edit of one ``[d]`` vector (see module docstring)."""
        k_i, k_dir, k_mag = jax.random.split(key, 3)
        d = self.table.dim
        i = jax.random.randint(k_i, (), 0, d)
        direction = jax.random.randint(k_dir, (), -1, 2).astype(jnp.float32)
        steps = jnp.asarray(self.table.steps, jnp.float32)
        uniform = jnp.asarray([k == UNIFORM for k in self.table.kinds])
        mag = jnp.where(uniform[i], jax.random.uniform(k_mag) * steps[i], steps[i])
        low, high = jnp.asarray(self.low), jnp.asarray(self.high)
        new_i = jnp.clip(vec[i] + direction * mag, low[i], high[i])
        return vec.at[i].set(new_i)

    def mutate(self, key: jax.Array, vec: jax.Array) -> jax.Array:
        """``num_edits`` sequential edits of one ``[d]`` vector (a ``lax.scan``)."""
        vec = jnp.asarray(vec, jnp.float32)
        if self.external is not None:
            out = self.external(key, self.space.from_vector(vec), self.num_edits)
            return jnp.clip(self.space.to_vector(out), self.low, self.high)
        keys = jax.random.split(key, self.num_edits)
        out, _ = jax.lax.scan(lambda v, k: (self.edit(k, v), None), vec, keys)
        return out

    def mutate_batch(self, key: jax.Array, vecs: jax.Array) -> jax.Array:
        """Edit each row of ``[n, d]`` with its own key."""
        return jax.vmap(self.mutate)(jax.random.split(key, vecs.shape[0]), vecs)

    def sample_easy(self, key: jax.Array, num: int) -> jax.Array:
        """``num`` EASY base levels ``[num, d]`` (uniform in the EASY box, clipped to the bounds)."""
        lo = jnp.asarray(self.table.easy_low, jnp.float32)
        hi = jnp.asarray(self.table.easy_high, jnp.float32)
        u = jax.random.uniform(key, (num, self.table.dim), jnp.float32)
        return jnp.clip(lo + u * (hi - lo), self.low, self.high)


def _env_editor(env, space):
    """The environment's own editor on params (``env.ued.editor``), if it has one, its levels carry a
    terrain seed and the box is its whole ``param_space``."""
    fn = ued(env).editor
    if fn is None or not hasattr(space.base, "terrain_seed"):
        return None
    full = env.param_space
    if not (np.array_equal(space.low, full.low) and np.array_equal(space.high, full.high)):
        return None  # a sub-box Θ needs clipping to Θ at every edit: use the vector editor
    return fn
