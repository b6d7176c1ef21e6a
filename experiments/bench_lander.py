"""Lander throughput: env steps/s of jit(vmap(step)) inside lax.scan (random actions, auto-reset
included) for several batch sizes on whatever device JAX sees, plus Gymnasium LunarLander-v3 on one
CPU core as the anchor.

    python -m experiments.bench_lander --batches 1024,16384,131072,1048576 --out $OUT
    python -m experiments.bench_lander --batches 131072 --kernel-shapes 128x4,256x8   # fused kernel launch shapes
Writes bench_lander.json into --out (or $OUT); prints a table.
"""
from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from envs.physics2d import fused


def jax_throughput(batch: int, steps: int, continuous: bool, repeats: int = 3, unroll: int = 1) -> dict:
    import envs

    env = envs.make("lander-continuous" if continuous else "lander", unroll=unroll)
    params = env.default_params
    levels = env.param_space.sample(jax.random.PRNGKey(1), (batch,))
    levels = levels.replace(enable_wind=jnp.arange(batch) % 2 == 0)
    space = env.action_space()

    @jax.jit
    def run(key, obs, state):
        def body(c, k):
            obs, state = c
            ka, ks = jax.random.split(k)
            a = jax.vmap(space.sample)(jax.random.split(ka, batch))
            obs, state, r, d, _ = jax.vmap(env.step)(jax.random.split(ks, batch), state, a, levels)
            return (obs, state), r.sum()

        (obs, state), r = jax.lax.scan(body, (obs, state), jax.random.split(key, steps))
        return obs, state, r.sum()

    obs, state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), batch), levels)
    t = time.perf_counter()
    out = run(jax.random.PRNGKey(2), obs, state)
    jax.block_until_ready(out)
    compile_s = time.perf_counter() - t
    times = []
    for i in range(repeats):
        t = time.perf_counter()
        out = run(jax.random.PRNGKey(3 + i), out[0], out[1])
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t)
    best = min(times)
    del params
    return dict(batch=batch, steps=steps, unroll=unroll, seconds=best, steps_per_s=batch * steps / best, compile_s=compile_s)


def gym_throughput(seconds: float = 5.0, wind: bool = False) -> float:
    import gymnasium as gym

    env = gym.make("LunarLander-v3", enable_wind=wind)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for a in rng.integers(0, 4, 1000):
            _, _, term, trunc, _ = env.step(int(a))
            n += 1
            if term or trunc:
                env.reset()
    return n / (time.perf_counter() - t0)


def peak_memory() -> dict:
    out = {}
    for d in jax.devices():
        try:
            stats = d.memory_stats() or {}
        except Exception:  # CPU backends may not implement it
            stats = {}
        if stats:
            out[str(d)] = {k: int(v) for k, v in stats.items() if k in ("peak_bytes_in_use", "bytes_limit")}
    return out


def _kernel_shape(text: str) -> tuple[int, int]:
    """``'256x8'`` -> (256, 8); the block must be a power of two of at least 32 threads' worth."""
    try:
        block, warps = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"--kernel-shapes: {text!r} is not BLOCKxWARPS, e.g. 128x4") from None
    if block < 1 or block & (block - 1) or warps < 1 or warps & (warps - 1):
        raise SystemExit(f"--kernel-shapes: {text!r} needs powers of two for BLOCK and WARPS")
    return block, warps


def main(argv=None) -> int:
    from shed_jax.xla_gpu import apply_gpu_codegen

    apply_gpu_codegen()  # as python -m shed_jax compiles (before the backend starts)
    p = argparse.ArgumentParser(description="lander env steps/s")
    p.add_argument("--batches", default="1024,16384,131072,1048576", help="comma-separated batch sizes")
    p.add_argument("--steps", type=int, default=100, help="scanned steps per timed call")
    p.add_argument("--continuous", action="store_true")
    p.add_argument("--gym-seconds", type=float, default=5.0)
    p.add_argument("--unroll", default="1", help="comma-separated solver-loop unroll factors to compare")
    p.add_argument("--kernel-shapes", default="",
                   help="comma-separated BLOCKxWARPS launch shapes of the fused solver kernel to compare, "
                        "e.g. 128x4,256x8 (default: the module's, envs.physics2d.fused.BLOCK/NUM_WARPS)")
    p.add_argument("--out", default=os.environ.get("OUT"))
    args = p.parse_args(argv)
    shapes = [_kernel_shape(s) for s in args.kernel_shapes.split(",") if s] or [(fused.BLOCK, fused.NUM_WARPS)]
    unrolls = [int(u) for u in args.unroll.split(",") if u]
    batches = [int(b) for b in args.batches.split(",") if b]
    if not batches or min(batches) < 1:
        raise SystemExit(f"--batches needs positive integers, got {args.batches!r}")
    try:
        gym_sps = gym_throughput(args.gym_seconds) if args.gym_seconds > 0 else float("nan")
    except Exception as err:  # e.g. gymnasium's box2d package without pygame on the GPU image
        print(f"gymnasium anchor unavailable: {type(err).__name__}: {err}")
        gym_sps = float("nan")
    rows = []
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}); gymnasium 1 core: {gym_sps:,.0f} steps/s")
    print(f"{'batch':>9} {'unroll':>6} {'kernel':>7} {'steps/s':>14} {'x gym':>9} {'compile s':>10}")
    default_shape = (fused.BLOCK, fused.NUM_WARPS)
    try:
        for block, warps in shapes:
            # read when the kernel is traced; each jax_throughput call builds and traces a fresh program
            fused.BLOCK, fused.NUM_WARPS = block, warps
            for u in unrolls:
                for b in batches:
                    r = jax_throughput(b, args.steps, args.continuous, unroll=u)
                    r["speedup_vs_gym_core"] = r["steps_per_s"] / gym_sps if gym_sps == gym_sps else None
                    r["kernel_block"], r["kernel_warps"] = block, warps
                    rows.append(r)
                    print(f"{b:9d} {u:6d} {block:>4}x{warps:<2} {r['steps_per_s']:14,.0f} "
                          f"{r['speedup_vs_gym_core'] or float('nan'):9.1f} {r['compile_s']:10.1f}", flush=True)
    finally:
        fused.BLOCK, fused.NUM_WARPS = default_shape
    from shed_jax.runtime import provenance

    # the record says where, when and from which sources it was measured, and with which XLA flags
    # (the GPU multiply-add flag changes the kernels); a missing anchor is null, not NaN (strict JSON)
    result = dict(**provenance("experiments.bench_lander", argv), xla_flags=os.environ.get("XLA_FLAGS", ""),
                  backend=jax.default_backend(), gym_steps_per_s=gym_sps if gym_sps == gym_sps else None,
                  continuous=args.continuous, rows=rows, memory=peak_memory())
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "bench_lander.json"), "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
