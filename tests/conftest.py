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
#: XLA options of an ``optimized`` test's programs: that level, with LLVM's expensive passes back on
#: (TEST_FLAGS turns them off for the compile-bound rest). The 17 optimized tests took 242 s instead of
#: 287 s with them (two workers, an empty cache, one run each, 2-core Intel Xeon, 2026-12-03), each
#: test as fast or faster, and all passed.
OPTIMIZED_OPTIONS = {"xla_backend_optimization_level": OPTIMIZED_LEVEL, "xla_llvm_disable_expensive_passes": False}


@pytest.fixture(autouse=True)
def _optimized_programs(request, monkeypatch):
    """In an ``optimized`` test, every ``jax.jit`` made during the test compiles with OPTIMIZED_OPTIONS, and
    so do the test's child processes. Not covered: jits made at import or by a module-scoped fixture, and
    eager (un-jitted) operations, so a test compares bits only between programs it jits itself."""
    if request.node.get_closest_marker("optimized") is not None:
        jit, option = jax.jit, OPTIMIZED_OPTIONS

        def optimized_jit(fun, /, *args, compiler_options=None, **kwargs):
            return jit(fun, *args, compiler_options={**option, **(compiler_options or {})}, **kwargs)

        monkeypatch.setattr(jax, "jit", optimized_jit)
        flags = os.environ.get("XLA_FLAGS", "")
        for name, value in OPTIMIZED_OPTIONS.items():
            flags = with_flag(flags, f"--{name}={str(value).lower()}")
        monkeypatch.setenv("XLA_FLAGS", flags)
    yield


@pytest.fixture(autouse=True)
def _exit_at_once_cleared():
    """A test that interrupts a start-up sets shed_jax.driver.EXIT_AT_ONCE; later tests in the worker start clear."""
    yield
    driver = sys.modules.get("shed_jax.driver")
    if driver is not None:
        driver.EXIT_AT_ONCE.clear()
