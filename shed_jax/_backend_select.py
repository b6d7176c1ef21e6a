"""Which JAX build ``make setup`` installs: ``cpu``, ``cuda12`` or ``cuda13``.

Standard library only and free of package imports: the Makefile runs it as a plain script
(``python3 shed_jax/_backend_select.py [VALUE]``) before anything is installed, and
``shed_jax.runtime`` imports it to explain a CPU-only JAX on a machine with a GPU.

``auto`` (the default) asks ``nvidia-smi``. Its header names the newest CUDA version the driver
supports: 13.x or newer picks ``cuda13`` (jax's CUDA 13 wheels need driver >= 580, which reports
13.0), 12.x picks ``cuda12`` (driver >= 525); anything else (no ``nvidia-smi``, a failing one,
an older driver) picks ``cpu``. The installed extra is ``jax[cuda12]`` or ``jax[cuda13]``, which
both exist for every jax release that pyproject.toml admits and that this project's index holds
(0.10.0-0.10.2; checked 2026-11-24 with ``pip download --no-deps``).

Script use:
  _backend_select.py [VALUE]           print one line: the choice and why (exit 2 on a bad VALUE)
  _backend_select.py --name [VALUE]    print only the choice, or the one-line error (exit 2)
  _backend_select.py --stale BACKEND   print the installed jax CUDA plugin packages that BACKEND
                                       does not use (run with the venv's python, before pip)
VALUE defaults to the environment variable ``JAX_BACKEND``, then to ``auto``.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

VARIABLE = "JAX_BACKEND"
BACKENDS = ("cpu", "cuda12", "cuda13")
ALLOWED = ("auto",) + BACKENDS
# pip distributions that jax[cudaNN] adds; a backend switch uninstalls the other ones, since jax
# loads any CUDA plugin it finds.
PLUGINS = {cuda: (f"jax-{cuda}-plugin", f"jax-{cuda}-pjrt") for cuda in ("cuda12", "cuda13")}


class BadValue(ValueError):
    pass


def probe_gpu(timeout: float = 20.0):
    """``(cuda, driver, why)`` from ``nvidia-smi``: ``cuda`` is ``(major, minor)`` or ``None``.

    ``why`` says in a few words what was found; ``driver`` is the driver version string or ``None``.
    """
    exe = shutil.which("nvidia-smi")
    if exe is None:
        return None, None, "no nvidia-smi on PATH"
    try:
        proc = subprocess.run([exe], capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.SubprocessError) as err:
        return None, None, f"nvidia-smi did not run ({type(err).__name__})"
    if proc.returncode != 0:
        first = (proc.stdout + proc.stderr).strip().splitlines()
        return None, None, f"nvidia-smi failed (exit {proc.returncode}{': ' + first[0] if first else ''})"
    driver = re.search(r"Driver Version:\s*([0-9][0-9.]*)", proc.stdout)
    cuda = re.search(r"CUDA Version:\s*([0-9]+)\.([0-9]+)", proc.stdout)
    driver = driver.group(1) if driver else None
    if cuda is None:
        return None, driver, "nvidia-smi names no CUDA version"
    version = (int(cuda.group(1)), int(cuda.group(2)))
    return version, driver, f"nvidia-smi: driver {driver or '?'}, CUDA {version[0]}.{version[1]}"


def backend_for(cuda) -> str:
    """The JAX build for a driver supporting CUDA ``cuda`` (``(major, minor)`` or ``None``)."""
    if cuda is None or cuda[0] < 12:
        return "cpu"
    return "cuda12" if cuda[0] == 12 else "cuda13"


def choose(value: str | None, probe=probe_gpu):
    """``(backend, why)`` for the override ``value`` (``None``/empty/``auto``: ask ``probe``).

    Raises ``BadValue`` with a one-line message for a value outside ``ALLOWED``.
    """
    value = (value or "auto").strip()
    if value not in ALLOWED:
        raise BadValue(f"{VARIABLE}={value!r} is not allowed; use one of: {', '.join(ALLOWED)}")
    if value != "auto":
        return value, f"set by {VARIABLE}={value}"
    cuda, _, why = probe()
    backend = backend_for(cuda)
    if cuda is not None and backend == "cpu":
        why += "; JAX's CUDA builds need CUDA >= 12 (driver >= 525)"
    return backend, why


def stale_plugins(backend: str, installed) -> list[str]:
    """Installed (names in ``installed``) jax CUDA plugin distributions that ``backend`` does not use."""
    keep = PLUGINS.get(backend, ())
    return sorted(name for names in PLUGINS.values() for name in names if name in installed and name not in keep)


def installed_plugins() -> set[str]:
    from importlib import metadata

    names = {name for pair in PLUGINS.values() for name in pair}
    found = set()
    for name in names:
        try:
            metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
        found.add(name)
    return found


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--stale"]:
        if len(argv) != 2 or argv[1] not in BACKENDS:
            print(f"usage: --stale {{{','.join(BACKENDS)}}}", file=sys.stderr)
            return 2
        print(" ".join(stale_plugins(argv[1], installed_plugins())))
        return 0
    name_only = argv[:1] == ["--name"]
    rest = argv[1:] if name_only else argv
    if len(rest) > 1:
        print(f"usage: _backend_select.py [--name] [{'|'.join(ALLOWED)}]", file=sys.stderr)
        return 2
    value = rest[0] if rest else os.environ.get(VARIABLE)
    try:
        backend, why = choose(value)
    except BadValue as err:
        # --name: the Makefile shows this line as its error; otherwise a plain one-line error.
        print(err, file=sys.stdout if name_only else sys.stderr)
        return 2
    if name_only:
        print(backend)
    else:
        print(f"[shed_jax] JAX build: {backend} ({why}; choose with make setup {VARIABLE}={'|'.join(BACKENDS)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
