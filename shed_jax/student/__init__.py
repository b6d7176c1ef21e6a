"""The PPO student (see docs/architecture.md, "Student")."""
from shed_jax.student.config import PPOConfig, PPOHyperparams
from shed_jax.student.ppo import Policy, PPOStudent, StudentState, Trajectory, make_student

__all__ = ["PPOConfig", "PPOHyperparams", "Policy", "PPOStudent", "StudentState", "Trajectory", "make_student"]
