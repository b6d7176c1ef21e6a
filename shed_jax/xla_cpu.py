"""An XLA:CPU deadlock, what avoids it, and older guards applied before JAX starts its CPU backend.

The deadlock (found 2026-11-23 with ``gdb`` on a hung test, jax/jaxlib 0.10.2)
-------------------------------------------------------------------------------
jaxlib's CPU LAPACK kernels (QR ``lapack_sgeqrf_ffi``, Cholesky ``potrf``, ...) split a *batched*
call into chunks with ``jax::ParallelBatchMap``: the chunks go onto XLA:CPU's intra-op thread pool
and the calling thread waits on a ``BlockingCounter``. The calling thread is itself a pool thread
(the thunk executor runs custom calls there), and the executor runs independent thunks at the same
time. When as many batched LAPACK calls run at once as the pool has threads, every pool thread
waits for chunks that only a pool thread could run: the process sleeps forever with the main
thread in ``BlockUntilReady``. The native stack of a hung ``tests/test_bench_ppo.py`` resume test
(1 hang in 6 local runs of it) shows exactly that: both ``tf_XLAEigen`` threads in
``QrFactorization::Kernel`` -> ``ParallelBatchMap`` -> ``BlockingCounter::Wait``, nothing running.

Our programs make such calls wherever a ``vmap`` over seeds batches them: every student init
(orthogonal weights come from a QR; actor and critic have six of them, all independent) and MJX's
Cholesky factorisations in the walker's step. The pool has one thread per schedulable CPU, so the
2-core CI machine and the 2-core development machine have two: two concurrent QRs suffice. This
explains the hangs seen on CPUs and never on the GPU: the failed CI run of 2026-11-23 (three tests
killed at the 8-minute timeout, among them that resume test) and the walker's runs of two seeds
(hung in every try before; ``gdb`` on one showed the same two QR threads). The ``make run
ENV=lander`` hangs of the same day were not caught with a native stack; they looked the same.

The remedy: our code makes no batched LAPACK call on a CPU. The student's orthogonal init computes
its QR in ``jax.numpy`` there (shed_jax/student/orthogonal.py); nothing else of ours calls LAPACK.
Measured on the 2-core machine with the pool forced to 2 threads (``NPROC=2``), 16 vmapped cartpole
students initialised 1,000 times in a loop: with the library initializer 3 of 3 tries hung within
60 s; with ours 3 of 3 finished, in about 9 s (``python -m experiments.cpu_deadlock`` repeats it;
tests/test_xla_cpu.py keeps a 300-call version).
MJX's Cholesky in the walker's step is batched LAPACK too, but its calls are sequential within a
step: 300 calls of 20 vmapped walker steps with auto-reset (16 envs) finished with ``NPROC=2``.

A second way out, not taken: XLA sizes the pool from the environment variable ``NPROC`` when it is
set (``xla::DefaultThreadPoolSize``). With ``NPROC=8`` a loop of eight concurrent batched QRs
finished (3 of 3 tries, 500 calls) where ``NPROC=4`` hung (3 of 3). But idle pool threads cost
CPU time on a small machine: the lander's heuristic parity test took 28-31 s with the default
pool, 35 s with 4 threads, 38 s with 8, 47 s with 16 and 70 s with 64, and the whole test suite
went from 12.0 to 13.9 minutes with 64 (one run each). Set it yourself if your own code vmaps
LAPACK calls on a CPU. A public report (PyAutoLabs' PyAutoHeart diagnostics, the same stack with
Cholesky) says jaxlib 0.11.2 no longer takes this parallel path in open-source builds; the newest
CPU wheel here is 0.10.2.

Two XLA flags are older guards, chosen before the cause was known:
``--xla_cpu_multi_thread_eigen=false`` (after PyAutoLabs/PyAutoFit#1528, whose hang looked the
same) and ``--xla_cpu_use_xnnpack=false`` (``make run ENV=lander`` on a CPU hung in 4 of 4 tries
without it, 0 of 1 with it). Neither touches the LAPACK path, which is why hangs went on. They stay
because the CPU runs behind this project's numbers used them; whether they still help is untested.
The XNNPACK one looked costly: the test suite took 13 min 8 s with it against 10 min 14 s without
(one run each, 2026-11-23), so it is the first to drop once it is shown not to matter: with the
QR fix in place, that lander run finished with XNNPACK on (1 of 1, docs/log/benchmarks.md "The XLA:CPU deadlock").
That cost did not reproduce under the suite's own flags (below): on 2026-12-03 three of the slowest
test files (the 2-D walker's environment, the lander's parity and the evaluation rollouts, 32 tests,
two workers, an empty cache, one run each, 2-core Intel Xeon) took 276 s with the flag and 295 s
with XNNPACK on, so dropping it would not shorten the suite. GPU runs are unaffected by both flags,
which touch only the CPU backend.
"""
from __future__ import annotations

import os

FLAG = "--xla_cpu_multi_thread_eigen=false"
FLAGS = (FLAG, "--xla_cpu_use_xnnpack=false")


#: The test suite's compile-time flags (tests/conftest.py), for CPU-only processes. The first: LLVM skips
#: its expensive optimisation passes. Compiling dominates the suite (a lander evaluation program: 52 s
#: of XLA compile with the passes, 24 s without, 2-core CPU, 2026-11-25), while its programs run
#: briefly; even the run-bound PPO tests got faster (62 s -> 51 s). The suite passed with it.
#: The second: LLVM's optimisation level 1 instead of 2 (2-core Intel Xeon, 2026-11-29, two workers, one run
#: each, an empty cache): the five slowest compile-bound tests (the 2-D walker's reset, the lander's early-stop
#: evaluation, the fused loop evaluation twice, SHED vs h-MDP) took 293 s in all against 344 s, and the
#: run-bound lander parity tests 77 s and 81 s, as before. Level 0 compiled faster still (215 s) but ran
#: slower: those parity tests took 344 s and 306 s, the whole suite 26.0 min against 28.
#: The third: XLA:CPU's older fusion emitters instead of its newer (MLIR) ones (same machine, same five
#: tests plus the lander parity pair and a DDPG test, two workers, an empty cache, 2026-11-29): 193 s
#: instead of 236 s wall, every test faster, the run-bound parity tests too (67 s and 63 s against 77 s
#: and 81 s); the 2-D walker's step compiled in 41 s against 52-58 s alone and ran as fast (14 ms).
#: Results differ from the newer emitters' in the last float bits (a sum of 30.79 over the walker's
#: observations by 2e-6).
#: Since 2026-11-29 the level is 0 (same machine, two workers, an empty cache, one run each): the whole
#: suite took 927 s against 1,152 s at level 1, the sum of its test times 1,791 s against 2,244 s. Two
#: kinds of test compile at level 1 instead (marked ``optimized``, tests/conftest.py): those whose
#: programs run long (level 0 ran them up to 4x slower: 200 QRs 15 -> 56 s, a DDPG bandit 13 -> 33 s),
#: and those that compare two different programs bit for bit: level 0 failed six of them (last-bit
#: differences, 2e-10 to 6e-6 relative; the lander's 1,000-step episodes drifted by 2e-5). One of the
#: six, whose programs come from a module-scoped fixture, compares within 1e-5 instead.
#: Not used by the CLI: LLVM's options may also reach GPU code generation (not checked), and long CPU runs
#: would pay at run time.
TEST_FLAGS = ("--xla_llvm_disable_expensive_passes=true", "--xla_backend_optimization_level=0",
              "--xla_cpu_use_fusion_emitters=false")


def apply_cpu_guard(extra: tuple[str, ...] = ()) -> None:
    """Add each of ``FLAGS`` (then those of ``extra`` this jaxlib knows, :func:`xla_knows`) to ``XLA_FLAGS``
    unless the user already set that option either way.

    Call it before the first JAX computation; once the backend exists it has no effect.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    known = xla_knows([flag[2:].split("=")[0] for flag in extra])
    for flag in (*FLAGS, *(f for f, k in zip(extra, known) if k)):
        option = flag[2:].split("=")[0]
        if option not in flags:
            flags = f"{flags} {flag}".strip()
    os.environ["XLA_FLAGS"] = flags


def with_flag(flags: str, flag: str) -> str:
    """``flags`` (an ``XLA_FLAGS`` string) with ``flag`` (``--option=value``) in place of any setting of its
    option: for a child process or a test that needs one option changed and the rest kept."""
    option = flag.split("=")[0]
    kept = [f for f in flags.split() if f.split("=")[0] != option]
    return " ".join([*kept, flag])


def xla_knows(options: list[str]) -> list[bool]:
    """Whether the installed jaxlib's XLA names each flag ``option`` (its shared library holds the name).

    An unknown flag in ``XLA_FLAGS`` aborts the process when the backend starts, so the tuning flags of
    ``extra`` (which a newer jaxlib may drop) are passed only when named; looking does not import jaxlib
    and takes about 0.2 s (a 334 MB library, from the page cache). False for all when the library is not
    where jaxlib 0.10-0.11 keep it.
    """
    import importlib.util
    import pathlib

    if not options:
        return []
    spec = importlib.util.find_spec("jaxlib")
    if spec is None or not spec.origin:
        return [False] * len(options)
    return names_in_libraries(sorted(pathlib.Path(spec.origin).parent.glob("libjax_common*.so*")), options)


def names_in_libraries(paths, names: list[str]) -> list[bool]:
    """Whether any of the shared libraries ``paths`` holds each of ``names`` as bytes (memory-mapped,
    nothing loaded); unreadable paths are skipped."""
    import mmap

    found = [False] * len(names)
    for lib in paths:
        try:
            with open(lib, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                found = [k or m.find(o.encode()) >= 0 for k, o in zip(found, names)]
        except (OSError, ValueError):
            continue
    return found
