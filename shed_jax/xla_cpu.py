"""Guards against an XLA:CPU deadlock, applied before JAX initialises its CPU backend.

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
(hung in every try before; with this guard a two-seed walker loop finishes). The ``make run
ENV=lander`` hangs of the same day were not caught with a native stack; they looked the same.

The remedy is more pool threads than a program has concurrent LAPACK calls. XLA sizes the pool
from the environment variable ``NPROC`` when it is set (``xla::DefaultThreadPoolSize``), so the
guard sets ``NPROC=max(64, cpu count)`` unless the user set it; ``import shed_jax`` does so too,
which protects library use as long as the import comes before JAX's first computation. Measured on the 2-core machine with
a vmapped init of eight orthogonal Dense layers (16 seeds) in a loop: the default pool of 2 hung in
5 of 5 tries within 300 calls and ``NPROC=4`` in 3 of 3; ``NPROC=8`` finished 3 of 3 tries of 500
calls and ``NPROC=16`` 6 of 6 tries of 1,000 calls. ``tests/test_xla_cpu.py`` keeps a small version
of that loop (with ``NPROC=2`` it hung in 3 of 3 tries). The idle threads cost nothing we could
measure: three test files took 24 s with ``NPROC=16``, 25 and 34 s with 64, and 28 s with the
default in the try that did not hang. A public report (PyAutoLabs' PyAutoHeart diagnostics, the
same stack with Cholesky) says jaxlib 0.11.2 no longer takes this parallel path in open-source
builds; the newest CPU wheel here is 0.10.2.

Two XLA flags are older guards, chosen before the cause was known:
``--xla_cpu_multi_thread_eigen=false`` (after PyAutoLabs/PyAutoFit#1528, whose hang looked the
same) and ``--xla_cpu_use_xnnpack=false`` (``make run ENV=lander`` on a CPU hung in 4 of 4 tries
without it, 0 of 1 with it). Neither touches the LAPACK path, which is why hangs went on. They stay
because the CPU runs behind this project's numbers used them; whether they still help is untested.
GPU runs are unaffected by all three settings, which touch only the CPU backend.
"""
from __future__ import annotations

import os

FLAG = "--xla_cpu_multi_thread_eigen=false"
FLAGS = (FLAG, "--xla_cpu_use_xnnpack=false")
MIN_POOL_THREADS = 64


def pool_threads() -> int:
    """The XLA:CPU intra-op pool size the guard asks for: ``max(64, cpu count)``."""
    return max(MIN_POOL_THREADS, os.cpu_count() or 1)


def size_cpu_pool() -> None:
    """Set ``NPROC`` to :func:`pool_threads` unless the user set it (``import shed_jax`` does this)."""
    os.environ.setdefault("NPROC", str(pool_threads()))


def apply_cpu_guard() -> None:
    """:func:`size_cpu_pool`, and add each of ``FLAGS`` to ``XLA_FLAGS`` unless the user set that
    option either way (the CLI and the tests do this).

    Call it before the first JAX computation; once the backend exists it has no effect.
    """
    size_cpu_pool()
    flags = os.environ.get("XLA_FLAGS", "")
    for flag in FLAGS:
        option = flag[2:].split("=")[0]
        if option not in flags:
            flags = f"{flags} {flag}".strip()
    os.environ["XLA_FLAGS"] = flags
