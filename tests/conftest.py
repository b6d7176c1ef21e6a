"""Shared test set-up: CPU only, float32, a persistent compilation cache under .cache/."""
import os
import pathlib
import sys

import pytest

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
from shed_jax.xla_cpu import TEST_FLAGS, apply_cpu_guard  # noqa: E402

# XLA:CPU hang guard (see shed_jax/xla_cpu.py); two xdist workers on two cores lose nothing. TEST_FLAGS:
# LLVM at optimisation level 1 without its expensive passes, and XLA:CPU's older fusion emitters, for the
# compiles that dominate the suite's time (measurements in shed_jax/xla_cpu.py).
apply_cpu_guard(extra=TEST_FLAGS)

import jax  # noqa: E402

_cache = pathlib.Path(__file__).resolve().parents[1] / ".cache" / "jax"
_cache.mkdir(parents=True, exist_ok=True)
jax.config.update("jax_compilation_cache_dir", str(_cache))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


@pytest.fixture(autouse=True)
def _exit_at_once_cleared():
    """A test that interrupts a start-up sets shed_jax.driver.EXIT_AT_ONCE; later tests in the worker start clear."""
    yield
    driver = sys.modules.get("shed_jax.driver")
    if driver is not None:
        driver.EXIT_AT_ONCE.clear()
