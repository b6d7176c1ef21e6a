"""Gymnasium's BipedalWalker on the physics2d solver with DCD's level space (see docs/bipedal.md)."""
from envs.bipedal.env import BipedalOptions, BipedalState, BipedalWalker
from envs.bipedal.heuristic import HeuristicState, heuristic, heuristic_init
from envs.walker.levels import LEVELS  # DCD's named levels: the same params as the MJX walker's

__all__ = ["BipedalOptions", "BipedalState", "BipedalWalker", "HeuristicState", "LEVELS", "heuristic", "heuristic_init"]
