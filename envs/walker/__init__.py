"""Parametric bipedal walker on MuJoCo MJX with DCD's 8-parameter level space (see docs/walker.md)."""
from envs.walker.env import BipedalWalker, WalkerState
from envs.walker.options import WalkerOptions
from envs.walker.params import PARAM_NAMES, WalkerParams, make_params

__all__ = ["BipedalWalker", "WalkerOptions", "WalkerParams", "WalkerState", "PARAM_NAMES", "make_params"]
