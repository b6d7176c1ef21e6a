"""shed_jax: SHED and UED baselines, end to end in JAX."""
from shed_jax.xla_cpu import size_cpu_pool as _size_cpu_pool

# before JAX creates its CPU backend: a pool of one thread per core deadlocks batched LAPACK calls
# on small machines (shed_jax/xla_cpu.py)
_size_cpu_pool()

__version__ = "0.1.0"
