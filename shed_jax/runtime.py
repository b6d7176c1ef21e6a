"""What every ``python -m shed_jax`` command does before its own work (``start_up``).

* Turns on JAX's persistent compilation cache in ``cache_root()/jax`` and caches every compile,
  however short or small (CPU programs too), so a second run of the same program skips XLA's
  compile. A cache the caller configured already (``JAX_COMPILATION_CACHE_DIR``, or
  ``jax.config`` as tests/conftest.py sets it) is left as it is; ``JAX_ENABLE_COMPILATION_CACHE=false``
  turns caching off.
* Gives MLIR locations the innermost user frame, not the call stack (:func:`call_site_free_locations`),
  so XLA compiles a Pallas kernel called from several places once.
* Refuses to start, in one line naming them, when packages the project depends on are missing
  (:func:`missing_packages`): otherwise a missing one (say ``orjson``, first imported when the first
  chunk's metrics are written) would stop a run with a traceback after minutes of compiling.
* Prints one line naming the JAX version, backend and devices, and warns in one line when
  ``nvidia-smi`` sees an NVIDIA GPU but JAX runs on the CPU, naming the ``make setup`` that fixes it.
"""
from __future__ import annotations

import contextlib
import logging
import os
import pathlib
import sys
import threading
from collections import Counter
from typing import Callable

CACHE_VARIABLE = "SHED_JAX_CACHE"

# pyproject.toml's `dependencies` -> the module each provides (tests/test_runtime.py keeps them in step).
REQUIRED_MODULES = {
    "jax": "jax", "jaxlib": "jaxlib", "flax": "flax", "optax": "optax", "chex": "chex",
    "orbax-checkpoint": "orbax.checkpoint", "brax": "brax", "mujoco": "mujoco", "mujoco-mjx": "mujoco.mjx",
    "numpy": "numpy", "orjson": "orjson", "matplotlib": "matplotlib", "pillow": "PIL", "tqdm": "tqdm",
}


def _module_found(name: str) -> bool:
    """Whether ``name`` can be imported, without importing it (a dotted name's parent is not run either).

    A dotted name is looked for in its parent's folder and in that parent's folder under every
    ``sys.path`` entry (a package split across entries, as ``pkgutil.extend_path`` joins them)."""
    import importlib.util

    top, _, rest = name.partition(".")
    spec = importlib.util.find_spec(top)
    if spec is None or not rest:
        return spec is not None
    here = [pathlib.Path(p) for p in (spec.submodule_search_locations or [])]
    here += [pathlib.Path(entry or ".") / top for entry in sys.path if isinstance(entry, str)]
    parts = rest.split(".")
    for i, part in enumerate(parts):
        found = [p / part for p in here if (p / part).is_dir()]
        if not found:  # a plain module ends the path: the last part as a file
            return i == len(parts) - 1 and any(
                f.is_file() for p in here if p.is_dir() for f in p.glob(part + ".*") if f.suffix in (".py", ".so", ".pyd"))
        here = found
    return True


def _distribution_found(dist: str) -> bool:
    from importlib import metadata

    try:
        metadata.distribution(dist)
        return True
    except metadata.PackageNotFoundError:
        return False


def missing_packages(modules: dict[str, str] | None = None) -> list[str]:
    """The distributions (keys of ``modules``, default :data:`REQUIRED_MODULES`) found neither as their
    module (value) nor as installed metadata, in order: a false "missing" would block every command."""
    modules = REQUIRED_MODULES if modules is None else modules
    return [dist for dist, module in modules.items() if not _module_found(module) and not _distribution_found(dist)]


def missing_packages_line(missing: list[str]) -> str:
    return (f"[shed_jax] missing package(s): {', '.join(missing)}; `make setup` installs the project's "
            "dependencies (or, in an environment of your own: pip install -e .)")


def cache_root() -> pathlib.Path:
    """``$SHED_JAX_CACHE``, else ``.cache/`` in the source checkout, else ``~/.cache/shed_jax``."""
    if os.environ.get(CACHE_VARIABLE):
        return pathlib.Path(os.environ[CACHE_VARIABLE]).expanduser()
    repo = pathlib.Path(__file__).resolve().parents[1]
    if (repo / "pyproject.toml").is_file():  # an editable install: the checkout the Makefile made
        return repo / ".cache"
    return pathlib.Path.home() / ".cache" / "shed_jax"


def enable_compilation_cache() -> str | None:
    """Point JAX's persistent cache at ``cache_root()/jax`` unless one is set; return the folder in use."""
    import jax

    if not jax.config.jax_enable_compilation_cache:
        return None
    current = jax.config.jax_compilation_cache_dir
    if current:
        return current
    folder = cache_root() / "jax"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        print(f"[shed_jax] no compilation cache: cannot create {folder} ({err.strerror})", file=sys.stderr)
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    # JAX's defaults store only compiles of >= 1 s; an explicit environment setting still wins.
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    if "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES" not in os.environ:
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # -1: no size floor
    return str(folder)


def call_stacks_in_locations() -> bool:
    """Whether MLIR locations now hold call stacks (more than the innermost user frame)."""
    import jax

    return bool(jax.config.jax_include_full_tracebacks_in_locations) and \
        jax.config.jax_traceback_in_locations_limit not in (0, 1)


def call_site_free_locations() -> bool:
    """Give MLIR locations the innermost user frame only, not the whole Python call stack, unless
    ``JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS`` or ``JAX_TRACEBACK_IN_LOCATIONS_LIMIT`` is set; return
    whether locations are now free of call stacks.

    Why: a Pallas kernel's Triton IR keeps its locations, and XLA compiles a Triton call once per
    distinct IR (and grid). With full call stacks the same fused loop called from a reset, a training
    step and an evaluation step embeds three different stacks, so XLA compiled it three times; on the
    2-D walker each large solver kernel compiles for minutes (``experiments.kernel_census`` counts the
    distinct kernels of a run's program). Outside kernels the compilation cache ignores locations.

    How: tracebacks stay on, cut to one frame (``jax_traceback_in_locations_limit`` = 1). Turning them
    off (``jax_include_full_tracebacks_in_locations`` = False, as until 2026-12-07) gives the same
    frame but drops JAX's name stack from the compiled HLO's ``op_name`` metadata, so a profile could
    not tell a budget step's evaluation from its training by name."""
    import jax

    if not {"JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS", "JAX_TRACEBACK_IN_LOCATIONS_LIMIT"} & set(os.environ):
        jax.config.update("jax_include_full_tracebacks_in_locations", True)
        jax.config.update("jax_traceback_in_locations_limit", 1)
    return not call_stacks_in_locations()


# JAX logs each persistent-cache lookup at debug level, as "<prefix> '<program>' with key <key>"
_COMPILER_LOG = "jax._src.compiler"
_LOOKUP_PREFIXES = {"Persistent compilation cache hit for": True, "PERSISTENT COMPILATION CACHE MISS for": False}


class _CacheLookups(logging.Filter):
    """The one filter on JAX's compiler logger while any ``cache_lookups`` block runs: calls every
    block's callback for each lookup line, and passes on only what the logger's level before the
    first block would have passed."""

    def __init__(self, floor: int):
        super().__init__()
        self.floor = floor
        self.callbacks: list = []

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.msg if isinstance(record.msg, str) else ""
        for prefix, hit in _LOOKUP_PREFIXES.items():
            if msg.startswith(prefix) and isinstance(record.args, tuple) and len(record.args) == 2:
                for callback in list(self.callbacks):
                    try:
                        callback(str(record.args[0]), hit, str(record.args[1]))
                    except Exception:  # noqa: BLE001 - a report must never fail JAX's compile
                        pass
        return record.levelno >= self.floor


_lookups_lock = threading.Lock()
_lookups: list = []  # [the installed filter, the logger's level before it] while blocks run


@contextlib.contextmanager
def cache_lookups(on_lookup: Callable[[str, bool, str], None]):
    """While the block runs, ``on_lookup(program, hit, key)`` for each lookup JAX makes in its
    persistent compilation cache (in any thread), e.g. ``("jit_chunk", False, "jit_chunk-4f0c...")``.

    Why: a program that should have been read from a carried cache but is compiled again costs
    minutes; without this, only the time it takes says so. JAX reports lookups only in its debug log
    (``jax._src.compiler``): while blocks run, that logger's level is DEBUG and one filter reads the
    two lookup lines, passing on nothing that the logger's level before would not have passed; the
    last block to end puts the level back. Blocks may overlap, in any order and thread; an exception
    in ``on_lookup`` is dropped, so a report cannot fail a compile."""
    logger = logging.getLogger(_COMPILER_LOG)
    with _lookups_lock:
        if not _lookups:
            _lookups[:] = [_CacheLookups(logger.getEffectiveLevel()), logger.level]
            logger.addFilter(_lookups[0])
            logger.setLevel(logging.DEBUG)
        _lookups[0].callbacks.append(on_lookup)
    try:
        yield
    finally:
        with _lookups_lock:
            lookups, level = _lookups
            lookups.callbacks.remove(on_lookup)
            if not lookups.callbacks:
                logger.removeFilter(lookups)
                logger.setLevel(level)
                _lookups.clear()


def pad_kernels_to(worlds: int) -> int:
    """Pad the GPU kernels of programs lowered from now on to at least ``worlds`` worlds (the 2-D
    physics' fused loops, ``envs.physics2d.fused.pad_worlds_to``); returns the padding in force.

    Why: XLA compiles a Triton call once per distinct IR and grid, and a grid counts blocks of worlds,
    so a loop run by the training rollout (e.g. 5,120 worlds) and by an evaluation (200) was two
    compiles of a kernel that alone compiles for minutes on the 2-D walker. Padded to the training
    batch they are one (``experiments.kernel_census``); an evaluation's kernel of more blocks takes
    the same time on a GPU with more multiprocessors than blocks. Nothing changes off the GPU."""
    from envs.physics2d import fused

    return fused.pad_worlds_to(worlds)


def describe_devices(devices) -> str:
    """``'2 x NVIDIA H200'``-style summary, one group per device kind, in first-seen order."""
    kinds = Counter(getattr(d, "device_kind", d.platform) for d in devices)
    return ", ".join(f"{n} x {kind}" for kind, n in kinds.items())


SOURCE_COMMIT_FILE = ".source_commit"


def source_commit(repo: pathlib.Path | None = None) -> str | None:
    """The commit of this project's checkout, or of ``repo``: ``git describe --always --dirty``, whose
    ``-dirty`` suffix says tracked files differ from that commit. None outside a git checkout of the
    project itself (an installed wheel, a copied tree, no git).

    A ``.source_commit`` file at the checkout's root wins: ``experiments/slim_tree.sh`` writes the
    tree's ``git describe`` there for a device call, whose copy of the tree can carry git metadata
    older than the tree (its records then named a commit of hours before)."""
    import subprocess

    repo = pathlib.Path(__file__).resolve().parents[1] if repo is None else pathlib.Path(repo)
    pinned = repo / SOURCE_COMMIT_FILE
    if pinned.is_file():
        return pinned.read_text().strip() or None
    if not (repo / ".git").exists():  # not a checkout of its own (never the git repository of a folder above)
        return None
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=repo, capture_output=True, text=True,
                             timeout=10, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def provenance(module: str, argv=None) -> dict:
    """Where, how and when a record was measured: ``device`` (backend and devices), ``command``
    (``python -m module`` and its arguments, ``argv`` or the process's), ``date`` (UTC, minutes) and
    ``commit`` (:func:`source_commit`)."""
    import time

    import jax

    args = sys.argv[1:] if argv is None else list(argv)
    return {"device": f"{jax.default_backend()}: {describe_devices(jax.devices())}",
            "command": f"python -m {module} " + " ".join(args),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "commit": source_commit()}


def gpu_unused_warning(backend: str, platforms: str, probe=None) -> str | None:
    """The one-line warning when ``nvidia-smi`` sees a usable GPU but JAX runs on ``backend`` 'cpu'.

    ``platforms`` is ``JAX_PLATFORMS``: a user who asked for the CPU only gets no warning.
    """
    from shed_jax import _backend_select as select

    wanted = {p.strip() for p in platforms.split(",") if p.strip()}
    if backend != "cpu" or (wanted and not wanted & {"cuda", "gpu"}):
        return None
    cuda, driver, why = (probe or select.probe_gpu)()
    fix = select.backend_for(cuda)
    if fix == "cpu":
        return None
    if select.PLUGINS[fix][0] in select.installed_plugins():
        return (f"[shed_jax] warning: {why}, but JAX's {fix} plugin did not start and JAX runs on the CPU "
                f"(JAX's own warning above says why)")
    return (f"[shed_jax] warning: {why}, but JAX has no CUDA build and runs on the CPU; "
            f"install it with: make setup {select.VARIABLE}={fix}")


def start_up() -> None:
    """Enable the compilation cache, then print the backend line (and the GPU warning if due)."""
    import jax

    cache = enable_compilation_cache()
    call_site_free_locations()
    backend = jax.default_backend()
    print(f"[shed_jax] jax {jax.__version__}, backend {backend}: {describe_devices(jax.devices())}; "
          f"compilation cache {cache or 'off'}", flush=True)
    warning = gpu_unused_warning(backend, os.environ.get("JAX_PLATFORMS", ""))
    if warning:
        print(warning, file=sys.stderr, flush=True)
