"""Where one step of the 2-D walker (``envs.make("bipedal")``) spends its time on a GPU.

For each solver variant: milliseconds per sequential ``vmap(step_without_reset)`` (random actions,
a ``lax.scan`` of ``--steps``) at each batch; then, with ``--trace``, a ``jax.profiler`` trace of the first
variant's scans, summarised per kernel (launches and device time per step, the HLO op that launched it; with
``XLA_FLAGS=--xla_dump_to=...`` the optimised HLO maps those ops to the named scopes of
``physics2d.step``'s phases) and as the share of the wall time the device is busy. The raw trace is not kept (too large to come back from a device).

``--step`` picks what is timed: ``step_without_reset`` (default), ``step`` (with its auto-reset) or
``reset`` (``env.reset`` alone, a new terrain and push each time).

Variants change only the solver's configuration (the same env otherwise):
``default`` (Box2D's passes), ``passes_1_1`` (1 velocity / 1 position pass), ``toi_unrolled``
(the time-of-impact passes unrolled instead of looped), ``no_toi`` (no time of impact: not the walker,
its cost only), ``xla`` (no Pallas kernel), ``no_skip`` (the kernels compute every contact
point and time of impact, also in blocks of worlds none of which needs it), ``no_early_stop`` (all
of Box2D's position passes in every block, solved or not: the solver before 2026-12-02), ``full_reset`` (the
env's ``light_reset=False``: the reset's physics step with its edge manifolds), ``profile_obstacles``
(the env's ``obstacles="profile"``: obstacles as the height profile's edges, the model before Box2D
polygons), ``terrain_loop`` (the env's ``terrain_kernel="xla"``: the terrain's 200-column loop as an
XLA loop, the generator before 2026-12-02), ``packed_6`` / ``packed_4`` (the velocity passes over the
manifolds with points packed into 6 or 4 slots instead of all 12, ``SolverConfig.velocity_manifolds``),
``toi_gated`` (``SolverConfig.toi_gate``: the time of impact's solve skipped in batch-steps where no
walker has an impact candidate; random actions give one in every batch-step of 200, so its gain is
for rollouts of a walking policy, experiments/toi_census.py).

    python -m experiments.profile_bipedal_step --batches 200 --variants default,passes_1_1 --out $OUT/profile.json
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import glob
import json
import os
import tempfile
import time

import jax
import jax.numpy as jnp

VARIANTS = {
    "default": {},
    "passes_1_1": {"velocity_iterations": 1, "position_iterations": 1},
    "toi_unrolled": {"toi_loop": False},
    "no_toi": {"continuous": False},
    "xla": {"kernel": "xla"},
    "no_skip": {"skip_untouched": False},
    "no_early_stop": {"position_early_stop": False},
    "full_reset": {},  # env options below: the reset's physics step with its edge manifolds
    "profile_obstacles": {},  # the height profile's edges at obstacles instead of Box2D polygons
    "terrain_loop": {},  # the terrain generator as an XLA loop instead of one kernel
    "packed_6": {"velocity_manifolds": 6},  # the velocity passes over 6 packed manifold slots, not 12
    "packed_4": {"velocity_manifolds": 4},
    "lanes": {"velocity_lanes": True},  # each leg's manifolds in a lane of the velocity loop: 4 threads per world
    "position_lanes": {"position_lanes": True},  # ... and of the position loop
    "lanes_both": {"velocity_lanes": True, "position_lanes": True},
    "toi_gated": {"toi_gate": True},  # the time of impact's solve only in batch-steps where some walker needs it
}
ENV_OPTIONS = {"full_reset": {"light_reset": False}, "profile_obstacles": {"obstacles": "profile"},
               "terrain_loop": {"terrain_kernel": "xla"}}


def make_env(variant: str, **options):
    import envs

    env = envs.make("bipedal", **{**ENV_OPTIONS.get(variant, {}), **options})
    cfg = dataclasses.replace(env.model.config, **VARIANTS[variant])
    env.model = dataclasses.replace(env.model, config=cfg)
    return env


def reset_scan(env, batch: int, steps: int):
    """A jitted ``run(key)``: ``steps`` sequential ``vmap(env.reset)`` of ``batch`` envs on sampled levels,
    each with new keys (a new terrain and push); their observations and poses are summed, so XLA keeps them."""
    levels = env.param_space.sample(jax.random.PRNGKey(1), (batch,))

    @jax.jit
    def run(key):
        def body(total, k):
            obs, state = jax.vmap(env.reset)(jax.random.split(k, batch), levels)
            return total + obs.sum() + state.world.bodies.com.sum(), None

        total, _ = jax.lax.scan(body, jnp.float32(0.0), jax.random.split(key, steps))
        return total

    return run


def heuristic_scan(env, batch: int, steps: int, step_fn):
    """As ``bench_latency.random_action_scan``, but Gymnasium's scripted gait (``envs.bipedal.heuristic``)
    on the flat level (its own terrain seed per env): a walking batch, where most worlds' position passes
    are solved in a few passes, instead of random actions, where many never are."""
    from envs.bipedal.heuristic import heuristic, heuristic_init
    from envs.walker import levels as LV

    flat = LV.LEVELS["BipedalWalker"](terrain_seed=0)
    levels = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch,) + jnp.shape(x)), flat)
    levels = levels.replace(terrain_seed=jnp.arange(batch, dtype=jnp.int32))

    @jax.jit
    def run(key):
        obs, state = jax.vmap(env.reset)(jax.random.split(key, batch), levels)
        h = jax.vmap(lambda _: heuristic_init())(jnp.arange(batch))

        def body(c, k):
            obs, state, h = c
            a, h = jax.vmap(heuristic)(h, obs)
            obs, state, r, d, _ = jax.vmap(step_fn)(jax.random.split(k, batch), state, a, levels)
            h = jax.tree_util.tree_map(lambda x, y: jnp.where(d, x, y), jax.vmap(lambda _: heuristic_init())(h.phase), h)
            return (obs, state, h), r.sum()

        _, r = jax.lax.scan(body, (obs, state, h), jax.random.split(key, steps))
        return r.sum()

    return run


def terrain_check(n: int) -> dict:
    """The env's terrain (its ``terrain_kernel``, one kernel on a GPU) against the XLA loop's on ``n``
    sampled levels (a fifth of them Gymnasium's Hardcore), new terrains: worlds whose column kinds, box
    count or box slots differ, and the largest coordinate difference."""
    import numpy as np

    import envs

    env, loop = envs.make("bipedal"), envs.make("bipedal", terrain_kernel="xla")
    levels = env.param_space.sample(jax.random.PRNGKey(2), (n,))
    levels = levels.replace(fixed_terrain=jnp.zeros((n,), bool), gym_hardcore=jnp.arange(n) % 5 == 0)
    keys = jax.random.split(jax.random.PRNGKey(3), n)
    a, b = (jax.tree_util.tree_map(np.asarray, jax.jit(jax.vmap(e.terrain))(keys, levels)) for e in (env, loop))
    exact = ((a.kinds == b.kinds).all(1) & (a.n_boxes == b.n_boxes) & (a.box_valid == b.box_valid).all(1))
    return {"worlds": n, "terrain_kernel": env.options.terrain_kernel, "worlds_differing": int((~exact).sum()),
            "max_abs_diff": {f: float(np.abs(getattr(a, f) - getattr(b, f)).max()) for f in ("x", "y", "boxes")}}


def time_scan(run, repeats: int = 3) -> tuple[float, float]:
    t = time.perf_counter()
    lowered = run.lower(jax.random.PRNGKey(0))
    lower_s = time.perf_counter() - t
    lowered.compile()
    print(json.dumps({"lower_s": round(lower_s, 1), "xla_compile_s": round(time.perf_counter() - t - lower_s, 1)}),
          flush=True)
    jax.block_until_ready(run(jax.random.PRNGKey(0)))
    compile_s = time.perf_counter() - t
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(run(jax.random.PRNGKey(0)))
        best = min(best, time.perf_counter() - t)
    return compile_s, best


def summarise_trace(path: str, steps: int, wall_s: float) -> dict:
    """Kernel launches and device time per step from an xplane file: per kernel (its name, the HLO
    op or command buffer that launched it, launch details) and the device's busy share."""
    from jax.profiler import ProfileData

    pd = ProfileData.from_file(path)
    by_kernel = {}
    spans, memcpy = [], collections.Counter()
    for plane in pd.planes:
        if not plane.name.startswith("/device:GPU"):
            continue
        for line in plane.lines:
            if not line.name.startswith("Stream"):
                continue
            for ev in line.events:
                stats = dict(ev.stats)
                name = ev.name
                if "memcpy" in name.lower() or "memset" in name.lower():
                    memcpy[name.split(" ")[0]] += 1
                rec = by_kernel.setdefault(name, {"n": 0, "t": 0.0, "hlo_op": str(stats.get("hlo_op", "")),
                                                  "details": str(stats.get("kernel_details", ""))[:300]})
                rec["n"] += 1
                rec["t"] += ev.duration_ns * 1e-9
                spans.append((ev.start_ns, ev.start_ns + ev.duration_ns))
    spans.sort()
    busy, end = 0.0, -1.0
    for s, e in spans:
        if e <= end:
            continue
        busy += e - max(s, end)
        end = e
    top = sorted(by_kernel.items(), key=lambda kv: -kv[1]["t"])[:80]
    return {
        "launches_per_step": len(spans) / steps,
        "device_busy_ms_per_step": busy * 1e-6 / steps,
        "wall_ms_per_step": 1e3 * wall_s / steps,
        "memcpy_per_step": {k: v / steps for k, v in memcpy.items()},
        "kernels": len(by_kernel),
        "top_kernels": [{"kernel": k[:200], "hlo_op": r["hlo_op"], "launches_per_step": r["n"] / steps,
                         "device_ms_per_step": 1e3 * r["t"] / steps, "details": r["details"]} for k, r in top],
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batches", default="200")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--variants", default="default")
    p.add_argument("--step", default="step_without_reset", choices=("step_without_reset", "step", "reset"),
                   help="what each scan iteration runs: a step without or with its auto-reset, or a reset alone")
    p.add_argument("--actions", default="random", choices=("random", "heuristic"),
                   help="random actions on sampled levels, or Gymnasium's scripted gait on the flat level")
    p.add_argument("--trace", action="store_true", help="trace the first variant's scans (jax.profiler)")
    p.add_argument("--terrain-check", type=int, default=0, metavar="N",
                   help="first compare the terrain kernel with the XLA loop on N sampled levels")
    p.add_argument("--out", default="runs/profile_bipedal_step.json")
    args = p.parse_args(argv)
    variants = args.variants.split(",")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        p.error(f"unknown variant(s) {unknown}; known: {sorted(VARIANTS)}")
    from experiments.bench_latency import random_action_scan
    from shed_jax.runtime import provenance

    rec = {**provenance("experiments.profile_bipedal_step", argv), "step": args.step, "actions": args.actions, "rows": []}

    def write():
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(rec, f, indent=1)

    rec["traces"] = []
    if args.terrain_check:
        rec["terrain_check"] = terrain_check(args.terrain_check)
        print(json.dumps(rec["terrain_check"]), flush=True)
        write()
    for i, v in enumerate(variants):
        env = make_env(v)
        for b in (int(x) for x in args.batches.split(",")):
            scan = heuristic_scan if args.actions == "heuristic" else random_action_scan
            run = (reset_scan(env, b, args.steps) if args.step == "reset"
                   else scan(env, b, args.steps, getattr(env, args.step)))
            compile_s, best = time_scan(run)
            row = {"variant": v, "batch": b, "steps": args.steps, "compile_s": round(compile_s, 1),
                   "ms_per_step": 1e3 * best / args.steps, "steps_per_second": b * args.steps / best}
            rec["rows"].append(row)
            print(json.dumps(row), flush=True)
            if i == 0 and args.trace:  # the first variant's program, traced once more
                with tempfile.TemporaryDirectory() as d:
                    t = time.perf_counter()
                    with jax.profiler.trace(d):
                        jax.block_until_ready(run(jax.random.PRNGKey(0)))
                    wall = time.perf_counter() - t
                    files = glob.glob(os.path.join(d, "**", "*.xplane.pb"), recursive=True)
                    tr = {"variant": v, "batch": b, "steps": args.steps, **summarise_trace(files[0], args.steps, wall)}
                rec["traces"].append(tr)
                print(json.dumps({k: tr[k] for k in ("batch", "launches_per_step", "device_busy_ms_per_step",
                                                     "wall_ms_per_step", "kernels")}), flush=True)
            write()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
