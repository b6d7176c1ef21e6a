"""Fused multiply-adds in XLA's GPU code, as XLA:CPU already emits them.

XLA compiles GPU kernels (its own fusions and the Triton kernels of ``envs.physics2d.fused``) through
LLVM's NVPTX backend, which by default keeps every ``a * b + c`` as a rounded multiply and a rounded
add (``mul.rn`` / ``add.rn`` in the PTX, which ptxas may not fuse). XLA:CPU fuses them on any CPU with
FMA instructions: ``jit(lambda a, b, c: a * b + c)`` equals the single-rounding result for every
element on the project's CI machines. So the CPU path, on which every parity figure of the lander
and the 2-D walker was measured, already rounds this way, and the GPU did not.

``apply_gpu_codegen`` passes LLVM's ``-nvptx-fma-level=1`` (contract a multiply and an add into one
``fma.rn``) through ``--xla_backend_extra_options`` when a CUDA plugin is installed. Measured on one
H100 (2026-12-07, docs/log/benchmarks.md "FMA in the GPU kernels"): the 2-D walker's step at 200
walkers without the auto-reset 1.020 -> 0.867 ms, its velocity loop's kernel 0.494 -> 0.387 ms
(SASS: 2,276 -> 1,725 instructions a pass). Each ``a * b + c`` then rounds once, not twice: results
differ from an uncontracted GPU program in the last bits, and from XLA:CPU's where the two compilers
pair different products and sums.

Set ``XLA_FLAGS=--xla_backend_extra_options=-nvptx-fma-level=0`` to compile without it; a setting of
``xla_backend_extra_options`` already in ``XLA_FLAGS`` is left as it is. It is part of XLA's compile
options, so programs compiled with and without it have different cache keys.
"""
from __future__ import annotations

import importlib.util
import os
import pkgutil

OPTION = "--xla_backend_extra_options"
FLAG = f"{OPTION}=-nvptx-fma-level=1"


def cuda_plugin_installed() -> bool:
    """Whether a JAX CUDA plugin (``jax_plugins.xla_cuda*``) is importable; nothing is imported."""
    spec = importlib.util.find_spec("jax_plugins")
    if spec is None or not spec.submodule_search_locations:
        return False
    return any(m.name.startswith("xla_cuda") for m in pkgutil.iter_modules(spec.submodule_search_locations))


def apply_gpu_codegen(plugin: bool | None = None) -> bool:
    """Add ``FLAG`` to ``XLA_FLAGS`` when a CUDA plugin is installed (``plugin``: whether one is, else
    looked up) and the user has not set ``xla_backend_extra_options``; returns whether it was added.
    Call it before the first JAX computation, as ``shed_jax.xla_cpu.apply_cpu_guard``."""
    plugin = cuda_plugin_installed() if plugin is None else plugin
    flags = os.environ.get("XLA_FLAGS", "")
    if not plugin or any(f.split("=")[0] == OPTION for f in flags.split()):
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    return True
