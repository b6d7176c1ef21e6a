"""Reproduce (or rule out) the XLA:CPU batched-LAPACK deadlock of shed_jax/xla_cpu.py.

Each try runs a fresh process that initialises 16 vmapped cartpole students ``--calls`` times in a
loop, with XLA's CPU pool set to ``--nproc`` threads, and reports whether it finished within
``--timeout`` seconds. ``--init library`` swaps the student's orthogonal initializer back to
``jax.nn.initializers.orthogonal`` (a LAPACK QR on a CPU); ``--init ours`` keeps
shed_jax/student/orthogonal.py.

    python -m experiments.cpu_deadlock --init library --nproc 2 --tries 3   # hung 3 of 3 here
    python -m experiments.cpu_deadlock --init ours --nproc 2 --tries 3      # finished 3 of 3
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time


def child_source(init: str, calls: int) -> str:
    """The program one try runs; it prints ``finished`` at the end."""
    if init not in ("ours", "library"):
        raise ValueError(f"--init must be 'ours' or 'library', got {init!r}")
    swap = ["import shed_jax.student.networks as networks",
            "networks.orthogonal = jax.nn.initializers.orthogonal"] if init == "library" else []
    return "\n".join(["import jax", *swap,
                      "import envs",
                      "from shed_jax.student import PPOConfig, make_student",
                      'student = make_student(envs.make("cartpole"), PPOConfig.for_env("cartpole"))',
                      "init = jax.jit(jax.vmap(student.init))",
                      f"for i in range({int(calls)}):",
                      "    jax.block_until_ready(init(jax.random.split(jax.random.PRNGKey(i), 16)))",
                      'print("finished")', ""])


def run_try(init: str, nproc: int, calls: int, timeout: float) -> tuple[bool, float]:
    """(finished, seconds) of one try in a fresh process."""
    env = dict(os.environ, NPROC=str(nproc), JAX_PLATFORMS="cpu")
    t0 = time.perf_counter()
    try:
        out = subprocess.run([sys.executable, "-c", child_source(init, calls)], env=env, capture_output=True,
                             text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return False, time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(f"the try failed (exit {out.returncode}):\n{out.stderr[-2000:]}")
    return out.stdout.strip().endswith("finished"), time.perf_counter() - t0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--init", choices=("ours", "library"), default="ours")
    p.add_argument("--nproc", type=int, default=2, help="XLA:CPU intra-op pool threads (NPROC)")
    p.add_argument("--tries", type=int, default=3)
    p.add_argument("--calls", type=int, default=1000)
    p.add_argument("--timeout", type=float, default=60.0, help="seconds before a try counts as hung")
    a = p.parse_args(argv)
    if min(a.nproc, a.tries, a.calls) < 1 or a.timeout <= 0:
        p.error("--nproc, --tries and --calls must be >= 1 and --timeout > 0")
    done = 0
    for t in range(a.tries):
        ok, secs = run_try(a.init, a.nproc, a.calls, a.timeout)
        done += ok
        print(f"try {t + 1}: {'finished' if ok else 'HUNG'} after {secs:.1f} s", flush=True)
    print(f"init={a.init} NPROC={a.nproc} calls={a.calls}: finished {done} of {a.tries}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
