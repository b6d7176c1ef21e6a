"""Where a lander step's time goes at a large batch, and whether TF32 touches its results.

Times, at one batch size (best of 3 after compile, ``lax.scan`` of ``--steps`` steps, levels over
the whole parameter space, wind on in half the envs), each part of ``env.step`` on its own:

* ``step``: the full ``env.step`` (random actions, auto-reset included), as ``bench_lander`` does;
* ``step_env``: the physics step and rules without the auto-reset;
* ``reset_env``: only the reset (terrain, creation, the no-op physics step);
* ``solver_1_1``: the full step with 1 velocity and 1 position iteration instead of 60 / 20, which
  leaves the work outside the solver loops.

``--trace`` also records one ``step`` call with ``jax.profiler`` and sums the device time per
kernel from its Perfetto trace (the ``kernels`` list of ``profile_lander.json``, top kernels first).

``--tf32-check`` runs ``experiments.tf32_check`` on the lander: the same rollout at JAX's default
float32 matmul precision (TF32 on recent NVIDIA GPUs) and at ``highest``; bitwise equal means no
matrix product in the step is rounded to TF32.

    python -m experiments.profile_lander --batch 131072 --trace --tf32-check --out $OUT
"""
from __future__ import annotations

import argparse
import glob
import gzip
import json
import os
import shutil
from collections import defaultdict

import jax
import jax.numpy as jnp

from experiments.bench_latency import _timed  # compile, then the best of 3 timed calls


def _levels(env, batch):
    levels = env.param_space.sample(jax.random.PRNGKey(1), (batch,))
    return levels.replace(enable_wind=jnp.arange(batch) % 2 == 0)


def make_variant(env, name: str, batch: int, steps: int):
    """A jitted ``fn(key, obs, state) -> (obs, state, total)`` that scans ``steps`` calls of one part."""
    levels = _levels(env, batch)
    space = env.action_space()

    def actions(k):
        return jax.vmap(space.sample)(jax.random.split(k, batch))

    if name in ("step", "solver_1_1"):
        def one(k, obs, state):
            ka, ks = jax.random.split(k)
            obs, state, r, _, _ = jax.vmap(env.step)(jax.random.split(ks, batch), state, actions(ka), levels)
            return obs, state, r.sum()
    elif name == "step_env":
        def one(k, obs, state):
            ka, ks = jax.random.split(k)
            obs, state, r, _, _ = jax.vmap(env.step_env)(jax.random.split(ks, batch), state, actions(ka), levels)
            return obs, state, r.sum()
    elif name == "reset_env":
        def one(k, obs, state):
            obs, state = jax.vmap(env.reset_env)(jax.random.split(k, batch), levels)
            return obs, state, obs.sum()
    else:
        raise ValueError(f"unknown variant {name!r}")

    @jax.jit
    def run(key, obs, state):
        def body(c, k):
            obs, state, r = one(k, *c)
            return (obs, state), r

        (obs, state), r = jax.lax.scan(body, (obs, state), jax.random.split(key, steps))
        return obs, state, r.sum()

    return run, levels


def time_variant(name: str, batch: int, steps: int, continuous: bool) -> dict:
    import envs

    kwargs = dict(velocity_iterations=1, position_iterations=1) if name == "solver_1_1" else {}
    env = envs.make("lander-continuous" if continuous else "lander", **kwargs)
    run, levels = make_variant(env, name, batch, steps)
    obs, state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), batch), levels)
    compile_s, best = _timed(run, jax.random.PRNGKey(2), obs, state)
    return dict(variant=name, batch=batch, steps=steps, compile_s=compile_s, seconds=best,
                ms_per_step=1e3 * best / steps, calls_per_s=batch * steps / best)


def kernel_summary(trace_dir: str, top: int = 40) -> list[dict]:
    """Device time per kernel name from the Perfetto trace ``jax.profiler`` wrote under ``trace_dir``."""
    files = glob.glob(os.path.join(trace_dir, "**", "perfetto_trace.json.gz"), recursive=True)
    if not files:
        return []
    with gzip.open(files[0], "rt") as f:
        trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    names = {e["pid"]: e.get("args", {}).get("name", "") for e in events
             if e.get("ph") == "M" and e.get("name") == "process_name"}
    gpu = {pid for pid, n in names.items() if "GPU" in n or "gpu" in n}
    total, count = defaultdict(float), defaultdict(int)
    for e in events:
        if e.get("ph") == "X" and (not gpu or e.get("pid") in gpu):
            total[e["name"]] += float(e.get("dur", 0.0))
            count[e["name"]] += 1
    rows = sorted(total, key=total.get, reverse=True)[:top]
    return [dict(name=n, total_us=round(total[n], 1), count=count[n]) for n in rows]


def traced_step(batch: int, steps: int, continuous: bool, trace_dir: str) -> list[dict]:
    import envs

    env = envs.make("lander-continuous" if continuous else "lander")
    run, levels = make_variant(env, "step", batch, steps)
    obs, state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), batch), levels)
    jax.block_until_ready(run(jax.random.PRNGKey(2), obs, state))
    with jax.profiler.trace(trace_dir, create_perfetto_trace=True):
        jax.block_until_ready(run(jax.random.PRNGKey(3), obs, state))
    rows = kernel_summary(trace_dir)
    shutil.rmtree(trace_dir, ignore_errors=True)  # tens of MB; the summary is what is kept
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="lander step time by part")
    p.add_argument("--batch", type=int, default=131072)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--variants", default="step,step_env,reset_env,solver_1_1")
    p.add_argument("--continuous", action="store_true")
    p.add_argument("--trace", action="store_true", help="also write kernels.json from a profiler trace")
    p.add_argument("--tf32-check", action="store_true")
    p.add_argument("--out", default=os.environ.get("OUT", "."))
    a = p.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    result = dict(device=str(jax.devices()[0]), jax=jax.__version__, variants=[])
    for name in [v for v in a.variants.split(",") if v]:
        row = time_variant(name, a.batch, a.steps, a.continuous)
        result["variants"].append(row)
        print(f"{name:>11}: {row['ms_per_step']:.3f} ms per step at batch {a.batch} "
              f"({row['calls_per_s'] / 1e6:.1f}M per s, compile {row['compile_s']:.1f} s)", flush=True)
    if a.tf32_check:
        from experiments import tf32_check

        env_name = "lander-continuous" if a.continuous else "lander"
        result["tf32"] = tf32_check.check(env_name, min(a.batch, 4096), 200)
        print("tf32 check:", result["tf32"], flush=True)
    if a.trace:
        result["kernels"] = traced_step(a.batch, a.steps, a.continuous, os.path.join(a.out, "trace"))
        for row in result["kernels"][:25]:
            print(f"{row['total_us'] / 1e3:9.2f} ms  x{row['count']:<5d} {row['name'][:100]}")
    with open(os.path.join(a.out, "profile_lander.json"), "w") as f:
        json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
