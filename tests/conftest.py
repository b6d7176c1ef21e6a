"""Shared test set-up: CPU only, float32, a persistent compilation cache under .cache/."""
import os
import pathlib
import sys

import pytest

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
from shed_jax.xla_cpu import TEST_FLAGS, apply_cpu_guard, with_flag  # noqa: E402

# XLA:CPU hang guard (see shed_jax/xla_cpu.py); two xdist workers on two cores lose nothing. TEST_FLAGS:
# LLVM at optimisation level 0 without its expensive passes (level 1 in tests marked `optimized`, below),
# and XLA:CPU's older fusion emitters, for the compiles that dominate the suite's time (measurements in
# shed_jax/xla_cpu.py).
apply_cpu_guard(extra=TEST_FLAGS)

import jax  # noqa: E402

_cache = pathlib.Path(__file__).resolve().parents[1] / ".cache" / "jax"
_cache.mkdir(parents=True, exist_ok=True)
jax.config.update("jax_compilation_cache_dir", str(_cache))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


#: LLVM's optimisation level for tests marked ``optimized``; the rest of the suite compiles at TEST_FLAGS'
#: level 0. Two kinds of test need it: programs that run for tens of seconds (level 0 runs them up to 4x
#: slower), and bitwise comparisons of two different programs (at level 0 two programs can round the
#: same computation differently; at level 1 and above, as in real runs, they agree). Measurements in
#: shed_jax/xla_cpu.py.
OPTIMIZED_LEVEL = 1


@pytest.fixture(autouse=True)
def _optimized_programs(request, monkeypatch):
    """In an ``optimized`` test, every ``jax.jit`` made during the test compiles at OPTIMIZED_LEVEL, and so
    do the test's child processes. Not covered: jits made at import or by a module-scoped fixture, and
    eager (un-jitted) operations, so a test compares bits only between programs it jits itself."""
    if request.node.get_closest_marker("optimized") is not None:
        jit, option = jax.jit, {"xla_backend_optimization_level": OPTIMIZED_LEVEL}

        def optimized_jit(fun, /, *args, compiler_options=None, **kwargs):
            return jit(fun, *args, compiler_options={**option, **(compiler_options or {})}, **kwargs)

        monkeypatch.setattr(jax, "jit", optimized_jit)
        monkeypatch.setenv("XLA_FLAGS", with_flag(os.environ.get("XLA_FLAGS", ""),
                                                  f"--xla_backend_optimization_level={OPTIMIZED_LEVEL}"))
    yield


@pytest.fixture(autouse=True)
def _exit_at_once_cleared():
    """A test that interrupts a start-up sets shed_jax.driver.EXIT_AT_ONCE; later tests in the worker start clear."""
    yield
    driver = sys.modules.get("shed_jax.driver")
    if driver is not None:
        driver.EXIT_AT_ONCE.clear()
