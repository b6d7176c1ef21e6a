"""Does a run's chunk lower to the same program whatever the process traced before it?

    python -m experiments.lowering_determinism [--env bipedal] [--method accel] [--preset quick]
        [--out docs/results/lowering_determinism_2026-12-02.json]

The persistent compilation cache keys a program by its StableHLO with source locations stripped, but
the Triton IR that a Pallas kernel embeds keeps its locations, and a jitted helper traced earlier in
the process lends its cached locations to the kernels that call it later. A fresh run traces its
initial state before the chunk; a resumed run traces only a restore target. This script lowers one
seed's chunk, for CUDA (the kernels in Pallas mode; any host can do it, nothing is compiled):

* ``alone``: from empty tracing caches, as a resumed run's chunk;
* ``after_init``: after lowering the sharded initial state, as a fresh run did before 2026-12-02;
* ``helped``: after the initial state again, through ``driver.lower_from_clean_caches`` (what the
  driver does now).

and records whether ``after_init`` and ``helped`` equal ``alone`` (SHA-256 of the StableHLO text).
"""
from __future__ import annotations

import argparse
import hashlib
import time


def measure(env: str, method: str, preset: str) -> dict:
    import jax

    import envs.physics2d.fused as fused
    from experiments.kernel_census import cuda_chunk
    from shed_jax import driver

    with fused.auto_as("pallas"):  # the GPU's kernels, lowered anywhere
        run_chunk, target, init, inputs, _ = cuda_chunk(env, method, preset, 1)
        cuda = {"lowering_platforms": ("cuda",)}
        digest = lambda lowered: hashlib.sha256(lowered.as_text().encode()).hexdigest()  # noqa: E731
        t = time.perf_counter()
        alone = driver.lower_from_clean_caches(run_chunk, target, 1, 0, **cuda)
        kernels = alone.as_text().count("__gpu$xla.gpu.triton")
        jax.clear_caches()
        init.trace(*inputs).lower(**cuda)
        after_init = run_chunk.trace(target, 1, 0).lower(**cuda)
        init.trace(*inputs).lower(**cuda)
        helped = driver.lower_from_clean_caches(run_chunk, target, 1, 0, **cuda)
        seconds = round(time.perf_counter() - t, 1)
    return {"triton_kernels": kernels, "alone": digest(alone)[:16], "after_init": digest(after_init)[:16],
            "helped": digest(helped)[:16], "after_init_equal": digest(after_init) == digest(alone),
            "helped_equal": digest(helped) == digest(alone), "seconds": seconds}


def main(argv=None) -> int:
    from experiments import checkpoint_size as cs

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env", default="bipedal")
    ap.add_argument("--method", default="accel")
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--out", default=None, help="JSON record to merge this measurement into (label env/method/preset)")
    args = ap.parse_args(argv)
    out = measure(args.env, args.method, args.preset)
    print(" ".join(f"{k}={v}" for k, v in out.items()))
    if args.out:
        cs.merge_labelled(args.out, f"{args.env}/{args.method}/{args.preset}",
                          {**cs.record_header("experiments.lowering_determinism", argv), **out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
