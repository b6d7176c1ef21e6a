"""Parametric bipedal walker on MuJoCo MJX with DCD's 8-parameter level space (see docs/walker.md)."""
from envs.walker.mjx_import import import_mjx

import_mjx()  # before env.py's `from mujoco import mjx`: drops MJX's "Failed to import warp" lines
from envs.walker.env import BipedalWalker, WalkerState  # noqa: E402
from envs.walker.options import WalkerOptions  # noqa: E402
from envs.walker.params import PARAM_NAMES, WalkerParams, make_params  # noqa: E402

__all__ = ["BipedalWalker", "WalkerOptions", "WalkerParams", "WalkerState", "PARAM_NAMES", "make_params"]
