"""How long XLA takes to compile the 2-D walker's GPU programs, measured on a CPU host with no GPU.

A new 2-D walker program costs minutes of a device call before it runs a step, most of it in the
Triton compile of the fused solver loops (``envs.physics2d.fused``). XLA compiles for a GPU it does
not have from a description of the target (``targets/h200.txtpb``: an H200's multiprocessors,
memory, clock and compute capability), so changes to those loops can be weighed here: compile
seconds, and ptxas' registers and spills for every Pallas kernel (XLA logs them; spills inside a
loop cost time on the GPU, which only the GPU measures). The device host's own compile was about
twice as slow per thread as this 2-core AMD EPYC's (2026-12-04); these figures are the CPU host's.

Needs a Python with the GPU host's jax, jaxlib and CUDA plugin (its set-up: docs/running.md,
"Compiling for the GPU on a CPU host"); no cache is read or written, so every figure is a cold
compile:

    PY -m experiments.gpu_compile loops --out FILE.json       # each fused loop of one step, alone
    PY -m experiments.gpu_compile loops --velocity-manifolds 6 --out FILE.json  # with 6 packed slots
    PY -m experiments.gpu_compile loops --lanes --out FILE.json  # and three of the loops in lanes
    PY -m experiments.gpu_compile run "RUN FLAGS" --out FILE.json  # a run's initial state and first chunk
    PY -m experiments.gpu_compile run "RUN FLAGS" --launches 3 --out FILE.json  # and its launches per budget step
    PY -m experiments.gpu_compile update --env bipedal --out FILE.json  # launches of one PPO update
    PY -m experiments.gpu_compile launches [--variant V] --out FILE.json  # kernel launches per step
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import sys
import tempfile
import time

TARGETS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "targets")
# XLA prints ptxas' report of each kernel at these log settings (set before jax is imported)
_LOG = {"TF_CPP_MIN_LOG_LEVEL": "0", "TF_CPP_VMODULE": "subprocess_compilation=2"}


def _device(target: str):
    from jax.experimental import topologies

    path = os.path.join(TARGETS, f"{target}.txtpb")
    if not os.path.exists(path):
        have = sorted(f[:-6] for f in os.listdir(TARGETS) if f.endswith(".txtpb"))
        raise SystemExit(f"gpu_compile: no target {target!r}; have {', '.join(have)}")
    with open(path) as f:
        return topologies.get_topology_desc(platform="cuda", target_config=f.read(), topology="1x1x1").devices[0]


def ptxas_report(text: str) -> list[dict]:
    """Per Pallas kernel in XLA's log (ptxas' entries ``kernel``, ``kernel__1``, ...: XLA numbers a
    program's Triton kernels): registers, spill bytes, stack frame."""
    out = []
    for m in re.finditer(r"Compiling entry function '(kernel(?:__\d+)?)'.*?(\d+) bytes stack frame, (\d+) bytes "
                         r"spill stores, (\d+) bytes spill loads.*?Used (\d+) registers", text, re.S):
        frame, stores, loads, regs = (int(g) for g in m.groups()[1:])
        out.append({"kernel": m.group(1), "registers": regs, "spill_stores": stores, "spill_loads": loads,
                    "stack_frame": frame})
    return out


@contextlib.contextmanager
def _stderr_to(path: str):
    """The process's file descriptor 2 (XLA's C++ log) into ``path`` for the block."""
    sys.stderr.flush()
    saved = os.dup(2)
    with open(path, "w") as f:
        os.dup2(f.fileno(), 2)
    try:
        yield
    finally:
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)


def _compile(label: str, lower, launches_depth: int = 0, per: int = 1) -> dict:
    """Lower (timed), then compile (timed) with XLA's log captured for ptxas' kernel reports; with
    ``launches_depth``, also the program's kernel launches (``experiments.hlo_launches``) per ``per``
    (a chunk's budget steps), overall and per JAX scope to that depth."""
    t = time.time()
    lowered = lower()
    lower_s = time.time() - t
    with tempfile.NamedTemporaryFile(suffix=".log") as log:
        t = time.time()
        with _stderr_to(log.name):
            compiled = lowered.compile()
        compile_s = time.time() - t
        with open(log.name) as f:
            kernels = ptxas_report(f.read())
    row = {"program": label, "lower_s": round(lower_s, 1), "compile_s": round(compile_s, 1), "kernels": kernels}
    if launches_depth:
        from experiments import hlo_launches

        text = compiled.as_text()
        c = hlo_launches.count(text)
        row["launches"] = {"per": per, "total": round(c["total"] / per, 1),
                           # loops whose trip count is data-dependent (an evaluation's early stop) count one trip
                           "unknown_trips": len(c["unknown_trips"]),
                           "by_scope": {k: round(v / per, 1) for k, v in sorted(
                               hlo_launches.by_scope(text, launches_depth).items(), key=lambda kv: -kv[1])}}
    print(json.dumps({k: v for k, v in row.items() if k != "launches"}), flush=True)
    return row


def loops(device, worlds: int, lanes: bool = False, **options) -> list[dict]:
    """Each fused loop of one 2-D walker step (``env.step_without_reset``; ``options``: the env's), vmapped
    over ``worlds`` worlds, as the Pallas kernel the GPU runs (inputs abstract: nothing is computed);
    ``lanes``: the velocity, position and time-of-impact velocity loops in lane form too
    (``solver_kernel_bench.lanes_program``)."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import SingleDeviceSharding

    from experiments import solver_kernel_bench as skb

    env, inputs = skb._env_and_inputs(worlds, 2, concrete=False, **options)
    leaf = jax.ShapeDtypeStruct((worlds,), jnp.float32, sharding=SingleDeviceSharding(device))
    rows = []
    for name, (n, body, ctree, stree, done) in skb._structures(env, inputs).items():
        consts = jax.tree_util.tree_unflatten(ctree, [leaf] * ctree.num_leaves)
        carry = jax.tree_util.tree_unflatten(stree, [leaf] * stree.num_leaves)
        with jax.default_device(device):
            row = _compile(name, lambda: skb.loop_program(n, body, done, "pallas").trace(consts, carry).lower())
        rows.append(dict(row, iterations=n, consts=ctree.num_leaves, carry=stree.num_leaves))
        if lanes and name in (skb.LOOPS[0], skb.LOOPS[1], skb.LOOPS[3]):  # in lane form too (velocity_lanes, position_lanes)
            with jax.default_device(device):
                row = _compile(name + "/lanes", lambda: skb.lanes_program(n, body, done, "pallas").trace(consts, carry).lower())
            rows.append(dict(row, iterations=n, consts=ctree.num_leaves, carry=stree.num_leaves))
    return rows


def launches(device, variant: str, batch: int, steps: int, depth: int, hlo: str | None = None,
             step: str = "step") -> list[dict]:
    """The kernel launches per step of ``steps`` sequential steps of ``batch`` walkers with random
    actions (``bench_latency.random_action_scan``, the program ``profile_bipedal_step --step step``
    traces on a GPU; its reset amortized over the steps), counted in the optimized HLO
    (``experiments.hlo_launches``), overall, per opcode and per JAX scope to ``depth``; ``hlo``: a
    file to keep the optimized HLO in (gzipped), to count it again another way; ``step``: ``"step"``
    (``env.step``, its auto-reset included) or ``"without-reset"`` (``env.step_without_reset``, as a
    teacher's evaluation steps)."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import SingleDeviceSharding

    from experiments import aot_cache, hlo_launches
    from experiments.bench_latency import random_action_scan
    from experiments.profile_bipedal_step import make_env

    env = make_env(variant)
    run = random_action_scan(env, batch, steps, env.step_without_reset if step == "without-reset" else None)
    key = jax.ShapeDtypeStruct((2,), jnp.uint32, sharding=SingleDeviceSharding(device))
    with aot_cache._as_gpu_host(device):
        t = time.time()
        lowered = run.trace(key).lower()
        lower_s = time.time() - t
        t = time.time()
        text = lowered.compile().as_text()
        compile_s = time.time() - t
    if hlo:
        import gzip

        with gzip.open(hlo, "wt") as f:
            f.write(text)
    c = hlo_launches.count(text)
    per = lambda d: {k: round(v / steps, 2) for k, v in d.items()}  # noqa: E731
    row = {"program": f"{batch} walkers x {steps} steps ({variant}, {step})", "lower_s": round(lower_s, 1),
           "compile_s": round(compile_s, 1), "launches_per_step": round(c["total"] / steps, 2),
           "by_op": per(c["by_op"]), "by_scope": per(hlo_launches.by_scope(text, depth)),
           "unknown_trips": len(c["unknown_trips"])}
    print(json.dumps({k: row[k] for k in ("program", "compile_s", "launches_per_step")}), flush=True)
    return [row]


def update_launches(device, env_name: str, seeds: int, depth: int, rollout: bool = False) -> list[dict]:
    """Kernel launches of one PPO update (``epochs x minibatches`` SGD steps) of ``seeds`` vmapped
    students of ``env_name``'s paper preset, on a trajectory of the rollout's shapes, compiled for the
    GPU: the part of a budget step that compiles no environment step; with ``rollout``, then the
    launches of one rollout of those students (minutes: it compiles the environment's step)."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import SingleDeviceSharding

    from experiments import aot_cache, hlo_launches
    from shed_jax.experiment import build
    from shed_jax.presets import build_experiment

    _, student, _, _ = build(build_experiment(env_name, "hmdp", "paper"))
    env = student.env
    on = lambda tree: jax.tree.map(  # noqa: E731
        lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=SingleDeviceSharding(device)), tree)
    keys = jax.ShapeDtypeStruct((seeds, 2), jnp.uint32)
    levels = env.param_space.sample(jax.random.PRNGKey(1), (4,))
    with aot_cache._as_gpu_host(device):
        state = jax.eval_shape(jax.vmap(lambda k: student.assign_levels(student.init(k), k, levels)), keys)
        traj = jax.eval_shape(jax.vmap(student.rollout), state, keys)[1]

    def counted(what: str, fn, args, unit: str, per: int) -> dict:
        """``fn`` vmapped, compiled for the GPU on ``args`` (abstract), and its launches counted."""
        with aot_cache._as_gpu_host(device):
            t = time.time()
            text = jax.jit(jax.vmap(fn)).trace(*map(on, args)).lower().compile().as_text()
            compile_s = time.time() - t
        c = hlo_launches.count(text)
        row = {"program": f"{what} of {seeds} students ({env_name}, paper preset)", "compile_s": round(compile_s, 1),
               f"{unit}s": per, "launches": c["total"], f"launches_per_{unit}": round(c["total"] / per, 2),
               "unknown_trips": len(c["unknown_trips"]), "by_op": c["by_op"], "by_scope": hlo_launches.by_scope(text, depth)}
        print(json.dumps({k: row[k] for k in ("program", "compile_s", "launches", f"launches_per_{unit}")}), flush=True)
        return row

    cfg = student.config
    rows = [counted("PPO update", student.update, (state, keys, traj), "sgd_step", cfg.update_epochs * cfg.num_minibatches)]
    if rollout:
        rows.append(counted("rollout", student.rollout, (state, keys), "step", cfg.num_steps))
    return rows


def run_programs(device, flags: str, launches_depth: int = 0) -> list[dict]:
    """A run's initial state and its first chunk, as ``shed_jax run FLAGS`` builds them for the GPU;
    with ``launches_depth``, the chunk's kernel launches per budget step by scope."""
    from experiments import aot_cache
    from shed_jax import driver, runtime

    runtime.call_site_free_locations()  # as ``python -m shed_jax`` starts (kernel IR holds locations)

    with tempfile.NamedTemporaryFile("w", suffix=".args") as f:
        f.write(flags)
        f.flush()
        init, ins, run_chunk, sizes, state = aot_cache.build(f.name, device)
    rows = []
    with aot_cache._as_gpu_host(device):
        rows.append(_compile("jit_init_point", lambda: init.trace(*ins).lower()))
        rows.append(_compile(f"chunk of {sizes[0]}", lambda: driver.lower_from_clean_caches(run_chunk, state, sizes[0], 0),
                             launches_depth, sizes[0]))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    lp = sub.add_parser("loops", help="each fused loop of a 2-D walker step, alone")
    lp.add_argument("--worlds", type=int, default=1024, help="worlds per loop (default: the kernels' least padding)")
    lp.add_argument("--velocity-manifolds", type=int, default=0,
                    help="the env's velocity_manifolds: manifold slots of the velocity passes (0: all 12)")
    lp.add_argument("--lanes", "--velocity-lanes", dest="lanes", action="store_true",
                    help="also the velocity, position and time-of-impact velocity loops in lane form (4 threads per world: "
                         "SolverConfig.velocity_lanes, position_lanes)")
    cp = sub.add_parser("launches", help="kernel launches per 2-D walker step (optimized HLO), by op and scope")
    cp.add_argument("--variant", default="default",
                    help="an env variant of experiments.profile_bipedal_step (default, packed_6, no_toi, ...)")
    cp.add_argument("--batch", type=int, default=200, help="walkers (default 200)")
    cp.add_argument("--steps", type=int, default=200, help="sequential steps in the program (default 200)")
    cp.add_argument("--depth", type=int, default=2, help="scope levels to group launches by (default 2)")
    cp.add_argument("--hlo", default=None, help="also write the optimized HLO text here (gzipped)")
    cp.add_argument("--step", default="step", choices=["step", "without-reset"],
                    help="env.step (with its auto-reset, default) or env.step_without_reset (as evaluations step)")
    up = sub.add_parser("update", help="kernel launches of one PPO update of a walker paper preset's students")
    up.add_argument("--env", default="bipedal", choices=("bipedal", "walker"), help="the environment (default bipedal)")
    up.add_argument("--seeds", type=int, default=5, help="vmapped students (default 5)")
    up.add_argument("--depth", type=int, default=3, help="scope levels to group launches by (default 3)")
    up.add_argument("--rollout", action="store_true", help="also count one rollout's launches (compiles the env step)")
    rp = sub.add_parser("run", help="a run's initial state and first chunk")
    rp.add_argument("flags", help="shed_jax run's flags, one string, e.g. \"--env bipedal --method dr --preset dcd\"")
    rp.add_argument("--launches", type=int, default=0, metavar="DEPTH",
                    help="also count the chunk's kernel launches per budget step, by JAX scope to DEPTH levels")
    for p in (lp, cp, up, rp):
        p.add_argument("--target", default="h200", help="a GPU description in experiments/targets (default h200)")
        p.add_argument("--tile", type=int, default=None,
                       help="per-world fields per kernel memory access (default: envs.physics2d.fused.TILE)")
        p.add_argument("--out", required=True, help="JSON record to write")
    a = ap.parse_args(argv)
    if a.tile is not None and (a.tile < 1 or a.tile & (a.tile - 1)):
        ap.error(f"--tile must be a power of two (1, 2, 4, ...), got {a.tile}")
    from shed_jax.xla_gpu import apply_gpu_codegen

    apply_gpu_codegen()  # the GPU code a run compiles (shed_jax/xla_gpu.py)
    for k, v in _LOG.items():
        os.environ.setdefault(k, v)
    os.environ["JAX_ENABLE_COMPILATION_CACHE"] = "false"  # cold compiles only
    os.environ.setdefault("JAX_PLATFORMS", "cpu")  # the CUDA plugin then loads for compiling only
    import jax

    from envs.physics2d import fused
    from experiments.aot_cache import _cpu_model
    from shed_jax.runtime import provenance

    try:
        device = _device(a.target)
    except NotImplementedError:  # jax without its CUDA plugin
        raise SystemExit(f"gpu_compile: jax {jax.__version__} here has no CUDA plugin to compile with; use a Python "
                         "with jax[cuda13] (docs/running.md, 'Compiling for the GPU on a CPU host')") from None
    if a.tile is not None:
        fused.TILE = a.tile
    t = time.time()
    if a.cmd == "loops":
        try:
            rows = loops(device, a.worlds, lanes=a.lanes, velocity_manifolds=a.velocity_manifolds)
        except ValueError as e:  # the env's own check of the option, one line
            raise SystemExit(f"gpu_compile: {e}") from None
    elif a.cmd == "launches":
        from experiments.profile_bipedal_step import VARIANTS

        if a.variant not in VARIANTS:
            ap.error(f"--variant must be one of {', '.join(VARIANTS)}, got {a.variant!r}")
        if min(a.batch, a.steps, a.depth) < 1:
            ap.error("--batch, --steps and --depth must be at least 1")
        rows = launches(device, a.variant, a.batch, a.steps, a.depth, a.hlo, a.step)
    elif a.cmd == "update":
        if min(a.seeds, a.depth) < 1:
            ap.error("--seeds and --depth must be at least 1")
        rows = update_launches(device, a.env, a.seeds, a.depth, a.rollout)
    else:
        if a.launches < 0:
            ap.error(f"--launches must be a depth of at least 1 (0: no count), got {a.launches}")
        rows = run_programs(device, a.flags, a.launches)
    record = {**provenance("experiments.gpu_compile", argv), "jax": jax.__version__,
              "device": f"{_cpu_model()} ({os.cpu_count()} CPUs), compiling for {device.device_kind} (deviceless)",
              "kernel_tile": fused.TILE, "total_s": round(time.time() - t, 1), "programs": rows}
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(record, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
