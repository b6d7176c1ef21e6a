"""Walker env throughput on the device JAX sees, with Brax walker2d (MJX) as the anchor.

For every combination of the option grid and every batch size: steps/s of ``jit(scan(vmap(step)))``
with random actions and auto-reset on FULL-range random levels, the cost of one batched reset
(the base class evaluates it at every step), and peak device memory. Results go to
``<out>/bench_walker.json``.

    python -m experiments.bench_walker --out runs/bench --batch-sizes 1024,4096,8192,16384,32768 \
        --substeps 4,5 --iterations 1,4 --resolution 2,4 --upper-legs 0,1 --unroll 0,1
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import pathlib
import time


def _ints(s):
    return [int(v) for v in s.split(",") if v]


def _bools(s):
    return [bool(int(v)) for v in s.split(",") if v]


def parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT", "runs/bench_walker"))
    ap.add_argument("--batch-sizes", type=_ints, default=[1024, 4096, 8192, 16384, 32768])
    ap.add_argument("--steps", type=int, default=100, help="env steps per timed scan")
    ap.add_argument("--repeats", type=int, default=2, help="timed scans after the warm-up")
    ap.add_argument("--substeps", type=_ints, default=[5])
    ap.add_argument("--iterations", type=_ints, default=[4])
    ap.add_argument("--ls-iterations", type=_ints, default=[5])
    ap.add_argument("--resolution", type=_ints, default=[4])
    ap.add_argument("--upper-legs", type=_bools, default=[False])
    ap.add_argument("--unroll", type=_bools, default=[False])
    ap.add_argument("--precision", type=lambda s: s.split(","), default=["highest"],
                    help="comma-separated WalkerOptions.matmul_precision values (highest | high | default)")
    ap.add_argument("--no-brax", action="store_true", help="skip the Brax walker2d anchor")
    ap.add_argument("--brax-substeps", type=int, default=4, help="Brax walker2d n_frames (4 = its default)")
    ap.add_argument("--wall-check", action="store_true", help="only run the heightfield face-as-wall check (MuJoCo C)")
    return ap.parse_args(argv)


def _peak_mem():
    import jax

    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def _time_scan(run, state, key, repeats):
    import jax

    t0 = time.perf_counter()
    state, r = run(state, key)
    jax.block_until_ready(r)
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for i in range(repeats):
        t0 = time.perf_counter()
        state, r = run(state, jax.random.fold_in(key, i + 1))
        jax.block_until_ready(r)
        best = min(best, time.perf_counter() - t0)
    return compile_s, best


def bench_walker(opts: dict, batch: int, steps: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    from envs.walker import BipedalWalker
    from envs.walker.levels import sample_full

    env = BipedalWalker(**opts)
    key = jax.random.PRNGKey(0)
    levels = sample_full(key, (batch,))
    levels = levels.replace(fixed_terrain=jnp.zeros((batch,), bool))
    reset = jax.jit(jax.vmap(env.reset))
    obs, state = reset(jax.random.split(key, batch), levels)
    vstep = jax.vmap(env.step)

    @jax.jit
    def run(state, key):
        def body(s, k):
            ka, ks = jax.random.split(k)
            a = jax.random.uniform(ka, (batch, 4), minval=-1.0, maxval=1.0)
            o, s, r, d, info = vstep(jax.random.split(ks, batch), s, a, levels)
            return s, (r.sum(), d.sum())
        s, (r, d) = jax.lax.scan(body, state, jax.random.split(key, steps))
        return s, (r.sum(), d.sum())

    compile_s, best = _time_scan(run, state, key, repeats)
    # Reset alone (what auto-reset adds to every step under vmap).
    keys = jax.random.split(jax.random.PRNGKey(1), batch)
    jax.block_until_ready(reset(keys, levels))
    t0 = time.perf_counter()
    for _ in range(3):
        out = reset(keys, levels)
    jax.block_until_ready(out)
    reset_s = (time.perf_counter() - t0) / 3
    step_s = best / steps
    return dict(kind="walker", options=opts, batch=batch, steps_per_s=batch * steps / best, compile_s=compile_s,
                step_ms=1e3 * step_s, reset_ms=1e3 * reset_s, reset_fraction=reset_s / step_s, peak_bytes=_peak_mem())


def bench_brax(batch: int, steps: int, repeats: int, n_frames: int) -> dict:
    import jax
    from brax import envs as benvs
    from brax.envs.wrappers import training

    env = training.wrap(benvs.get_environment("walker2d", backend="mjx", n_frames=n_frames), episode_length=1000)
    state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))

    @jax.jit
    def run(state, key):
        def body(s, k):
            a = jax.random.uniform(k, (batch, env.action_size), minval=-1.0, maxval=1.0)
            s = env.step(s, a)
            return s, s.reward.sum()
        s, r = jax.lax.scan(body, state, jax.random.split(key, steps))
        return s, r.sum()

    compile_s, best = _time_scan(run, state, jax.random.PRNGKey(1), repeats)
    return dict(kind="brax_walker2d", batch=batch, n_frames=n_frames, steps_per_s=batch * steps / best, compile_s=compile_s,
                peak_bytes=_peak_mem())


def wall_check(resolution: int, step_height: float, force: float = 40.0, seconds: float = 2.0) -> dict:
    """Does a one-cell heightfield face act as a wall? (MuJoCo C, which matches MJX at 4 solver
    iterations.) A vertical lower-leg capsule (mass 1, slide x/z, leg-ground friction) is pushed
    horizontally with ``force`` N into an obstacle ``step_height`` TERRAIN_STEPs high; returns how
    far it got past the face and how high it climbed."""
    import math

    import mujoco
    import numpy as np

    from envs.walker import constants as C
    from envs.walker.model import LOWER_R
    from envs.walker.terrain import make_grid

    g = make_grid(resolution)
    half = (g.n - 1) * g.dx / 2
    f = math.sqrt(C.LEG_FRICTION * C.TERRAIN_FRICTION)
    face = 6.0
    xml = f"""<mujoco><option timestep="0.004" gravity="0 0 -10" iterations="4" ls_iterations="5" solver="Newton" cone="pyramidal"/>
      <asset><hfield name="t" nrow="2" ncol="{g.n}" size="{half} 0.5 10 1"/></asset>
      <worldbody><geom name="t" type="hfield" hfield="t" pos="{g.x_min + half} 0 0" contype="0" conaffinity="0"/>
        <body name="foot" pos="0 0 0"><joint name="x" type="slide" axis="1 0 0"/><joint name="z" type="slide" axis="0 0 1"/>
          <geom name="foot" type="capsule" fromto="0 0 {LOWER_R} 0 0 {C.LEG_H - LOWER_R}" size="{LOWER_R}" mass="1" contype="0" conaffinity="0"/></body>
      </worldbody><contact><pair geom1="t" geom2="foot" condim="3" friction="{f} {f} 0.005 0.0001 0.0001"/></contact></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    gx = g.x_min + g.dx * np.arange(g.n)
    h = np.where(gx >= face - 1e-4, step_height * C.TERRAIN_STEP, 0.0)
    m.hfield_data[:] = np.concatenate([h, h]) / 10.0
    d = mujoco.MjData(m)
    d.qpos[:] = [face - 1.0, 0.002]
    zmax, xmax = 0.0, -np.inf
    for _ in range(int(seconds / 0.004)):
        d.qfrc_applied[0] = force
        mujoco.mj_step(m, d)
        zmax, xmax = max(zmax, d.qpos[1]), max(xmax, d.qpos[0] + LOWER_R)
    return dict(resolution=resolution, step_height=step_height, force=force, past_face_m=float(xmax - face), climbed_m=float(zmax))


def main(argv=None) -> int:
    args = parse(argv)
    import jax

    if args.wall_check:
        rows = [wall_check(r, h) for r in (1, 2, 4, 8) for h in (0.25, 0.5, 1.0, 2.0)]
        for r in rows:
            print(json.dumps(r))
        out = pathlib.Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "wall_check.json").write_text(json.dumps(rows, indent=1))
        return 0

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    grid = [
        dict(substeps=s, solver_iterations=i, ls_iterations=ls, terrain_resolution=r, collide_upper_legs=u, unroll_substeps=un,
             matmul_precision=pr)
        for s, i, ls, r, u, un, pr in itertools.product(
            args.substeps, args.iterations, args.ls_iterations, args.resolution, args.upper_legs, args.unroll, args.precision
        )
    ]
    results = dict(device=str(jax.devices()[0]), backend=jax.default_backend(), jax=jax.__version__, steps=args.steps, runs=[])
    path = out / "bench_walker.json"

    def record(r):
        results["runs"].append(r)
        print(json.dumps(r), flush=True)
        path.write_text(json.dumps(results, indent=1))

    for batch in args.batch_sizes:
        if not args.no_brax:
            try:
                record(bench_brax(batch, args.steps, args.repeats, args.brax_substeps))
            except Exception as e:  # the anchor must not stop the walker runs
                record(dict(kind="brax_walker2d", batch=batch, error=repr(e)))
        for opts in grid:
            try:
                record(bench_walker(opts, batch, args.steps, args.repeats))
            except Exception as e:  # e.g. out of memory at the largest batch
                record(dict(kind="walker", options=opts, batch=batch, error=repr(e)))
    walker = [r for r in results["runs"] if r["kind"] == "walker" and "steps_per_s" in r]
    brax = {r["batch"]: r["steps_per_s"] for r in results["runs"] if r["kind"] == "brax_walker2d" and "steps_per_s" in r}
    if walker:
        best = max(walker, key=lambda r: r["steps_per_s"])
        results["best"] = dict(steps_per_s=best["steps_per_s"], batch=best["batch"], options=best["options"])
        results["ratio_to_brax"] = [
            dict(batch=r["batch"], options=r["options"], ratio=r["steps_per_s"] / brax[r["batch"]]) for r in walker if r["batch"] in brax
        ]
    path.write_text(json.dumps(results, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
