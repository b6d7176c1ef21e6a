"""Parametric Lunar Lander (Gymnasium LunarLander-v3 rules) in pure JAX; see docs/lander.md."""
from envs.lander.env import LanderParams, LanderState, LunarLander, make_params
from envs.lander.heuristic import heuristic

__all__ = ["LanderParams", "LanderState", "LunarLander", "heuristic", "make_params"]
