"""How many Triton kernels XLA compiles for one budget step of a run on a GPU, counted on any host.

    python -m experiments.kernel_census [--env bipedal] [--methods dr,shed] [--preset paper] [--seeds 5]
        [--out docs/results/bipedal_kernel_census.json]

Lowers a run's chunk for CUDA as ``shed_jax run`` builds it (all its seeds: a kernel's grid counts
the worlds of every seed), with ``physics2d.fused``'s ``"auto"`` loops as the GPU's Pallas kernels;
nothing is compiled. Each fused loop is one ``__gpu$xla.gpu.triton`` custom call in the program. XLA
compiles a call's Triton IR once per distinct backend configuration (IR, grid and warps) and reuses
the binary for identical calls, so the distinct configurations are the Triton compiles the program
pays: on the 2-D walker a large solver kernel alone compiles for minutes (docs/bipedal.md). The IR
holds the kernel's MLIR locations, so with JAX's default locations (whole call stacks) the same loop
called from two places is two kernels; ``shed_jax`` commands give locations the innermost user frame
only (``runtime.call_site_free_locations``), and ``--full-tracebacks`` counts the default. A run pads
its compiled kernels to its training batch (``runtime.pad_kernels_to``, at least
``fused.DEFAULT_MIN_WORLDS``), so its evaluations and its training rollout share one grid;
``--min-worlds 1024`` counts small batches padded only, ``--min-worlds 128`` whole blocks only.
Printed and recorded per method: calls, distinct kernels, and the distinct kernels by grid
(``grid_x``: blocks of 128 worlds).
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import re
import sys
import time

_CALL = "@__gpu$xla.gpu.triton("
_IR = re.compile(r'\bir = "((?:[^"\\]|\\.)*)"')
_FIELD = re.compile(r"\b(grid_x|grid_y|grid_z|num_warps|num_stages) = (\d+)")


def triton_calls(text: str) -> list[dict]:
    """Every Triton custom call in a lowered program's text: its grid, warps and the SHA-256 of its IR
    (with the name, the key XLA reuses a compiled kernel by)."""
    calls = []
    start = text.find(_CALL)
    while start >= 0:
        end = text.find("\n", start)
        op = text[start:end if end >= 0 else len(text)]  # one operation per line
        ir = _IR.search(op)
        rest = op[:ir.start()] + op[ir.end():] if ir else op  # the fields, not the IR's bytes
        name = re.search(r'\bname = "([^"]*)"', rest)
        calls.append({**{k: int(v) for k, v in _FIELD.findall(rest)}, "name": name.group(1) if name else "",
                      "ir_sha256": hashlib.sha256(ir.group(1).encode()).hexdigest()[:16] if ir else ""})
        start = text.find(_CALL, start + len(_CALL))
    return calls


def census(calls: list[dict]) -> dict:
    """Calls, distinct kernels (IR, name, grid, warps) and the distinct kernels per ``grid_x``."""
    distinct = {tuple(sorted(c.items())) for c in calls}
    by_grid: dict[int, int] = {}
    for key in distinct:
        g = dict(key).get("grid_x", 0)
        by_grid[g] = by_grid.get(g, 0) + 1
    return {"triton_calls": len(calls), "triton_kernels_distinct": len(distinct),
            "distinct_by_grid_x": {str(g): n for g, n in sorted(by_grid.items())}}


def cuda_chunk(env: str, method: str, preset: str, seeds: int):
    """A run's chunk of one budget step as the driver builds it, with its state target, ``init``,
    inputs (ShapeDtypeStructs) and the run's kernel padding (``driver.kernel_worlds``), for lowering
    with ``lowering_platforms=("cuda",)``. Call it inside ``fused.auto_as("pallas")`` to get the GPU's
    kernels."""
    import jax

    from experiments import checkpoint_size as cs
    from shed_jax import driver, sharding

    _, batch = cs.build_batch(env, method, preset, seeds)
    batch = dataclasses.replace(batch, chunk=1)
    placed = driver.place(batch, sharding.batch_mesh(jax.devices()[:1]))
    s = sharding.batch_sharding(placed.mesh)
    run_chunk = sharding.sharded_run(batch.run, placed.mesh)
    target = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s),
                          driver.state_target(batch, placed))
    init = sharding.sharded_init(driver.batch_init(batch.init, batch.method), placed.mesh)
    inputs = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), placed.inputs)
    return run_chunk, target, init, inputs, driver.kernel_worlds(batch, placed)


DEFAULT_FRAMES = 100  # JAX's own default jax_traceback_in_locations_limit (jax 0.10 and 0.11)


def measure(env: str, method: str, preset: str, seeds: int, full_tracebacks: bool = False,
            min_worlds: int | None = None) -> dict:
    """The census of one method's chunk, its MLIR locations as ``shed_jax`` commands make them
    (``runtime.call_site_free_locations``) or, with ``full_tracebacks``, with JAX's default call stacks;
    kernels padded to ``min_worlds`` worlds (default: as a run pads them, to its training batch and
    at least ``fused.DEFAULT_MIN_WORLDS``; ``fused.BLOCK``: whole blocks only)."""
    import jax

    import envs.physics2d.fused as fused
    from shed_jax import driver, runtime

    t = time.perf_counter()
    before, padding = jax.config.jax_include_full_tracebacks_in_locations, fused.MIN_WORLDS
    frames = jax.config.jax_traceback_in_locations_limit
    try:
        if full_tracebacks:
            jax.config.update("jax_include_full_tracebacks_in_locations", True)
            jax.config.update("jax_traceback_in_locations_limit", DEFAULT_FRAMES)
        else:
            runtime.call_site_free_locations()
        with fused.auto_as("pallas"):
            run_chunk, target, _, _, worlds = cuda_chunk(env, method, preset, seeds)
            if min_worlds is None:
                used = runtime.pad_kernels_to(worlds)
            else:  # exactly this padding, below the default too
                fused.MIN_WORLDS = used = min_worlds
            text = driver.lower_from_clean_caches(run_chunk, target, 1, 0, lowering_platforms=("cuda",)).as_text()
        full = runtime.call_stacks_in_locations()
    finally:  # the process's settings as they were
        jax.config.update("jax_include_full_tracebacks_in_locations", before)
        jax.config.update("jax_traceback_in_locations_limit", frames)
        fused.MIN_WORLDS = padding
    return {**census(triton_calls(text)), "full_tracebacks_in_locations": bool(full), "min_worlds": used,
            "lower_s": round(time.perf_counter() - t, 1)}


def main(argv=None) -> int:
    from experiments import checkpoint_size as cs

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env", default="bipedal")
    ap.add_argument("--methods", default="dr,shed", help="comma-separated UED methods")
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--full-tracebacks", action="store_true",
                    help="lower with JAX's default locations (whole call stacks), as runs did before 2026-12-04")
    ap.add_argument("--min-worlds", type=int, default=None,
                    help="pad compiled kernels to this many worlds (default: as a run does, to its training batch "
                         "and at least envs.physics2d.fused.DEFAULT_MIN_WORLDS; 1024: small batches only, as "
                         "from 2026-12-04 to 12-05; 128, one block, whole blocks only, as before)")
    ap.add_argument("--out", default=None, help="JSON record to merge each method into (label env/method/preset/seeds/min_worlds_N[/full_tracebacks])")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        print(f"kernel_census: --seeds must be at least 1, got {args.seeds}", file=sys.stderr)
        return 2
    if args.min_worlds is not None and args.min_worlds < 1:
        print(f"kernel_census: --min-worlds must be at least 1, got {args.min_worlds}", file=sys.stderr)
        return 2
    header = cs.record_header("experiments.kernel_census", argv)  # the commit of the sources about to load
    for method in [m for m in args.methods.split(",") if m]:
        try:
            out = measure(args.env, method, args.preset, args.seeds, args.full_tracebacks, args.min_worlds)
        except ValueError as err:
            print(f"kernel_census: {err}", file=sys.stderr)
            return 2
        print(f"{method}: " + " ".join(f"{k}={v}" for k, v in out.items()), flush=True)
        if args.out:
            label = (f"{args.env}/{method}/{args.preset}/{args.seeds}/min_worlds_{out['min_worlds']}"
                     + ("/full_tracebacks" if args.full_tracebacks else ""))
            cs.merge_labelled(args.out, label,
                              {**header,
                               "experiment": {"env": args.env, "method": method, "preset": args.preset,
                                              "seeds": args.seeds}, **out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
