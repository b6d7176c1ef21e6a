"""Levels, shared by every UED method: the teacher box, level vectors <-> env params, terrain
seeds, per-slot returns, and an environment's own level sets.

A level is a float vector in ``env.param_space`` order plus a terrain seed. What a method needs to
know about an environment (its box Θ, training time limit, evaluation/test/named sets) is the
environment's :class:`envs.core.UEDSpec` (``env.ued``); nothing here tests an environment's name.

* :func:`teacher_space` -- the box Θ levels live in, with the training-level settings in its base.
* :class:`LevelCodec` -- ``([n, d] vectors, [n] seeds)`` -> an env params pytree. Environments whose
  params have a ``terrain_seed`` field (the walker) get the seed and ``fixed_terrain=True``, so a
  level is exactly reproducible (DCD level semantics, docs/walker.md "Level"); others ignore the seed.
* :func:`new_seeds` -- fresh terrain seeds for new or edited levels.
* :func:`slot_returns` -- per-slot mean and max return of the episodes a rollout completed.
* :func:`evaluation_set`, :func:`test_set`, :func:`named_levels` -- the environment's level sets as params.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from envs.core import ParamSpace, UEDSpec

_NO_UED = UEDSpec()


def ued(env) -> UEDSpec:
    """The environment's UED data (an empty :class:`UEDSpec` for objects that define none)."""
    return getattr(env, "ued", None) or _NO_UED


def teacher_space(env, low=None, high=None) -> ParamSpace:
    """The box Θ the teacher samples from, its base params carrying the training-level settings.

    Explicit ``low``/``high`` (validated to lie inside ``env.param_space``) win; otherwise the
    environment's ``ued.theta_low``/``theta_high`` (the lander: the docs/design.md §5 box), else its
    whole ``param_space`` (walker: FULL). The base gets ``ued.training_params`` (the lander: wind on,
    600 steps), so every generated level has them.
    """
    spec, space = ued(env), env.param_space
    base = space.base
    if base is not None:
        base = spec.training_params(base)
    if low is None and high is None and spec.theta_low is not None:
        if len(spec.theta_low) != space.dim:
            raise ValueError(f"{env.name}: the teacher box Θ has {len(spec.theta_low)} parameters, "
                             f"its param_space {space.dim} ({', '.join(space.names)})")
        low, high = spec.theta_low, spec.theta_high
    return space.with_bounds(low, high, base)


def new_seeds(key: jax.Array, num: int) -> jax.Array:
    """Fresh terrain seeds for ``num`` edited or newly generated levels (int32, non-negative)."""
    return jax.random.randint(key, (num,), 0, jnp.iinfo(jnp.int32).max, dtype=jnp.int32)


@dataclasses.dataclass(frozen=True)
class LevelCodec:
    """Level vectors (+ terrain seeds) -> env params pytrees, for one box ``space``."""

    space: ParamSpace

    @property
    def dim(self) -> int:
        return self.space.dim

    @property
    def has_seed(self) -> bool:
        return self.space.base is not None and hasattr(self.space.base, "terrain_seed")

    def to_params(self, vecs: jax.Array, seeds: jax.Array | None = None):
        """``[n, d]`` vectors (clipped into the box) and ``[n]`` seeds -> params with leading n."""
        params = self.space.from_vector(vecs)
        if self.has_seed and seeds is not None:
            n = vecs.shape[0]
            params = params.replace(
                terrain_seed=jnp.asarray(seeds, jnp.asarray(self.space.base.terrain_seed).dtype),
                fixed_terrain=jnp.ones((n,), jnp.asarray(self.space.base.fixed_terrain).dtype),
            )
        return params

    def sample_uniform(self, key: jax.Array, n: int):
        """``n`` levels uniform over the box, each with a fresh seed -> (vecs [n, d], seeds [n])."""
        k_v, k_s = jax.random.split(key)
        return self.space.sample_vector(k_v, (n,)), new_seeds(k_s, n)


def slot_returns(traj, final_episode_return: jax.Array):
    """Per-slot (mean, max) undiscounted return of the episodes completed in a rollout [num_envs].

    Slots that completed no episode use ``final_episode_return`` (the unfinished episode's return
    at the end of the rollout) for both.
    """
    done = traj.dones.astype(bool)
    count = done.sum(axis=0)
    mean = jnp.where(done, traj.episode_returns, 0.0).sum(axis=0) / jnp.maximum(count, 1)
    best = jnp.where(done, traj.episode_returns, -jnp.inf).max(axis=0)
    none = count == 0
    return jnp.where(none, final_episode_return, mean), jnp.where(none, final_episode_return, best)


# --------------------------------------------------------------------------------------------
# the environment's level sets (host side, at set-up)
# --------------------------------------------------------------------------------------------


def evaluation_set(env, kind: str, m: int):
    """The environment's m teacher-evaluation levels -> (params with leading m, time limit or None).

    ``kind`` picks the construction where the environment has several (the lander: ``"official"``
    or ``"paper"``). The time limit is the set's own ``max_steps`` (None if the set leaves it to the
    environment's default).
    """
    build = ued(env).eval_set
    if build is None:
        raise ValueError(f"{env.name} has no evaluation set of its own (env.ued.eval_set); pass evaluation levels explicitly")
    ls = build(kind, m)
    cap = int(np.max(ls.fields["max_steps"])) if "max_steps" in ls.fields else None
    return ls.to_params(env.default_params), cap


def test_set(env, name: str):
    """The environment's test set ``name`` -> (params with a leading level axis, labels)."""
    return ued(env).test_set(name)(env.default_params)


def named_levels(env):
    """The environment's named levels -> (params with a leading level axis, labels), or None."""
    build = ued(env).named_levels
    return None if build is None else build(env.default_params)
