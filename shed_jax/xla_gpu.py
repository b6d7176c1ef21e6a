"""Fused multiply-adds in XLA's GPU code, as XLA:CPU already emits them.

XLA compiles GPU kernels (its own fusions and the Triton kernels of ``envs.physics2d.fused``) through
LLVM's NVPTX backend, which by default keeps every ``a * b + c`` as a rounded multiply and a rounded
add (``mul.rn`` / ``add.rn`` in the PTX, which ptxas may not fuse). XLA:CPU fuses them on any CPU with
FMA instructions at its default optimisation level (not at level 0, which the test suite uses for
most tests): ``jit(lambda a, b, c: a * b + c)`` equals the single-rounding result for every element
on the project's CI machines. So the CPU path, on which every parity figure of the lander and the
2-D walker was measured, already rounds this way, and the GPU did not.

``apply_gpu_codegen`` passes LLVM's ``-nvptx-fma-level=1`` (contract a multiply and an add into one
``fma.rn``) through ``--xla_backend_extra_options`` when a CUDA plugin is installed and both it and
jaxlib know that LLVM option (LLVM ends the process on an option it does not know; both know it in
jaxlib 0.10.2 and 0.11.2 with the CUDA 13 plugin). Measured on one H100 (2026-12-07,
docs/log/benchmarks.md "FMA in the GPU kernels"): the 2-D walker's step at 200 walkers without the
auto-reset 1.020 -> 0.867 ms, its velocity loop's kernel 0.494 -> 0.387 ms (SASS: 2,276 -> 1,725
instructions a pass). Each ``a * b + c`` then rounds once, not twice: results differ from an
uncontracted GPU program in the last bits, and from XLA:CPU's where the two compilers pair
different products and sums.

Set ``XLA_FLAGS=--xla_backend_extra_options=-nvptx-fma-level=0`` to compile without it; a setting of
``xla_backend_extra_options`` already in ``XLA_FLAGS`` is left as it is. JAX's compilation-cache keys
include ``XLA_FLAGS``, so programs compiled with and without it are cached apart, and a compile
for a GPU on a CPU host must see the same flag (it does where the plugin is installed, as it must be
for that compile).
"""
from __future__ import annotations

import importlib.util
import os
import pathlib
import pkgutil

OPTION = "--xla_backend_extra_options"
LLVM_OPTION = "nvptx-fma-level"
FLAG = f"{OPTION}=-{LLVM_OPTION}=1"


def _cuda_plugin_dirs() -> list[pathlib.Path]:
    spec = importlib.util.find_spec("jax_plugins")
    if spec is None or not spec.submodule_search_locations:
        return []
    return [pathlib.Path(m.module_finder.path) / m.name
            for m in pkgutil.iter_modules(spec.submodule_search_locations) if m.name.startswith("xla_cuda")]


def cuda_plugin_installed() -> bool:
    """Whether a JAX CUDA plugin (``jax_plugins.xla_cuda*``) is importable; nothing is imported."""
    return bool(_cuda_plugin_dirs())


def llvm_knows_fma_level() -> bool:
    """Whether jaxlib's and the CUDA plugin's libraries both name LLVM's ``nvptx-fma-level`` option."""
    from shed_jax.xla_cpu import names_in_libraries, xla_knows

    libs = sorted(p for d in _cuda_plugin_dirs() for p in d.glob("*.so*"))
    return bool(libs) and xla_knows([LLVM_OPTION])[0] and names_in_libraries(libs, [LLVM_OPTION])[0]


def apply_gpu_codegen(plugin: bool | None = None) -> bool:
    """Add ``FLAG`` to ``XLA_FLAGS`` when a CUDA plugin is installed whose LLVM and jaxlib's know the
    option (``plugin``: whether so, else looked up, about 0.5 s) and the user has not set
    ``xla_backend_extra_options``; returns whether it was added. Call it before the first JAX
    computation, as ``shed_jax.xla_cpu.apply_cpu_guard``."""
    flags = os.environ.get("XLA_FLAGS", "")
    if any(f.split("=")[0] == OPTION for f in flags.split()):
        return False
    plugin = (cuda_plugin_installed() and llvm_knows_fma_level()) if plugin is None else plugin
    if not plugin:
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    return True
