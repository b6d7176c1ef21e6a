"""shed_jax.xla_gpu: the GPU's fused multiply-add flag, and the CPU rounding it matches."""
import os

import jax
import numpy as np
import pytest

from shed_jax import xla_cpu, xla_gpu


def test_flag_added_only_with_a_cuda_plugin(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_xnnpack=false")
    assert not xla_gpu.apply_gpu_codegen(plugin=False)
    assert xla_gpu.FLAG not in os.environ["XLA_FLAGS"]
    assert xla_gpu.apply_gpu_codegen(plugin=True)
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_use_xnnpack=false " + xla_gpu.FLAG
    assert not xla_gpu.apply_gpu_codegen(plugin=True)  # once
    assert os.environ["XLA_FLAGS"].count("xla_backend_extra_options") == 1


def test_a_users_backend_options_are_left_alone(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_extra_options=-nvptx-fma-level=0")
    assert not xla_gpu.apply_gpu_codegen(plugin=True)
    assert os.environ["XLA_FLAGS"] == "--xla_backend_extra_options=-nvptx-fma-level=0"
    monkeypatch.delenv("XLA_FLAGS")
    assert xla_gpu.apply_gpu_codegen(plugin=True)
    assert os.environ["XLA_FLAGS"] == xla_gpu.FLAG


def test_plugin_lookup_finds_a_cuda_plugin_in_the_jax_plugins_namespace(tmp_path, monkeypatch):
    import importlib
    import sys

    installed = xla_gpu.cuda_plugin_installed()  # this machine's answer (no plugin on the CI machine)
    (tmp_path / "jax_plugins" / "xla_cuda13").mkdir(parents=True)  # a namespace package, as the wheels lay it out
    (tmp_path / "jax_plugins" / "xla_cuda13" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in [m for m in sys.modules if m == "jax_plugins" or m.startswith("jax_plugins.")]:
        monkeypatch.delitem(sys.modules, name)
    importlib.invalidate_caches()
    assert xla_gpu.cuda_plugin_installed()
    assert not xla_gpu.llvm_knows_fma_level()  # a plugin without libraries names no LLVM option
    lib = tmp_path / "jax_plugins" / "xla_cuda13" / "xla_cuda_plugin.so"
    lib.write_bytes(b"\0-nvptx-fma-level\0")
    assert xla_gpu.llvm_knows_fma_level() == xla_cpu.xla_knows([xla_gpu.LLVM_OPTION])[0]  # and jaxlib's must too
    lib.write_bytes(b"\0-nvptx-sched4reg\0")
    assert not xla_gpu.llvm_knows_fma_level()
    lib.unlink()
    (tmp_path / "jax_plugins" / "xla_cuda13" / "__init__.py").unlink()
    (tmp_path / "jax_plugins" / "xla_cuda13").rmdir()
    (tmp_path / "jax_plugins" / "other_plugin").mkdir()
    (tmp_path / "jax_plugins" / "other_plugin" / "__init__.py").write_text("")
    importlib.invalidate_caches()
    assert xla_gpu.cuda_plugin_installed() == installed  # another plugin is not a CUDA one


def _cpu_has_fma():
    """Whether /proc/cpuinfo names the FMA instruction set; None where there is no /proc/cpuinfo."""
    try:
        with open("/proc/cpuinfo") as f:
            return " fma " in f.read()
    except OSError:
        return None


@pytest.mark.optimized  # LLVM level 1, as runs and the parity harness compile (level 0 does not contract)
def test_cpu_programs_already_round_a_multiply_add_once():
    """The premise of the flag: XLA:CPU fuses a * b + c on a CPU with FMA instructions."""
    rng = np.random.default_rng(0)
    a, b, c = (rng.standard_normal(4096).astype(np.float32) for _ in range(3))
    got = np.asarray(jax.jit(lambda a, b, c: a * b + c)(a, b, c))
    fused = (a.astype(np.float64) * b + c).astype(np.float32)  # exact product, one rounding
    separate = a * b + c  # numpy: two roundings
    assert np.mean(separate == fused) < 0.95  # the two roundings do differ on these inputs
    has_fma = _cpu_has_fma()
    if has_fma is None:  # unknown CPU: one rounding or the other, throughout
        assert np.all(got == fused) or np.all(got == separate)
    else:
        np.testing.assert_array_equal(got, fused if has_fma else separate)
