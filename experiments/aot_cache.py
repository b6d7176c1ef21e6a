"""Compile a carried run's programs for its GPU on a CPU host, into the run's compilation cache.

A 2-D walker run's first piece on a GPU spends most of its device call compiling (DR's chunk: more
than 510 s on an H200; SHED's: 526 s), and device time is the scarce resource. XLA can compile for a
GPU it does not have (deviceless ahead-of-time compilation: a compile-only PJRT topology of the
target), and JAX's persistent cache stores the result under a key of the program, the jaxlib
version, the platform, the XLA flags, the compile options and the devices. If a CPU host computes
the same key as the GPU host, a piece on the GPU reads the executable from the carried cache (about
100 s for SHED's chunk, its tracing and lowering) instead of compiling it. Two of the key's parts
cannot be read off a CPU host: the GPU client's platform version (the CUDA runtime's) and the
fingerprint of the GPU's topology. So the work has two steps:

1. ``probe`` (on the GPU, before a piece; ``run_piece.sh`` runs it when ``AOT_PROBE=1``): build the
   run's initial-state program as ``shed_jax run`` does, compute its cache key without compiling,
   and write every part of the key, the platform version and the serialized topology to a JSON file.
2. ``fill`` (on a CPU host with the GPU's jax, jaxlib and CUDA plugin versions installed): the same
   programs (the initial state; with ``--chunks`` the chunks and the final evaluation's programs,
   which a run compiles beside its first chunks) for the probed topology, the key computed with the
   probed platform version, compiled into the cache; the initial state's key parts are compared with
   the probe's before any chunk is compiled, and every difference is named, so a fill that the GPU
   would miss says so (and stops).

Both steps must run the run's own sources at the path the GPU host runs them from (kernel IR holds
source locations); ``experiments/aot_fill.sh`` does that on the CPU host with a private mount.

A filled cache served one H100 host and missed on the next (2026-12-05): hosts with one GPU model can
differ in the two host parts (the driver's version is in the topology). ``fill --portable`` files
the programs under *portable keys* instead (``PORTABLE_PARTS`` and the device kind: no host part),
renaming entries already there under the probed host's keys, and ``run -m shed_jax run ...`` (which
``run_piece.sh`` uses when the carried cache holds such entries) runs the run with the same keys, so
one cache serves every host with that GPU model. ``run`` also gives a resumed chunk without its
trace, from a *stand-in* an earlier piece wrote (``with_stand_ins``, below).
This file uses JAX internals (``jax._src.cache_key``, ``jax._src.compilation_cache``, the picklers of
``jax.experimental.serialize_executable``) of jax 0.10 and 0.11:
that is why it is a tool beside the runs, not part of ``shed_jax``.

    python experiments/aot_cache.py probe RUN_ARGS OUT.json          # on the GPU
    python experiments/aot_cache.py fill RUN_ARGS PROBE.json [--chunks] [--portable] [--out REPORT.json]
    python experiments/aot_cache.py run -m shed_jax run ARGS...       # on the GPU, portable keys

``run`` with ``AOT_TRACE_CALL=K AOT_TRACE_OUT=FILE.json`` also profiles the K-th chunk call
(``traced_calls``): where a piece's budget steps go, at no compile of its own.
"""
from __future__ import annotations

import argparse
import base64
import contextlib
import functools
import hashlib
import json
import os
import shlex
import sys
import threading
import time


SOURCE_DIRS = ("shed_jax", "envs", "experiments")  # what a run folder's src.tgz holds


def sources_digest(root: str = ".") -> str:
    """SHA-256 over the Python sources a run's programs are built from (``SOURCE_DIRS`` under
    ``root``: each file's relative path and bytes, in sorted order). Two trees with one digest build
    the same programs; a probe records it so that a fill can tell a probe of its own program from
    one of other sources."""
    h = hashlib.sha256()
    files = sorted(os.path.relpath(os.path.join(d, f), root)
                   for top in SOURCE_DIRS for d, _, fs in os.walk(os.path.join(root, top))
                   for f in fs if f.endswith(".py"))
    for rel in files:
        h.update(rel.encode() + b"\0")
        with open(os.path.join(root, rel), "rb") as fh:
            h.update(fh.read() + b"\0")
    return h.hexdigest()


PROGRAM_FREE_OPTIONS = "compile_options but the program's shape"
# the key parts that follow the program: a probe of another program is compared on the others
PROGRAM_PARTS = ("computation", "compile_options")


def _without_program_shape(options):
    """A copy of XLA ``CompileOptions`` without the fields JAX sets from the program (whether its
    inputs are passed as a tuple, per input and output whether sharding may propagate to it, and
    XLA's detailed logging, on for programs of 10 or more operations): what two programs compiled on
    one host share."""
    from jax._src.lib import xla_client

    o = xla_client.CompileOptions.ParseFromString(options.SerializeAsString())
    o.parameter_is_tupled_arguments = False
    o.executable_build_options.debug_options.xla_detailed_logging = True
    o.executable_build_options.allow_spmd_sharding_propagation_to_parameters = []
    o.executable_build_options.allow_spmd_sharding_propagation_to_output = []
    return o


# The key parts that follow the program, the software and its settings. The other two follow the GPU
# host: "backend version" (the CUDA runtime's version) and "accelerator_config" (the fingerprint of the
# GPU topology, which holds the driver's version, the clocks and the memory size). Two hosts with one
# GPU model can differ in those and still run each other's executables; a portable key names an entry
# by the parts below and the device kinds, so that a carried cache serves every such host.
HOST_PARTS = ("backend version", "accelerator_config")  # what only the GPU host knows
PORTABLE_PARTS = ("computation", "jax_lib version", "XLA flags", "compile_options", "compression", "custom_hook")
PORTABLE_TAG = "portable"


def portable_key(name: str, parts: dict, device_kinds) -> str:
    """``NAME-portable-HEX``: SHA-256 over ``PORTABLE_PARTS``' digests (``key_parts``) and the device
    kinds (e.g. "NVIDIA H100 80GB HBM3"), in order."""
    h = hashlib.sha256()
    for p in PORTABLE_PARTS:
        h.update(parts[p].encode() + b"\0")
    for kind in device_kinds:
        h.update(kind.encode() + b"\0")
    return f"{name}-{PORTABLE_TAG}-{h.hexdigest()}"


def is_portable(key: str) -> bool:
    return key.split("-")[1:2] == [PORTABLE_TAG]


def _rename_entry(folder: str, old: str, new: str) -> bool:
    """JAX's cache files of key ``old`` (``-cache`` and, where there is one, ``-atime``) renamed to ``new``."""
    src = os.path.join(folder, f"{old}-cache")
    if not os.path.exists(src):
        return False
    os.replace(src, os.path.join(folder, f"{new}-cache"))
    if os.path.exists(os.path.join(folder, f"{old}-atime")):
        os.replace(os.path.join(folder, f"{old}-atime"), os.path.join(folder, f"{new}-atime"))
    return True


_FILED = threading.local()  # .key: the cache key the hook filed last in this thread (``hook_keys``)


class _Captured(Exception):
    """Raised from the key hook in ``probe``: the key is known, the compile is not wanted."""


def key_parts(module, devices, options, backend, compression: str) -> dict:
    """Each part of JAX's persistent-cache key hashed on its own (SHA-256 hex), as ``cache_key.get``
    feeds them into one hash in this order; a part that differs between two hosts is the miss's cause.
    One more entry, not in JAX's key: ``PROGRAM_FREE_OPTIONS``, the compile options with the fields
    that follow the program's inputs and outputs cleared, to compare a probe of another program."""
    from jax._src import cache_key as ck

    parts = {
        "computation": lambda h: ck._hash_computation(h, module, False),
        "jax_lib version": lambda h: h.update(ck.jaxlib_version_str.encode("utf-8")),
        "backend version": lambda h: ck._hash_platform(h, backend),
        "XLA flags": lambda h: ck._hash_xla_flags(h, ck.get_flag_prefixes()),
        "compile_options": lambda h: ck._hash_serialized_compile_options(
            h, options, strip_device_assignment=(backend.platform == "gpu")),
        "accelerator_config": lambda h: ck._hash_accelerator_config(h, devices),
        "compression": lambda h: ck._hash_string(h, compression),
        "custom_hook": lambda h: ck._hash_string(h, ck.custom_hook()),
        PROGRAM_FREE_OPTIONS: lambda h: ck._hash_serialized_compile_options(
            h, _without_program_shape(options), strip_device_assignment=(backend.platform == "gpu")),
    }
    out = {}
    for name, fn in parts.items():
        h = hashlib.sha256()
        fn(h)
        out[name] = h.hexdigest()
    return out


class _Backend:
    """A backend with another platform version (the GPU host's), everything else the compile-only one's."""

    def __init__(self, backend, platform_version: str):
        self._backend, self.platform_version = backend, platform_version

    def __getattr__(self, name):
        return getattr(self._backend, name)


def hook_keys(seen: dict, platform_version: str | None = None, compression: str | None = None,
              stop_at: str | None = None, present_in: str | None = None, portable: bool = False,
              say=None) -> None:
    """Wrap ``compilation_cache.get_cache_key``: record each program's key and key parts in ``seen``
    (by module name; a GPU program's ``portable_key`` too), with the given platform version and
    compression name in the key (the GPU host's); raise :class:`_Captured` once the program named
    ``stop_at`` has its key, or once a GPU program's entry is already in the cache folder ``present_in``
    (e.g. compiled by the GPU host itself: this host could not load it to check it, and would replace
    it with its own).

    ``portable=True``: GPU programs are filed under their ``portable_key``; with ``present_in``, an
    entry there under JAX's key is renamed to the portable one (``seen[name]["rekeyed"]``). ``say``
    (a function of one line) hears the portable key and this host's two host parts of the first GPU
    program of each name."""
    import numpy as np
    from jax._src import cache_key as ck
    from jax._src import compilation_cache as cc

    default_compression = "zstandard" if cc.zstandard is not None else "zlib"
    told: set = set()

    def get_cache_key(module, devices, options, backend, ignore_custom_partitioning=False):
        comp = default_compression
        if backend.platform == "gpu":  # the host's own programs (eager operations on a CPU host) as they are
            comp = compression or default_compression
            if platform_version is not None:
                backend = _Backend(backend, platform_version)
        key = ck.get(module, devices, options, backend, comp, ignore_custom_partitioning)
        name = key.split("-")[0]
        parts = key_parts(module, devices, options, backend, comp)
        seen[name] = {"key": key, "parts": parts}
        gpu = backend.platform == "gpu"
        if gpu:
            seen[name]["portable_key"] = portable_key(name, parts, [d.device_kind for d in np.asarray(devices).flat])
            if say and name not in told:  # once per program name (eager operations come in hundreds)
                told.add(name)
                say(f"aot_cache: {name} under its portable key {seen[name]['portable_key'][:56]}... (this host's "
                    f"backend version {parts['backend version'][:12]}, accelerator_config {parts['accelerator_config'][:12]})")
        filed = seen[name]["portable_key"] if (gpu and portable) else key
        _FILED.key = filed
        if name == stop_at:
            raise _Captured(name)
        if present_in and gpu:
            if filed != key and _rename_entry(present_in, key, filed):
                seen[name]["rekeyed"] = True
            if os.path.exists(os.path.join(present_in, f"{filed}-cache")):
                seen[name]["present"] = True
                raise _Captured(name)
        return filed

    cc.get_cache_key = get_cache_key


def _options(args_file: str):
    """``args_file``'s ``shed_jax run`` flags as the run reads them (checked)."""
    from shed_jax import driver
    from shed_jax.cli import errors
    import shed_jax.cli.run as cli_run

    parser = errors.Parser(prog="aot_cache")
    cli_run.add_arguments(parser)
    opts = driver.RunOptions.from_args(parser.parse_args(shlex.split(open(args_file).read())))
    opts.check()
    return opts


def final_evals(args_file: str, state) -> list:
    """The run's final evaluation programs as a GPU run compiles them while it trains
    (``driver.FinalEvalCompile``: one per ``--final-eval`` level set, for point 0's students of the
    abstract ``state`` that ``build`` gives, and ``experiment.seed_keys(0, seeds)``), as ``[(level set,
    lower)]``; empty where the run has no final evaluation. Whether the run compiles it early or after
    training (``--compile-final-eval``, which a resumed run does not keep), the program and its
    arguments are the same, so one cache entry serves both. Call it after ``build``
    (which sets the kernels' padding) and each ``lower`` under ``_as_gpu_host``; the levels and the
    student are made here, on this host's default device (eager operations on a compile-only device
    cannot run)."""
    import jax
    import jax.numpy as jnp

    from shed_jax import rundir
    from shed_jax import experiment as xp
    from shed_jax.evaluation import evaluation_program, final_level_sets

    opts = _options(args_file).with_output(None)  # a new run's output settings: the env's level sets, 10 episodes
    plan = rundir.plan_fresh(opts, "gpu")
    parts = xp.build_checked(plan.exp, True)
    final_sets = final_level_sets(opts.final_eval, plan.exp, parts[0], parts[3])
    if not final_sets:
        return []
    seeds = plan.num_seeds
    students = jax.tree.map(lambda x: jax.ShapeDtypeStruct((seeds,) + x.shape[1:], x.dtype, sharding=x.sharding),
                            state.student)  # Batch.rows(students, 0): the first point's seeds, sharding kept
    keys = jax.ShapeDtypeStruct((seeds, 2), jnp.uint32)  # seed_keys: an uncommitted array
    student = parts[1]  # the batch's student (driver.make_batch keeps the parts' own)
    return [(name, lambda levels=levels: evaluation_program(student, levels, opts.final_eval_episodes,
                                                            plan.exp.loop.test_max_steps)
             .lower(students, keys)) for levels, _, name in final_sets]


def build(args_file: str, device):
    """The run of ``args_file`` (``shed_jax run`` flags) as the driver builds it for one ``device``:
    ``(init, abstract inputs, chunk, chunk lengths, abstract state)``, the kernels padded as a run pads them."""
    import jax

    from shed_jax import driver, rundir, runtime, sharding
    from shed_jax import experiment as xp

    opts = _options(args_file)
    plan = rundir.plan_fresh(opts, "gpu")
    batch = driver.make_batch(plan.exp, xp.build_checked(plan.exp, True), [({}, {})], num_seeds=plan.num_seeds,
                              root_seed=plan.root_seed, chunk=plan.chunk)
    placed = driver.place(batch, sharding.batch_mesh([device]))
    runtime.pad_kernels_to(driver.kernel_worlds(batch, placed))
    s = sharding.batch_sharding(placed.mesh)
    init = sharding.sharded_init(driver.batch_init(batch.init, batch.method), placed.mesh)
    ins = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), placed.inputs)
    state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), jax.eval_shape(init, *ins))
    run_chunk = sharding.sharded_run(batch.run, placed.mesh)
    return init, ins, run_chunk, driver.chunk_sizes(batch.chunk, 0, batch.total), state


@contextlib.contextmanager
def _as_gpu_host(device):
    """Trace as the GPU host does: ``jax.default_backend()`` says "gpu" (the code's own choices at trace
    time read it: the 2-D physics' fused loops are Pallas kernels there, XLA loops here; the lander's
    unroll) and the default device is the target (Pallas reads the GPU's kind off it)."""
    import jax

    real = jax.default_backend
    jax.default_backend = lambda: "gpu"
    try:
        with jax.default_device(device):
            yield
    finally:
        jax.default_backend = real


def _cpu_model() -> str:
    """This host's CPU, for the fill's report (compile times depend on it)."""
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        import platform

        return platform.processor() or platform.machine()


def _write_text(lowered, path: str) -> None:
    """The lowered program's text without source locations, gzipped (a few MB on the 2-D walker)."""
    import gzip

    with gzip.open(path, "wt") as f:
        f.write(lowered.as_text(debug_info=False))


def _start():
    """The process as ``python -m shed_jax`` starts it: its XLA flags, cache and MLIR locations; returns
    the cache folder."""
    from shed_jax.xla_cpu import apply_cpu_guard

    apply_cpu_guard()
    try:  # as the run's own sources start (those before 2026-12-07 have no shed_jax.xla_gpu, and no FMA flag)
        from shed_jax.xla_gpu import apply_gpu_codegen
    except ModuleNotFoundError:
        pass
    else:
        apply_gpu_codegen()
    from shed_jax import runtime

    cache = runtime.enable_compilation_cache()
    runtime.call_site_free_locations()
    return cache


def probe(args_file: str, out: str) -> int:
    import jax
    from jax._src import compilation_cache as cc
    from jax.experimental import topologies

    cache = _start()
    device = jax.devices()[0]
    seen: dict = {}
    hook_keys(seen, stop_at="jit_init_point")
    init, ins, *_ = build(args_file, device)
    t = time.time()
    lowered = init.trace(*ins).lower()
    _write_text(lowered, out.removesuffix(".json") + "_init.mlir.gz")  # to diff with a fill's when keys differ
    try:
        lowered.compile()
    except _Captured:
        pass
    rec = {"run_args": open(args_file).read().strip(), "sources": sources_digest(),
           "jax": jax.__version__, "device_kind": device.device_kind,
           "root": os.getcwd(), "cache": cache,
           "platform_version": device.client.platform_version,
           "compression": "zstandard" if cc.zstandard is not None else "zlib",
           "topology": base64.b64encode(topologies.get_attached_topology(device.platform).serialize()).decode(),
           "xla_flags": os.environ.get("XLA_FLAGS", ""), "programs": seen, "lower_s": round(time.time() - t, 1)}
    with open(out, "w") as f:
        json.dump(rec, f, indent=1)
    print(f"aot_cache probe: {device.device_kind}, platform {rec['platform_version']!r}, "
          f"jit_init_point key {seen.get('jit_init_point', {}).get('key', '?')[:40]}... -> {out}")
    return 0


def _cuda_plugin() -> None:
    """JAX's CUDA plugin, loaded without a GPU to run on (deviceless compiles and topologies)."""
    from jax._src import xla_bridge
    from jax._src.lib import xla_client

    xla_bridge._discover_and_register_pjrt_plugins()
    if not xla_client.pjrt_plugin_initialized("cuda"):
        xla_client.initialize_pjrt_plugin("cuda")


def target_probe(probe_file: str, target_file: str, out: str) -> int:
    """A probe for a GPU model that no piece has probed: ``probe_file`` (a real probe, of any GPU model,
    for its software: jax, the tree's root, the cache folder, compression, flags and the initial
    state's key parts) with the GPU of ``target_file`` (a GPU description, as ``experiments/targets``
    holds) in place of the probed one. A portable key holds no part that only the GPU host knows, so
    such a probe serves ``fill --portable`` (and nothing else): the probe's host parts (``HOST_PARTS``)
    are dropped, and the fill compares the rest. Whether the GPU host then finds the programs is for
    its first piece to say (``AOT_GATE=1`` stops one that does not, at the cost of a start)."""
    os.environ.setdefault("JAX_PLATFORMS", "cpu")  # no GPU here: the CUDA plugin only describes the target
    import jax
    from jax.experimental import topologies

    rec = json.load(open(probe_file))
    if rec.get("jax") != jax.__version__:
        print(f"aot_cache target-probe: {probe_file} is of jax {rec.get('jax')}, this host has {jax.__version__}",
              file=sys.stderr)
        return 2
    try:
        config = open(target_file).read()
    except OSError as err:
        print(f"aot_cache target-probe: cannot read {target_file}: {err.strerror}", file=sys.stderr)
        return 2
    _cuda_plugin()
    topo = topologies.get_topology_desc(platform="cuda", target_config=config, topology="1x1x1")
    kinds = sorted({d.device_kind for d in topo.devices})
    rec.update(device_kind=kinds[0], topology=base64.b64encode(topo.serialize()).decode(),
               target_probe={"from_probe": probe_file, "probed_gpu": rec.get("device_kind"), "target": target_file})
    for prog in rec.get("programs", {}).values():
        for part in HOST_PARTS:
            prog.get("parts", {}).pop(part, None)
        prog.pop("key", None)  # a key over the probed host's parts: no GPU of the target's asks for it
    with open(out, "w") as f:
        json.dump(rec, f, indent=1)
    print(f"aot_cache target-probe: {rec['target_probe']['probed_gpu']}'s probe as {kinds[0]} -> {out}")
    return 0


def fill(args_file: str, probe_file: str, chunks: bool, out: str | None, portable: bool = False) -> int:
    import jax
    from jax.experimental import topologies

    rec = json.load(open(probe_file))
    if rec.get("target_probe") and not portable:
        print(f"aot_cache fill: {probe_file} was made from a target description (target-probe), which knows no "
              f"GPU host's own key parts: fill with --portable", file=sys.stderr)
        return 2
    if jax.__version__ != rec["jax"]:
        print(f"aot_cache fill: this host has jax {jax.__version__}, the GPU host {rec['jax']}: install the GPU's "
              f"version (its CUDA plugin too)", file=sys.stderr)
        return 2
    if os.getcwd() != rec["root"]:
        print(f"aot_cache fill: run from {rec['root']} (the GPU host's tree; experiments/aot_fill.sh mounts it), "
              f"not {os.getcwd()}", file=sys.stderr)
        return 2
    cache = _start()
    if cache != rec["cache"]:
        print(f"aot_cache fill: the cache folder is {cache}, the GPU host's {rec['cache']}: set SHED_JAX_CACHE as "
              f"run_piece.sh does", file=sys.stderr)
        return 2
    _cuda_plugin()
    topo = topologies.TopologyDescription.deserialize(base64.b64decode(rec["topology"]))
    device = topo.devices[0]
    seen: dict = {}
    hook_keys(seen, platform_version=rec["platform_version"], compression=rec["compression"], present_in=cache,
              portable=portable)
    init, ins, run_chunk, sizes, state = build(args_file, device)
    report = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "host": _cpu_model(), "portable": portable,
              "cpus": os.cpu_count(), "jax": jax.__version__, "target": rec["device_kind"],
              "device": f"{_cpu_model()} ({os.cpu_count()} CPUs), compiling for {rec['device_kind']} (deviceless)",
              "command": " ".join(sys.argv), "probe": probe_file, "programs": {}}
    theirs = rec["programs"].get("jit_init_point", {})
    if not theirs.get("parts"):
        print(f"aot_cache fill: {probe_file} holds no key of the initial state to compare with", file=sys.stderr)
        return 1
    # a probe of another run, or of the same flags on other sources (one probe serves every run on that
    # GPU host): its program differs, the rest must not. A probe without "sources" (before 2026-12-05)
    # cannot say which sources it ran, so only its other key parts are compared
    same_run = rec.get("run_args") == open(args_file).read().strip() and rec.get("sources") == sources_digest()

    def compile_one(label, lower):
        t = time.time()
        with _as_gpu_host(device):
            lowered = lower()
        if label == "jit_init_point":
            _write_text(lowered, "aot_fill_init.mlir.gz")
        try:
            lowered.compile()
        except _Captured as c:  # its entry is in the cache already (hook_keys' present_in)
            rekeyed = bool(seen[c.args[0]].get("rekeyed"))
            report["programs"][label] = {"already_in_cache": True, "rekeyed": rekeyed}
            print(f"aot_cache fill: {label} is in the cache already; "
                  + ("renamed to its portable key" if rekeyed else "left as it is"), flush=True)
            return
        report["programs"][label] = {"compile_s": round(time.time() - t, 1)}
        print(f"aot_cache fill: {label} compiled in {time.time() - t:.1f} s", flush=True)

    def write_report(**kw):
        report.update(keys={k: v["key"] for k, v in seen.items()}, same_run_as_probe=same_run, **kw)
        if out:
            with open(out, "w") as f:
                json.dump(report, f, indent=1)

    compile_one("jit_init_point", lambda: init.trace(*ins).lower())
    ours = seen.get("jit_init_point", {})
    tp, op = theirs.get("parts", {}), ours.get("parts", {})
    if same_run:
        differ = [k for k, v in tp.items() if op.get(k) != v]
    else:  # another program: every part but those that follow it
        differ = [k for k, v in tp.items() if k not in PROGRAM_PARTS and op.get(k) != v]
        if PROGRAM_FREE_OPTIONS not in tp:
            print("aot_cache fill: the probe predates the program-free compile options; those were not "
                  "compared", flush=True)
    if differ:  # the chunks would be filed under keys the GPU host never asks for: not compiled
        write_report(init_key_matches=False, init_parts_differing=differ)
        print(f"aot_cache fill: the initial state's key differs from the GPU host's in {', '.join(differ)}: "
              f"the GPU would not find these programs in the cache; chunks not compiled", file=sys.stderr)
        return 1
    print("aot_cache fill: the initial state's key matches the GPU host's" if same_run else
          "aot_cache fill: every key part but the program matches the GPU host's (the probe was of another "
          "run or other sources)",
          flush=True)
    if chunks:
        from shed_jax import driver

        for n in sizes:
            compile_one(f"chunk of {n}", lambda n=n: driver.lower_from_clean_caches(run_chunk, state, n, 0))
        # the run compiles these beside its first chunks, and a piece rarely finishes them; a head start
        # only, so a failure is reported and the chunks compiled above are kept
        try:
            for name, lower in final_evals(args_file, state):
                compile_one(f"final evaluation ({name})", lower)
        except Exception as err:  # noqa: BLE001
            report["programs"]["final evaluation"] = {"error": f"{type(err).__name__}: {err}"}
            print(f"aot_cache fill: the final evaluation was not compiled ({type(err).__name__}: {err})", flush=True)
    write_report(init_key_matches=ours.get("key") == theirs.get("key"), init_parts_differing=[])
    return 0


# Stand-ins. A piece that resumes SHED on the 2-D walker reads its chunk from the carried cache, yet
# spends 76-122 s of its 555 s (2026-12-06) tracing and lowering the chunk only to compute that cache
# key. The first piece that compiles or reads a chunk therefore writes a *stand-in* beside JAX's cache
# folder: the compiled program as ``jax.experimental.serialize_executable`` pickles it, but with the
# executable's bytes replaced by the key of the JAX cache entry that holds them (and their SHA-256),
# filed under a key of everything the trace depends on (``stand_in_key``). A later piece with that key
# loads the entry and skips the trace. Anything that does not match (a missing or changed cache
# entry, another jax, an unpickling error) falls back to tracing, with one line saying why.
STAND_INS = "programs"  # the stand-ins' folder, beside JAX's cache folder (.cache/device/programs)
# environment variables that change only what JAX logs, not what it builds
_LOG_ONLY_ENV = ("JAX_EXPLAIN_CACHE_MISSES", "JAX_DEBUG_LOG_MODULES", "JAX_LOGGING_LEVEL", "TF_CPP_MIN_LOG_LEVEL",
                 "TF_CPP_VMODULE", "TF_CPP_MAX_VLOG_LEVEL")
# and those that change only how the client allocates device memory (experiments/run_pieces.sh gives
# each of several runs on one GPU a share of it)
_ALLOCATOR_ENV = "XLA_PYTHON_CLIENT_"
_SCALARS = (bool, int, float, str, type(None))


def stand_in_key(jitted, args: tuple, context: str) -> str | None:
    """SHA-256 naming the program ``jitted.trace(*args)`` lowers, or None where it cannot be named
    without the trace: not a ``jax.jit`` function, or a static argument that is not a plain scalar.
    ``context`` must name everything else the program follows (``stand_in_context``). Dynamic Python
    scalars count by type alone (their abstract value), static ones by value, arrays by shape, dtype,
    weak type and sharding, all in the arguments' tree structure."""
    import jax

    info = getattr(jitted, "_jit_info", None)
    if info is None:
        return None
    static = set(info.static_argnums)
    parts = [context, info.fun_sourceinfo, repr(info.in_shardings_leaves), repr(info.out_shardings_leaves),
             repr(info.donate_argnums), repr(info.static_argnums)]
    for i, a in enumerate(args):
        if i in static:
            if not isinstance(a, _SCALARS):
                return None
            parts.append(f"static {a!r}")
            continue
        leaves, tree = jax.tree.flatten(a)
        parts.append(str(tree))
        for x in leaves:
            if isinstance(x, _SCALARS):
                parts.append(type(x).__name__)
            elif hasattr(x, "shape") and hasattr(x, "dtype"):
                sharding = getattr(x, "sharding", None)
                ids = sorted(d.id for d in sharding.device_set) if sharding is not None else None
                parts.append(f"{tuple(x.shape)} {x.dtype} {getattr(x, 'weak_type', False)} {sharding!r} {ids}")
            else:
                return None
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def stand_in_context(run_dir: str | None) -> str | None:
    """What a run's programs follow beyond their arguments: its sources (``sources_digest`` of this
    folder), Python and its dependencies' versions, the devices, the ``JAX_*``/``XLA_*`` environment
    (less ``_LOG_ONLY_ENV`` and the allocator's ``XLA_PYTHON_CLIENT_*``) and the run's ``config.json`` less its output settings and commit; None
    where ``run_dir`` has none."""
    import jax

    path = os.path.join(run_dir, "config.json") if run_dir else None
    if not path or not os.path.isfile(path):
        return None
    config = json.load(open(path))
    config = {k: v for k, v in config.items() if k not in ("output", "commit")}
    env = sorted((k, v) for k, v in os.environ.items()
                 if k.startswith(("JAX_", "XLA_")) and k not in _LOG_ONLY_ENV and not k.startswith(_ALLOCATOR_ENV))
    devices = [(d.id, d.platform, d.device_kind) for d in jax.devices()]
    return json.dumps([sources_digest("."), sys.version, _versions(), devices, env, config], sort_keys=True)


def _versions() -> list:
    """The installed versions of the run's dependencies (``shed_jax.runtime.REQUIRED_MODULES``, the
    run's own list), whose code its programs are partly traced from."""
    from importlib import metadata

    from shed_jax.runtime import REQUIRED_MODULES

    out = []
    for name in sorted(REQUIRED_MODULES):
        try:
            out.append((name, metadata.version(name)))
        except metadata.PackageNotFoundError:
            out.append((name, None))
    return out


def _cache_payload(backend, key: str) -> bytes | None:
    """The serialized executable JAX's persistent cache holds under ``key``, or None."""
    from jax._src import compilation_cache as cc

    cache = cc._get_cache(backend)
    raw = cache.get(key) if cache is not None else None
    if raw is None:
        return None
    return cc.extract_executable_and_time(cc.decompress_executable(raw))[0]


def save_stand_in(path: str, compiled, key: str) -> str | None:
    """Write ``compiled``'s stand-in to ``path``, its executable named by the cache entry ``key``; returns
    None, or why it was not written."""
    import io
    import pickle

    import jax
    from jax.experimental import serialize_executable as se

    backend = jax.devices()[0].client
    payload = _cache_payload(backend, key)
    if payload is None:
        return f"the cache holds no entry {key[:48]}..."
    digest = hashlib.sha256(payload).hexdigest()

    from jax._src.lib import _jax
    from jax._src.lib import xla_client as xc

    class Pickler(se._JaxPjrtPickler):
        def persistent_id(self, obj):  # the executable by reference, never serialized here
            if isinstance(obj, (xc.LoadedExecutable, _jax.Executable)):
                return ("cached", key, digest)
            return super().persistent_id(obj)

    unloaded = getattr(compiled._executable, "_unloaded_executable", None)
    if unloaded is None or compiled._params.const_args:
        return "this executable cannot be serialized"
    args_info_flat, in_tree = jax.tree.flatten(compiled.args_info)
    with io.BytesIO() as f:
        Pickler(f).dump((unloaded, args_info_flat, compiled._no_kwargs))
        body = f.getvalue()
    devices = sorted({d.id for sh in jax.tree.leaves(compiled.input_shardings) for d in sh.device_set})
    blob = pickle.dumps({"jax": jax.__version__, "key": key, "sha256": digest, "in_tree": in_tree,
                         "out_tree": compiled.out_tree, "devices": devices, "body": body})
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path + ".tmp", "wb") as f:
        f.write(blob)
    os.replace(path + ".tmp", path)
    return None


def load_stand_in(path: str):
    """The ``jax.stages.Compiled`` a stand-in names; ValueError saying why where it cannot be had."""
    import io
    import pickle

    import jax
    from jax.experimental import serialize_executable as se

    entry = pickle.load(open(path, "rb"))
    if entry.get("jax") != jax.__version__:
        raise ValueError(f"written by jax {entry.get('jax')}, this is {jax.__version__}")
    backend = jax.devices()[0].client
    payload = _cache_payload(backend, entry["key"])
    if payload is None:
        raise ValueError(f"the cache holds no entry {entry['key'][:48]}...")
    if hashlib.sha256(payload).hexdigest() != entry["sha256"]:
        raise ValueError(f"the cache entry {entry['key'][:48]}... holds another executable")

    class Unpickler(se._JaxPjrtUnpickler):
        def persistent_load(self, pid):
            if pid[0] == "cached":
                return self.backend.deserialize_executable(payload, executable_devices=self.execution_devices)
            return super().persistent_load(pid)

    by_id = {d.id: d for d in backend.devices()}
    if not set(entry["devices"]) <= set(by_id):
        raise ValueError(f"its devices {entry['devices']} are not all on this host")
    devices = [by_id[i] for i in entry["devices"]]  # the program's own, not every device of the host
    unloaded, args_info_flat, no_kwargs = Unpickler(io.BytesIO(entry["body"]), backend, devices).load()
    return jax.stages.Compiled(unloaded.load(), [], entry["in_tree"].unflatten(args_info_flat),
                               entry["out_tree"], no_kwargs=no_kwargs)


class _Ready:
    """Stands for a ``Lowered`` whose ``compile()`` is already known."""

    def __init__(self, compiled):
        self._compiled = compiled

    def compile(self, *_, **__):
        return self._compiled


class _Saving:
    """A ``Lowered`` whose ``compile()`` also writes the program's stand-in."""

    def __init__(self, lowered, path: str, say):
        self._lowered, self._path, self._say = lowered, path, say

    def compile(self, *a, **kw):
        _FILED.key = None
        try:
            compiled = self._lowered.compile(*a, **kw)
        except Exception as err:  # said here too: a caller may swallow it (the final evaluation's worker does)
            self._say(f"aot_cache: {os.path.basename(self._path)[:16]}... not compiled, so no stand-in "
                      f"({type(err).__name__}: {_first_line(err)})")
            raise
        key = getattr(_FILED, "key", None)
        try:
            why = save_stand_in(self._path, compiled, key) if key else "the compile filed no cache key"
        except Exception as err:  # noqa: BLE001 - a stand-in is an optimisation; the run goes on
            why = f"{type(err).__name__}: {err}"
        self._say(f"aot_cache: {os.path.basename(self._path)[:16]}... stand-in "
                  + ("written" if why is None else f"not written ({why})"))
        return compiled

    def __getattr__(self, name):
        return getattr(self._lowered, name)


def with_stand_ins(lower, folder, context, say):
    """``lower(jitted, *args)`` (the driver's ``lower_from_clean_caches``) wrapped: a program whose
    stand-in is in ``folder`` comes back compiled without a trace; any other is traced and lowered by
    ``lower``, and its compile writes the stand-in. ``context()`` gives ``stand_in_context``'s string
    (or None: no stand-ins), at each program (memoize it). ``closure``, a keyword of the wrapper: a
    string naming what ``jitted`` closes over that the context does not (``values_digest``)."""

    def lower_or_load(jitted, *args, closure: str = "", **kwargs):
        try:
            ctx = context()
            # the 2-D physics' kernels pad their worlds to a process-wide number (envs/physics2d/fused.py)
            padding = getattr(sys.modules.get("envs.physics2d.fused"), "MIN_WORLDS", None)
            key = None if (kwargs or ctx is None) else stand_in_key(jitted, args, f"{ctx}\n{closure}\n{padding}")
            path = os.path.join(folder(), f"{key}.pkl") if key else None
        except Exception as err:  # noqa: BLE001 - no stand-in, the program traced as ever
            say(f"aot_cache: no stand-in ({type(err).__name__}: {err})")
            path = None
        if path is None:
            return lower(jitted, *args, **kwargs)
        name = os.path.basename(path)[:16]
        if os.path.exists(path):
            t0 = time.time()
            try:
                compiled = load_stand_in(path)
                say(f"aot_cache: {name}... read from its stand-in in {time.time() - t0:.1f} s, not traced")
                return _Ready(compiled)
            except Exception as err:  # noqa: BLE001
                say(f"aot_cache: {name}... stand-in not used ({type(err).__name__}: {err}); tracing it")
        try:
            lowered = lower(jitted, *args, **kwargs)
        except Exception as err:  # said here too, as a failed compile is (``_Saving``)
            say(f"aot_cache: {name}... not lowered, so no stand-in ({type(err).__name__}: {_first_line(err)})")
            raise
        return _Saving(lowered, path, say)

    return lower_or_load


def _profiling():
    """``shed_jax.profiling``: this tree's, or for a carried run whose own ``shed_jax`` predates it, the
    copy ``run_piece.sh`` puts beside this file."""
    try:
        from shed_jax import profiling
    except ImportError:
        import profiling
    return profiling


class _TracedLowered:
    def __init__(self, lowered, count):
        self._lowered, self._count = lowered, count

    def compile(self, *a, **kw):
        return _profiling().TracedCompiled(self._lowered.compile(*a, **kw), self._count)

    def __getattr__(self, name):
        return getattr(self._lowered, name)


def traced_calls(lower, call: int, out: str, say):
    """``lower(jitted, *args)`` wrapped so that the programs it compiles count their calls together:
    calls 1 to ``call + 1`` are waited for and timed, call ``call`` runs under ``jax.profiler`` and
    its summary goes to the JSON file ``out`` (``shed_jax.profiling.TracedCompiled``); other calls run
    untouched. For the driver's chunks, where one call is a few budget steps: the second call is the
    first with nothing left to compile. The runs of this tree's sources have ``shed_jax run
    --profile-chunk K`` for the same; this serves carried runs on older sources."""
    count = _profiling().TraceCount(call, out, say)

    def lower_traced(jitted, *args, **kwargs):
        return _TracedLowered(lower(jitted, *args, **kwargs), count)

    return lower_traced


def _trace_request() -> tuple[int, str] | None:
    """``AOT_TRACE_CALL`` (a call number, 1-based) and ``AOT_TRACE_OUT`` (a JSON path), or None; ValueError
    naming what is wrong."""
    call, out = os.environ.get("AOT_TRACE_CALL", ""), os.environ.get("AOT_TRACE_OUT", "")
    if not call and not out:
        return None
    if not call.isdigit() or int(call) < 1:
        raise ValueError(f"AOT_TRACE_CALL must be a call number from 1, got '{call}'")
    if not out:
        raise ValueError("AOT_TRACE_CALL needs AOT_TRACE_OUT, the summary's JSON path")
    return int(call), out


def _first_line(err: BaseException) -> str:
    text = str(err)
    return text.splitlines()[0] if text else ""


def values_digest(tree) -> str:
    """SHA-256 of a pytree's structure and its leaves' values (arrays: shape, dtype and bytes)."""
    import jax
    import numpy as np

    leaves, tree_def = jax.tree.flatten(tree)
    h = hashlib.sha256(str(tree_def).encode())
    for x in leaves:
        if isinstance(x, _SCALARS):
            h.update(f"{type(x).__name__} {x!r}".encode())
        else:
            a = np.asarray(x)
            h.update(f"{a.shape} {a.dtype}".encode() + a.tobytes())
    return h.hexdigest()


class _Program:
    """A jitted program whose ``lower(*args)`` goes through ``lower_or_load`` with its closure's digest."""

    def __init__(self, jitted, lower_or_load, closure: str):
        self._jitted, self._lower_or_load, self._closure = jitted, lower_or_load, closure

    def __call__(self, *args, **kwargs):
        return self._jitted(*args, **kwargs)

    def lower(self, *args):
        return self._lower_or_load(self._jitted, *args, closure=self._closure)

    def __getattr__(self, name):
        return getattr(self._jitted, name)


def evaluation_with_stand_ins(make, lower_or_load):
    """``shed_jax.evaluation.evaluation_program`` wrapped: its program's ``lower`` reads and writes
    stand-ins, named with the levels, episodes, step limit and determinism it closes over (the student
    follows the run's config). Run on GPU, a run compiles its final evaluation beside its first chunks:
    without this, a piece whose chunk came from a stand-in would lower that program after other traces
    than a traced piece does, which can change the source locations inside its kernels and so its key."""
    import inspect

    signature = inspect.signature(make)

    def evaluation_program(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        closure = values_digest({k: v for k, v in bound.arguments.items() if k != "student"})
        return _Program(make(*args, **kwargs), lower_or_load, f"{make.__module__}.{make.__name__} {closure}")

    return evaluation_program


def _run_dir(argv: list[str]) -> str | None:
    """The run directory of ``shed_jax run`` arguments (``--resume DIR`` or ``--out DIR``)."""
    for flag in ("--resume", "--out"):
        for i, a in enumerate(argv):
            if a == flag and i + 1 < len(argv):
                return argv[i + 1]
            if a.startswith(flag + "="):
                return a.split("=", 1)[1]
    return None


def _stand_in_folder() -> str:
    """``STAND_INS`` beside JAX's cache folder; ValueError where the run has none."""
    import jax

    cache = jax.config.jax_compilation_cache_dir
    if not cache or not jax.config.jax_enable_compilation_cache:
        raise ValueError("the persistent compilation cache is off")
    return os.path.join(os.path.dirname(os.path.abspath(cache)), STAND_INS)


def _hook_stand_ins(argv: list[str], say, stand_ins: bool = True, trace: tuple[int, str] | None = None) -> None:
    """``shed_jax.driver.lower_from_clean_caches`` (the chunks) and ``shed_jax.evaluation.evaluation_program``
    (the final evaluation) through stand-ins (``stand_ins``), and the chunks' calls through
    ``traced_calls`` (``trace``: its call and out), each as its module is imported (not before: the
    package sets things up before its first JAX computation); sources without them run as they are."""
    import importlib.abc
    import importlib.machinery

    run_dir = _run_dir(argv)
    context = functools.lru_cache(maxsize=None)(lambda: stand_in_context(run_dir))  # once per process
    load = with_stand_ins(lambda jitted, *a: jitted.lower(*a), _stand_in_folder, context, say)

    def patch(module):
        if module.__name__ == "shed_jax.driver" and hasattr(module, "lower_from_clean_caches"):
            if stand_ins:
                module.lower_from_clean_caches = with_stand_ins(module.lower_from_clean_caches,
                                                                _stand_in_folder, context, say)
            if trace:
                module.lower_from_clean_caches = traced_calls(module.lower_from_clean_caches, *trace, say)
        if stand_ins and module.__name__ == "shed_jax.evaluation" and hasattr(module, "evaluation_program"):
            module.evaluation_program = evaluation_with_stand_ins(module.evaluation_program, load)

    todo = {"shed_jax.driver", "shed_jax.evaluation"}

    class Finder(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name not in todo:
                return None
            todo.discard(name)  # once (importlib imports a module once, under its lock)
            spec = importlib.machinery.PathFinder.find_spec(name, path)
            if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
                return spec
            run = spec.loader.exec_module

            def exec_module(module):
                run(module)
                patch(module)

            spec.loader.exec_module = exec_module
            return spec

    sys.meta_path.insert(0, Finder())


def run_portable(argv: list[str]) -> int:
    """``-m MODULE ARGS...`` run as ``python -m MODULE ARGS...`` runs it, from this folder, but with its
    GPU programs filed in (and read from) the compilation cache under their portable keys; one line on
    stderr per GPU program names its key and this host's two host parts."""
    if len(argv) < 2 or argv[0] != "-m":
        print("usage: python aot_cache.py run -m MODULE [ARGS...]", file=sys.stderr)
        return 2
    import runpy

    sys.path.insert(0, os.getcwd())  # as ``python -m`` puts it
    say = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    try:
        trace = _trace_request()
    except ValueError as err:
        print(f"aot_cache run: {err}", file=sys.stderr)
        return 2
    hook_keys({}, portable=True, say=say)
    stand_ins = os.environ.get("AOT_STAND_INS", "1") == "1"
    if stand_ins or trace:
        _hook_stand_ins(argv[2:], say, stand_ins, trace)
    sys.argv = [argv[1], *argv[2:]]
    runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["run"]:  # its arguments are the module's, not this parser's
        return run_portable(argv[1:])
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("probe", help="on the GPU: the run's initial-state key parts, platform and topology")
    p.add_argument("args_file")
    p.add_argument("out")
    f = sub.add_parser("fill", help="on a CPU host: compile the run's programs for the probed GPU into the cache")
    f.add_argument("args_file")
    f.add_argument("probe")
    f.add_argument("--chunks", action="store_true",
                   help="the chunks and the final evaluation too (minutes each), not only the initial state")
    f.add_argument("--out", default=None, help="a JSON report: compile times, keys, differing key parts")
    f.add_argument("--portable", action="store_true",
                   help="file the GPU programs under portable keys (entries under the probed host's keys renamed)")
    t = sub.add_parser("target-probe", help="on a CPU host: a probe for a GPU model no piece has probed, from a real "
                                             "probe and a target description (fill --portable only)")
    t.add_argument("probe", help="a probe written on a GPU host (any model, this jax version)")
    t.add_argument("target", help="a GPU description, e.g. experiments/targets/h200.txtpb")
    t.add_argument("out")
    # listed for --help only: main() hands "run" and its arguments to run_portable before parsing
    sub.add_parser("run", help="-m MODULE ARGS...: run a module as python -m does, its GPU programs under portable keys")
    a = ap.parse_args(argv)
    if a.cmd == "probe":
        return probe(a.args_file, a.out)
    if a.cmd == "target-probe":
        return target_probe(a.probe, a.target, a.out)
    return fill(a.args_file, a.probe, a.chunks, a.out, a.portable)


if __name__ == "__main__":
    sys.exit(main())
