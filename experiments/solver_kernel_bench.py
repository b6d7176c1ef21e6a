"""The 2-D walker's fused solver loops timed alone, on inputs captured from real steps.

A whole walker step compiles for ~5 minutes on a GPU; one ``fused.per_world_fori_loop`` compiles in
seconds, so kernel variants can be compared in one device call. Two stages:

    # CPU: play ``--steps`` random-action steps on sampled levels, then capture the inputs (consts and
    # carry) of every fused loop of one more step, for ``--batch`` worlds
    python -m experiments.solver_kernel_bench capture --batch 200 --steps 40 --out runs/kernel_inputs.npz
    # GPU: each loop (velocity, position, the time of impact's two) per variant, ms per call
    python -m experiments.solver_kernel_bench bench --inputs runs/kernel_inputs.npz --out $OUT/kernels.json

Variants: ``block=B`` worlds per kernel instance (B/32 warps), ``tile=T`` per-world fields per memory
access of the kernel's inputs and outputs (``fused.TILE``; 1 is one field per access, as before
2026-12-05 though in the (worlds, fields) layout; the compile time falls as T grows:
``experiments.gpu_compile``), ``lower2`` (the velocity / position
pass over the lower legs' first two manifolds only: what a block whose worlds touch nothing else
would need), ``libtrig`` (the kernels' sines and cosines from ``jnp.sin`` / ``jnp.cos``, the GPU's
library calls, instead of ``envs.physics2d.vec.sincos``), ``lanes`` (the velocity, position and time-of-impact
velocity loops: each leg's manifolds in a lane of their own, 4 threads per world;
``SolverConfig.velocity_lanes`` and ``position_lanes``). ``ms`` is the wall time of a call (with the stacking and slicing around the kernel);
``--trace`` adds the kernels' device time.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

LOOPS = ("_velocity_pass_edges", "_position_pass_edges", "_toi_position_pass_polygons", "_toi_velocity_pass_polygons")


def _name(body) -> str:
    return getattr(body, "func", body).__name__


@contextlib.contextmanager
def _patched(fn):
    from envs.physics2d import fused

    orig = fused.per_world_fori_loop
    fused.per_world_fori_loop = fn
    try:
        yield orig
    finally:
        fused.per_world_fori_loop = orig


@contextlib.contextmanager
def _library_trig():
    """Within the block, the solver's ``sincos`` is ``(jnp.sin, jnp.cos)`` (what it was before 2026-12-07)."""
    from envs.physics2d import toi, vec, world

    mods = (vec, world, toi)
    saved = [m.sincos for m in mods]
    for m in mods:
        m.sincos = lambda a: (jnp.sin(a), jnp.cos(a))
    try:
        yield
    finally:
        for m, f in zip(mods, saved):
            m.sincos = f


def _env_and_inputs(batch: int, steps: int, concrete: bool = True, **options):
    """The env (XLA solver; ``options``: more of its options) and one step's inputs: the states after
    ``steps`` random-action steps."""
    import envs
    from experiments.bench_latency import random_action_scan

    env = envs.make("bipedal", solver_kernel="xla", **options)
    levels = env.param_space.sample(jax.random.PRNGKey(1), (batch,))  # random_action_scan's levels
    play = random_action_scan(env, batch, steps, final_state=True)
    state = play(jax.random.PRNGKey(0)) if concrete else jax.eval_shape(play, jax.random.PRNGKey(0))
    space = env.action_space()
    keys = jax.random.split(jax.random.PRNGKey(2), batch)
    actions = jax.vmap(space.sample)(jax.random.split(jax.random.PRNGKey(3), batch))
    return env, (keys, state, actions, levels)


def _structures(env, inputs):
    """Trace one vmapped step: per loop, (n, body, consts treedef, carry treedef, its early stop or None)."""
    found = {}

    def record(n, body, consts, carry, *, mode="auto", unroll=1, done=None, lanes=1):
        found.setdefault(_name(body), (n, body, jax.tree_util.tree_structure(consts),
                                       jax.tree_util.tree_structure(carry), done))
        return orig(n, body, consts, carry, mode="xla", unroll=unroll, done=done, lanes=lanes)

    with _patched(record) as orig:
        jax.eval_shape(jax.vmap(env.step_without_reset), *inputs)
    return found


def loop_program(n: int, body, done, mode: str):
    """One fused loop alone, vmapped over worlds and jitted: ``(consts, carry) -> carry`` (per-world
    leaves (W,)), as ``mode`` runs it ("pallas", "interpret" or "xla")."""
    from envs.physics2d import fused

    return jax.jit(jax.vmap(lambda c, s: fused.per_world_fori_loop(n, body, c, s, mode=mode, done=done)))


def lanes_program(n: int, body, done, mode: str):
    """The velocity loop ``body`` (``_velocity_pass_edges``, ``world.to_lanes``), the position loop
    (``_position_pass_edges``, ``world.to_position_lanes``) or the time of impact's velocity loop
    (``_toi_velocity_pass_polygons``, manifolds alone) in lane form (each leg's manifolds in a lane
    of their own, 4 threads per world in the kernel), vmapped and jitted, taking and returning the
    loop's own (consts, carry) form."""
    from envs.physics2d import world

    layout = world.lane_layout(body.args[1])
    if layout is None:
        raise ValueError(f"no lane layout for manifolds of bodies {body.args[1]}")

    def run(c, s):
        if _name(body) == LOOPS[1]:
            return world.position_passes_in_lanes(body.args[0], layout, n, c, s, mode=mode, done=done)
        return world.velocity_passes_in_lanes(body.args[0], layout, body.args[2], n, c, s, mode=mode,
                                              joints=_name(body) != LOOPS[3])

    return jax.jit(jax.vmap(run))


def capture(batch: int, steps: int, out: str) -> None:
    env, inputs = _env_and_inputs(batch, steps)
    got = {}

    def record(n, body, consts, carry, *, mode="auto", unroll=1, done=None, lanes=1):
        name = _name(body)
        leaves = jax.tree_util.tree_leaves((consts, carry))
        got.setdefault(name, leaves)
        return orig(n, body, consts, carry, mode="xla", unroll=unroll, done=done, lanes=lanes)

    # vmap a function that returns the loops' inputs: run the step, then read them back
    def inputs_of(*a):
        got.clear()
        env.step_without_reset(*a)
        return {k: v for k, v in got.items()}

    with _patched(record) as orig:
        leaves = jax.jit(jax.vmap(inputs_of))(*inputs)
    arrays = {f"{k}/{i}": np.asarray(x, np.float32) for k, v in leaves.items() for i, x in enumerate(v)}
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    np.savez_compressed(out, batch=batch, steps=steps, **arrays)
    print(json.dumps({"out": out, "loops": {k: len(v) for k, v in leaves.items()}}))


def _lower2(body, consts, carry, keep=(0, 1, 9, 10)):
    """The velocity or position pass restricted to manifolds ``keep`` (indices into the manifold list)."""
    pts = [k for p in keep for k in (2 * p, 2 * p + 1)]
    f = body.func
    args = list(body.args)
    # args: (model, body[, friction]); body / friction are per-point tuples
    args[1] = tuple(args[1][k] for k in pts)
    if len(args) > 2:
        args[2] = tuple(args[2][k] for k in pts)
    new_body = functools.partial(f, *args)
    per_point = {"on", "any", "fb", "a", "nrm", "pt", "n", "t", "arm", "nm", "tm"}
    per_manifold = {"blk", "k11", "k12", "k22", "inv"}
    c = dict(consts)
    for k in list(c):
        if k in per_point and len(c[k]) == len(body.args[1]):
            c[k] = tuple(c[k][i] for i in pts)
        elif k in per_manifold:
            c[k] = tuple(c[k][p] for p in keep)
    if f.__name__ == "_velocity_pass_edges":
        vel, omg, jimp, jmot, ln, lt = carry
        carry = (vel, omg, jimp, jmot, tuple(ln[i] for i in pts), tuple(lt[i] for i in pts))
    return new_body, c, carry


def _kernel_ms(fn, args, calls: int = 10) -> dict:
    """Device time per call of the Pallas kernel(s) in ``fn`` (a jax.profiler trace), and of all kernels."""
    import glob
    import tempfile

    from experiments.profile_bipedal_step import summarise_trace

    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d):
            for _ in range(calls):
                jax.block_until_ready(fn(*args))
        path = glob.glob(os.path.join(d, "**", "*.xplane.pb"), recursive=True)[0]
        s = summarise_trace(path, calls, 0.0)
    solver = sum(k["device_ms_per_step"] for k in s["top_kernels"] if k["kernel"].startswith("kernel"))
    return {"kernel_ms": solver, "all_kernels_ms": s["device_busy_ms_per_step"],
            "launches_per_call": s["launches_per_step"]}


def bench(inputs: str, variants: list[str], repeats: int, out: str, mode: str = "pallas",
          trace: bool = False, loops=LOOPS) -> dict:
    from envs.physics2d import fused
    from shed_jax.runtime import provenance

    tile = fused.TILE
    data = np.load(inputs)
    batch, steps = int(data["batch"]), int(data["steps"])
    env, ins = _env_and_inputs(batch, 1, concrete=False)  # only the loops' structures
    structs = _structures(env, ins)
    rec = {**provenance("experiments.solver_kernel_bench", None), "inputs": inputs, "batch": batch,
           "captured_after_steps": steps, "xla_flags": os.environ.get("XLA_FLAGS", ""), "rows": []}
    for name in loops:
        n, body, c_tree, s_tree, done = structs[name]
        leaves = [jnp.asarray(data[f"{name}/{i}"]) for i in range(c_tree.num_leaves + s_tree.num_leaves)]
        consts = jax.tree_util.tree_unflatten(c_tree, leaves[:c_tree.num_leaves])
        carry = jax.tree_util.tree_unflatten(s_tree, leaves[c_tree.num_leaves:])
        ref = None
        for v in variants:
            opts = dict(x.split("=") if "=" in x else (x, "1") for x in v.split("+")) if v != "default" else {}
            b, c, s = body, consts, carry
            if "lower2" in opts:
                if name not in LOOPS[:2]:
                    continue
                b, c, s = _lower2(body, consts, carry)
            if "lanes" in opts and name == LOOPS[2]:
                continue
            fused.BLOCK = int(opts.get("block", 128))
            fused.NUM_WARPS = max(1, fused.BLOCK // 32)
            fused.TILE = int(opts.get("tile", tile))
            fn = lanes_program(n, b, done, mode) if "lanes" in opts else loop_program(n, b, done, mode)
            t = time.perf_counter()
            try:
                with _library_trig() if "libtrig" in opts else contextlib.nullcontext():
                    res = jax.block_until_ready(fn(c, s))  # traced and compiled here
            except Exception as e:  # noqa: BLE001 - a variant that does not compile is a result
                rec["rows"].append({"loop": name, "variant": v, "error": str(e)[:400]})
                print(json.dumps(rec["rows"][-1]), flush=True)
                continue
            compile_s = time.perf_counter() - t
            best = float("inf")
            for _ in range(repeats):
                t = time.perf_counter()
                jax.block_until_ready(fn(c, s))
                best = min(best, time.perf_counter() - t)
            row = {"loop": name, "variant": v, "passes": n, "ms": 1e3 * best, "us_per_pass": 1e6 * best / n,
                   "compile_s": round(compile_s, 2)}
            if trace:
                row.update(_kernel_ms(fn, (c, s)))
            if "lower2" not in opts:
                flat = np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(res)])
                if ref is None:
                    xla = loop_program(n, body, done, "xla")(consts, carry)
                    ref = np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(xla)])
                row["max_abs_diff_vs_xla"] = float(np.max(np.abs(flat - ref)))
            rec["rows"].append(row)
            print(json.dumps(row), flush=True)
            with open(out, "w") as f:
                json.dump(rec, f, indent=1)
    fused.BLOCK, fused.NUM_WARPS, fused.TILE = 128, 4, tile
    return rec


def main(argv=None) -> int:
    from shed_jax.xla_gpu import apply_gpu_codegen

    apply_gpu_codegen()  # as python -m shed_jax compiles (before the backend starts)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("capture")
    c.add_argument("--batch", type=int, default=200)
    c.add_argument("--steps", type=int, default=40)
    c.add_argument("--out", default="runs/kernel_inputs.npz")
    b = sub.add_parser("bench")
    b.add_argument("--inputs", default="runs/kernel_inputs.npz")
    b.add_argument("--variants", default="default,tile=1,tile=32")
    b.add_argument("--repeats", type=int, default=20)
    b.add_argument("--out", default="runs/solver_kernel_bench.json")
    b.add_argument("--trace", action="store_true", help="also the kernels' device time (jax.profiler)")
    b.add_argument("--loops", default=",".join(LOOPS))
    b.add_argument("--mode", default="pallas", choices=("pallas", "interpret"), help="interpret: a CPU smoke test")
    args = p.parse_args(argv)
    if args.cmd == "capture":
        capture(args.batch, args.steps, args.out)
    else:
        bench(args.inputs, args.variants.split(","), args.repeats, args.out, args.mode, args.trace,
              args.loops.split(","))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
