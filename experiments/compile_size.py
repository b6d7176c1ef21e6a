"""How big and how slow to compile a run's two programs are: ``init`` and one budget step.

    python -m experiments.compile_size [--env bipedal] [--method dr] [--preset paper] [--label after]
                                       [--out docs/results/bipedal_compile_cpu_2026-11-28.json]

Builds the batch as ``shed_jax run`` does (one seed: vmapping over seeds leaves the program's size
alone), then lowers and compiles, for the backend JAX runs on, the vmapped ``init`` and one budget
step (``run(state, 1, 0)``). Nothing is run. It prints and records the seconds to lower (trace to
StableHLO) and to compile, and the StableHLO's size in characters: every call site of an
environment's ``reset`` or ``step`` puts another copy of it into the program (on the 2-D walker a
physics step is 1.6-2.1 MB of StableHLO). ``run``'s own chunks start at a traced step and scan several
steps; here the start step is a constant, so XLA may fold the budget step's episode-start and test
branches: the compile seconds can be lower than a run's, the StableHLO is the same step's.

The record (``--out``, merged by ``--label``: one entry per label, e.g. ``before`` and ``after`` a
change) holds the device, date, command, commit and the measurements.
"""
from __future__ import annotations

import argparse
import sys
import time


def measure(batch) -> dict:
    """Lower and compile the batch's vmapped ``init`` and one budget step -> seconds and StableHLO sizes."""
    import jax

    from shed_jax import driver

    inputs = driver.batch_inputs(batch)
    init = jax.jit(jax.vmap(driver.batch_init(batch.init, batch.method)))
    out = {}
    t = time.perf_counter()
    lowered = init.lower(*inputs)
    out["init_lower_s"] = round(time.perf_counter() - t, 1)
    out["init_stablehlo_chars"] = len(lowered.as_text())
    t = time.perf_counter()
    lowered.compile()
    out["init_compile_s"] = round(time.perf_counter() - t, 1)
    state = jax.eval_shape(init, *inputs)
    chunk = jax.jit(jax.vmap(lambda s: batch.run(s, 1, 0)))
    t = time.perf_counter()
    lowered = chunk.lower(state)
    out["chunk_lower_s"] = round(time.perf_counter() - t, 1)
    out["chunk_stablehlo_chars"] = len(lowered.as_text())
    t = time.perf_counter()
    lowered.compile()
    out["chunk_compile_s"] = round(time.perf_counter() - t, 1)
    return out


def main(argv=None) -> int:
    from experiments import checkpoint_size as cs

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env", default="bipedal")
    ap.add_argument("--method", default="dr")
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--label", default="after", help="key of this measurement in the record")
    ap.add_argument("--out", default=None, help="JSON record to merge this measurement into")
    args = ap.parse_args(argv)
    header = cs.record_header("experiments.compile_size", argv)  # the commit of the sources about to load
    try:
        _, batch = cs.build_batch(args.env, args.method, args.preset, 1)
    except ValueError as err:
        print(f"compile_size: {err}", file=sys.stderr)
        return 2
    sizes = measure(batch)
    print(" ".join(f"{k}={v}" for k, v in sizes.items()))
    record = {
        **header,
        "experiment": {"env": args.env, "method": args.method, "preset": args.preset, "seeds": 1},
        **sizes,
    }
    if args.out:
        cs.merge_labelled(args.out, args.label, record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
