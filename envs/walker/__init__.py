"""Parametric bipedal walker on MuJoCo MJX with DCD's 8-parameter level space (see docs/walker.md).

The level (``params``, ``levels``, ``constants``, ``terrain``) needs only JAX; ``BipedalWalker``,
``WalkerState`` and ``WalkerOptions`` load the MJX engine on first use, so the bipedal env and the
walker's evaluation sets do not import MuJoCo.
"""
import importlib
from typing import TYPE_CHECKING

from envs.walker.params import PARAM_NAMES, WalkerParams, make_params

if TYPE_CHECKING:  # what __getattr__ loads, for type checkers and editors
    from envs.walker.env import BipedalWalker, WalkerState
    from envs.walker.options import WalkerOptions

_ENGINE = {"BipedalWalker": "envs.walker.env", "WalkerState": "envs.walker.env", "WalkerOptions": "envs.walker.options"}

__all__ = ["BipedalWalker", "WalkerOptions", "WalkerParams", "WalkerState", "PARAM_NAMES", "make_params"]


def __getattr__(name: str):
    if name in _ENGINE:
        return getattr(importlib.import_module(_ENGINE[name]), name)
    raise AttributeError(f"module 'envs.walker' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_ENGINE))
