"""What both walkers (MJX ``envs.walker``, physics2d ``envs.bipedal``) share of the env interface:
the level (``WalkerParams``, DCD's box), the 24-float observation, the 4 motor actions and the
level's terrain. Only the physics differs between them."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs.core import Box
from envs.walker import params as P
from envs.walker import terrain as T


class WalkerInterface:
    """Mixin for an ``envs.core.Environment`` whose ``options`` has ``max_boxes``."""

    @property
    def default_params(self) -> P.WalkerParams:
        return P.WalkerParams()

    @property
    def param_space(self):
        return P.param_space(self.default_params)

    @property
    def param_bounds(self) -> dict:
        return P.param_bounds()

    def observation_space(self, params=None):
        return Box(-np.inf, np.inf, (24,), jnp.float32)

    def action_space(self, params=None):
        return Box(-1.0, 1.0, (4,), jnp.float32)

    def terrain(self, key: jax.Array, params: P.WalkerParams) -> T.Terrain:
        """The level's terrain: from ``terrain_seed`` if ``fixed_terrain``, else from ``key``."""
        o = self.options
        return T.level_terrain(key, params, o.max_boxes, o.terrain_unroll, o.terrain_kernel)
