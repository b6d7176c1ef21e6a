"""The walker level: ``WalkerParams`` (DCD's 8-parameter vector + terrain seed + replay flag)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.core import EnvParams, ParamSpace

#: DCD's level vector, in order (docs/design.md §13.2).
PARAM_NAMES = (
    "roughness",
    "pit_gap_low",
    "pit_gap_high",
    "stump_height_low",
    "stump_height_high",
    "stair_height_low",
    "stair_height_high",
    "stair_steps",
)
FULL_LOW = np.array([0, 0, 0, 0, 0, 0, 0, 1], np.float32)
FULL_HIGH = np.array([10, 10, 10, 5, 5, 5, 5, 9], np.float32)


@struct.dataclass
class WalkerParams(EnvParams):
    """One walker level. Heights and gaps are in TERRAIN_STEP units (0.4667 m), as in DCD.

    A level is (the 8 parameters, ``terrain_seed``). With ``fixed_terrain`` every reset rebuilds the
    same terrain from ``terrain_seed`` (exact replay for PLR/ACCEL); otherwise each reset draws a
    new terrain of the same parameters from the reset key. ``gym_hardcore`` switches the generator
    to Gymnasium's BipedalWalkerHardcore rules (``envs.walker.terrain``).
    """

    max_steps: jax.Array = struct.field(default_factory=lambda: jnp.int32(2000))
    roughness: jax.Array = struct.field(default_factory=lambda: jnp.float32(1.0))
    pit_gap_low: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    pit_gap_high: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    stump_height_low: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    stump_height_high: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    stair_height_low: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    stair_height_high: jax.Array = struct.field(default_factory=lambda: jnp.float32(0.0))
    stair_steps: jax.Array = struct.field(default_factory=lambda: jnp.float32(1.0))
    terrain_seed: jax.Array = struct.field(default_factory=lambda: jnp.int32(0))
    fixed_terrain: jax.Array = struct.field(default_factory=lambda: jnp.bool_(False))
    # Gymnasium's own hardcore generator instead of DCD's parametric one (the "Hardcore" test
    # level): the 8 parameters are then ignored. Not teacher-controlled (not in the vector).
    gym_hardcore: jax.Array = struct.field(default_factory=lambda: jnp.bool_(False))


def make_params(**fields) -> WalkerParams:
    """``WalkerParams`` with the given fields cast to their dtypes (unknown names raise)."""
    base = WalkerParams()
    unknown = set(fields) - set(base.__dataclass_fields__)
    if unknown:
        raise ValueError(f"WalkerParams has no field(s) {sorted(unknown)}")
    cast = {k: jnp.asarray(v, jnp.asarray(getattr(base, k)).dtype) for k, v in fields.items()}
    return base.replace(**cast)


def param_space(base: WalkerParams | None = None) -> ParamSpace:
    """The FULL box over the 8 DCD parameters, in DCD's order."""
    return ParamSpace(PARAM_NAMES, FULL_LOW, FULL_HIGH, WalkerParams() if base is None else base)


def param_bounds() -> dict:
    """Physically valid ranges, checked eagerly by ``Environment.check_params``."""
    b = {n: (float(lo), float(hi), True, True) for n, lo, hi in zip(PARAM_NAMES, FULL_LOW, FULL_HIGH)}
    b["max_steps"] = (1, 2**31 - 1, True, True)
    return b
