"""A guard against an XLA:CPU hang, applied before JAX initialises its CPU backend.

XLA:CPU's multi-threaded Eigen pool can wedge while a vmapped program runs: the host then waits in
``BlockUntilReady`` forever. It was seen here in a vmapped run of the UED loop (tests/test_loop.py,
2026-11-22, and in a CLI run in an earlier session). The same stack and the same remedy were reported in
PyAutoLabs/PyAutoFit#1528/#1530: ``--xla_cpu_multi_thread_eigen=false`` (12 runs, no hang, against
14 hangs in 16 runs). Our CPU programs are small, so Eigen's threads buy little; GPU runs are
unaffected (the flag only touches the CPU backend).
"""
from __future__ import annotations

import os

FLAG = "--xla_cpu_multi_thread_eigen=false"


def single_thread_eigen() -> None:
    """Add ``FLAG`` to ``XLA_FLAGS`` unless the user already set that option either way.

    Call it before the first JAX computation; once the backend exists it has no effect.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
