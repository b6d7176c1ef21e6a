"""A guard against an XLA:CPU hang, applied before JAX initialises its CPU backend.

XLA:CPU's multi-threaded Eigen pool can wedge while a vmapped program runs: the host then waits in
``BlockUntilReady`` forever. It was seen here in a vmapped run of the UED loop (tests/test_loop.py,
2026-11-22, and in a CLI run in an earlier session). The same stack and the same remedy were reported in
PyAutoLabs/PyAutoFit#1528/#1530: ``--xla_cpu_multi_thread_eigen=false`` (12 runs, no hang, against
14 hangs in 16 runs). Our CPU programs are small, so Eigen's threads buy little; GPU runs are
unaffected (the flag only touches the CPU backend).

A second flag, ``--xla_cpu_use_xnnpack=false``, keeps XLA:CPU from handing dots to XNNPACK and its
own thread pool. With the Eigen flag alone, ``python -m shed_jax run --env lander --method shed
--preset quick`` (what ``make run ENV=lander`` runs on a CPU) hung in 4 of 4 tries on 2026-11-23 on
the 2-core machine, each after its compile, with its CPU time frozen and the main thread in
``BlockUntilReady``. One try had JAX's asynchronous CPU dispatch off as well, which did not help.
With this flag added it finished (1 of 1, and again in the check after this change). The evidence
is thin: a short 2-seed walker run without the flag finished in 3 of 5 tries that day (one of the
two hangs had asynchronous dispatch off), after hanging in every try the session before; with the
flag it finished in 1 of 1. It is not free: with it the test suite took 13 min 8 s on that
machine, against 10 min 14 s without it earlier that day (one run each; runs had varied by 2 min).
"""
from __future__ import annotations

import os

FLAG = "--xla_cpu_multi_thread_eigen=false"
FLAGS = (FLAG, "--xla_cpu_use_xnnpack=false")


def apply_cpu_guard() -> None:
    """Add each of ``FLAGS`` to ``XLA_FLAGS`` unless the user already set that option either way.

    Call it before the first JAX computation; once the backend exists it has no effect.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    for flag in FLAGS:
        option = flag[2:].split("=")[0]
        if option not in flags:
            flags = f"{flags} {flag}".strip()
    os.environ["XLA_FLAGS"] = flags
