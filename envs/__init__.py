"""Environments for shed_jax, all behind one gymnax-style interface (see ``envs.core``).

    env = envs.make("lander")
    obs, state = env.reset(key, env.default_params)
    obs, state, reward, done, info = env.step(key, state, action, env.default_params)
"""
from __future__ import annotations

import importlib

from envs.core import Box, Discrete, EnvParams, EnvState, Environment, ParamSpace

# name -> (module, factory attribute, keyword arguments). Imported lazily so that, e.g., using the
# lander does not import MuJoCo.
_REGISTRY: dict[str, tuple[str, str, dict]] = {
    "lander": ("envs.lander", "LunarLander", {"continuous": False}),
    "lander-continuous": ("envs.lander", "LunarLander", {"continuous": True}),
    "walker": ("envs.walker", "BipedalWalker", {}),
    "bipedal": ("envs.bipedal", "BipedalWalker", {}),
    "cartpole": ("envs.cartpole", "CartPole", {}),
}


def registered() -> list[str]:
    return sorted(_REGISTRY)


def make(name: str, **kwargs) -> Environment:
    """Build a registered environment by name; keyword arguments override its defaults."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown environment {name!r}; known: {', '.join(registered())}")
    module, attr, defaults = _REGISTRY[name]
    cls = getattr(importlib.import_module(module), attr)
    return cls(**{**defaults, **kwargs})


__all__ = ["Box", "Discrete", "EnvParams", "EnvState", "Environment", "ParamSpace", "make", "registered"]
