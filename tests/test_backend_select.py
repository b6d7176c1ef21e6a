"""shed_jax/_backend_select.py: which JAX build `make setup` installs, with a fake `nvidia-smi` first on
PATH (the only thing on PATH, so a real one on a GPU machine cannot leak in)."""
import os
import pathlib
import shutil
import subprocess
import sys

import pytest

from shed_jax import _backend_select as select

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "shed_jax" / "_backend_select.py"

# The header of `nvidia-smi` as drivers 570 (CUDA 12.8) and 580 (CUDA 13.0) print it (table cut short).
_HEADER = """Mon Nov 24 12:00:00 2026
+-----------------------------------------------------------------------------------------+
| NVIDIA-SMI {driver}             Driver Version: {driver}     CUDA Version: {cuda}     |
|-----------------------------------------+------------------------+----------------------+
| GPU  Name                 Persistence-M | Bus-Id          Disp.A | Volatile Uncorr. ECC |
|=========================================+========================+======================|
|   0  NVIDIA H100 80GB HBM3          On  |   00000000:19:00.0 Off |                    0 |
+-----------------------------------------+------------------------+----------------------+
"""
_FAILED = ("NVIDIA-SMI has failed because it couldn't communicate with the NVIDIA driver. "
           "Make sure that the latest NVIDIA driver is installed and running.")


def _fake_bin(tmp_path, stdout=None, exit_code=0):
    """A folder holding an `nvidia-smi` that prints `stdout` and exits `exit_code` (None: no nvidia-smi)."""
    folder = tmp_path / "bin"
    folder.mkdir(parents=True)
    if stdout is not None:
        exe = folder / "nvidia-smi"
        quoted = stdout.replace("'", "'\"'\"'")
        exe.write_text(f"#!/bin/sh\nprintf '%s' '{quoted}'\nexit {exit_code}\n")  # printf: a builtin, no PATH needed
        exe.chmod(0o755)
    return folder


def _gpu(tmp_path, driver, cuda):
    return _fake_bin(tmp_path, _HEADER.format(driver=driver, cuda=cuda))


def _script(bin_dir, *args, env_value=None):
    env = {"PATH": str(bin_dir)}
    if env_value is not None:
        env["JAX_BACKEND"] = env_value
    return subprocess.run([sys.executable, str(SCRIPT), *args], env=env, capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("driver, cuda, want", [
    ("570.124.06", "12.8", "cuda12"),
    ("525.60.13", "12.0", "cuda12"),
    ("580.65.06", "13.0", "cuda13"),
    ("590.44.01", "13.1", "cuda13"),
])
def test_auto_follows_the_cuda_version_nvidia_smi_reports(tmp_path, monkeypatch, driver, cuda, want):
    monkeypatch.setenv("PATH", str(_gpu(tmp_path, driver, cuda)))
    assert select.probe_gpu() == (tuple(int(p) for p in cuda.split(".")), driver,
                                  f"nvidia-smi: driver {driver}, CUDA {cuda}")
    assert select.choose(None) == (want, f"nvidia-smi: driver {driver}, CUDA {cuda}")
    assert select.choose("auto")[0] == select.choose("")[0] == want


def test_no_usable_gpu_gives_cpu_and_says_why(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(_fake_bin(tmp_path)))  # no nvidia-smi at all
    assert select.choose(None) == ("cpu", "no nvidia-smi on PATH")

    failing = _fake_bin(tmp_path / "f", _FAILED + "\n", exit_code=9)
    monkeypatch.setenv("PATH", str(failing))
    assert select.choose(None) == ("cpu", f"nvidia-smi failed (exit 9: {_FAILED})")

    old = _gpu(tmp_path / "o", "470.82.01", "11.4")
    monkeypatch.setenv("PATH", str(old))
    assert select.choose(None) == ("cpu", "nvidia-smi: driver 470.82.01, CUDA 11.4; "
                                          "JAX's CUDA builds need CUDA >= 12 (driver >= 525)")

    no_version = _fake_bin(tmp_path / "n", "Driver Version: 580.65.06   CUDA Version: N/A\n")
    monkeypatch.setenv("PATH", str(no_version))
    assert select.choose(None) == ("cpu", "nvidia-smi names no CUDA version")


def test_override_wins_without_asking_nvidia_smi():
    def probe():
        raise AssertionError("an explicit choice must not run nvidia-smi")

    for value in ("cpu", "cuda12", "cuda13"):
        assert select.choose(value, probe=probe) == (value, f"set by JAX_BACKEND={value}")
    for bad in ("gpu", "cuda11", "CPU", "cuda"):
        with pytest.raises(select.BadValue) as err:
            select.choose(bad, probe=probe)
        assert str(err.value) == f"JAX_BACKEND={bad!r} is not allowed; use one of: auto, cpu, cuda12, cuda13"


def test_script_lines_and_exit_codes(tmp_path):
    """The script the Makefile runs: one explanatory line, `--name` for the bare choice, exit 2 on a bad value."""
    gpu = _gpu(tmp_path, "570.124.06", "12.8")
    proc = _script(gpu)
    assert (proc.returncode, proc.stderr) == (0, "")
    assert proc.stdout == ("[shed_jax] JAX build: cuda12 (nvidia-smi: driver 570.124.06, CUDA 12.8; "
                           "choose with make setup JAX_BACKEND=cpu|cuda12|cuda13)\n")
    assert _script(gpu, "--name").stdout == "cuda12\n"
    assert _script(gpu, "--name", "cpu").stdout == "cpu\n"
    assert _script(gpu, "--name", env_value="cuda13").stdout == "cuda13\n"  # the variable, when no argument
    assert _script(gpu, "--name", "auto", env_value="cpu").stdout == "cuda12\n"  # the argument wins
    assert _script(_fake_bin(tmp_path / "none"), "--name").stdout == "cpu\n"

    line = "JAX_BACKEND='cuda11' is not allowed; use one of: auto, cpu, cuda12, cuda13\n"
    bad = _script(gpu, "cuda11")
    assert (bad.returncode, bad.stdout, bad.stderr) == (2, "", line)
    bad = _script(gpu, "--name", "cuda11")
    assert (bad.returncode, bad.stdout, bad.stderr) == (2, line, "")


def test_stale_plugins_are_those_of_the_other_builds():
    every = {"jax-cuda12-plugin", "jax-cuda12-pjrt", "jax-cuda13-plugin", "jax-cuda13-pjrt", "jax", "jaxlib"}
    assert select.stale_plugins("cpu", every) == sorted(every - {"jax", "jaxlib"})
    assert select.stale_plugins("cuda12", every) == ["jax-cuda13-pjrt", "jax-cuda13-plugin"]
    assert select.stale_plugins("cuda13", every) == ["jax-cuda12-pjrt", "jax-cuda12-plugin"]
    assert select.stale_plugins("cpu", {"jax", "jaxlib"}) == []


_MAKE = shutil.which("make")


@pytest.mark.skipif(_MAKE is None, reason="no make")
def test_makefile_installs_the_chosen_build(tmp_path):
    """`make -n -B setup` (prints the recipe, runs nothing) installs the extra the fake GPU asks for, under a
    stamp named after the build; a bad value stops make with the script's line."""
    def make(bin_dir, *args):
        env = {"PATH": str(bin_dir), "HOME": str(tmp_path)}
        return subprocess.run([_MAKE, "-n", "-B", f"PYTHON={sys.executable}", *args], cwd=ROOT, env=env,
                              capture_output=True, text=True, timeout=60)

    recipe = make(_gpu(tmp_path, "580.65.06", "13.0"), "setup")
    assert recipe.returncode == 0, recipe.stderr
    assert 'pip install -q -e ".[test,cuda13]"' in recipe.stdout
    assert "--stale cuda13" in recipe.stdout and "touch .venv/.installed-cuda13" in recipe.stdout

    cpu = make(_fake_bin(tmp_path / "none"), "setup")
    assert 'pip install -q -e ".[test]"' in cpu.stdout and "touch .venv/.installed-cpu" in cpu.stdout
    forced = make(_gpu(tmp_path / "g", "570.124.06", "12.8"), "setup", "JAX_BACKEND=cpu")
    assert "touch .venv/.installed-cpu" in forced.stdout

    bad = make(_fake_bin(tmp_path / "b"), "setup", "JAX_BACKEND=rocm")
    assert bad.returncode != 0 and bad.stdout == ""
    assert bad.stderr.strip().endswith(
        "*** JAX_BACKEND='rocm' is not allowed; use one of: auto, cpu, cuda12, cuda13.  Stop.")
    assert len(bad.stderr.strip().splitlines()) == 1
