"""shed_jax: SHED and UED baselines, end to end in JAX."""

__version__ = "0.1.0"
