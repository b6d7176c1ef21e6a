"""One 2-D walker step with each leg's manifolds in a lane of their own (``--variant``, a
``profile_bipedal_step`` variant: ``lanes``, ``SolverConfig.velocity_lanes``, the velocity loop;
``position_lanes``, the position loop; ``lanes_both``) against the default sequential passes, from the states of random-action roll-outs:
the largest difference of every float output, and whether every other output is equal. CPU or GPU
(``--kernel``: the solver loops' mode, ``xla`` by default, so that a CPU host can run it).

    python -m experiments.lanes_check --batch 64 --steps 60 [--variant lanes_both] --out docs/results/bipedal_speed/FILE.json
"""
from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np


def compare(batch: int, steps: int, kernel: str, variant: str = "lanes") -> dict:
    from experiments.bench_latency import random_action_scan
    from experiments.profile_bipedal_step import make_env

    envs = {v: make_env(v, solver_kernel=kernel) for v in ("default", variant)}
    env = envs["default"]
    levels = env.param_space.sample(jax.random.PRNGKey(1), (batch,))
    state = random_action_scan(env, batch, steps, final_state=True)(jax.random.PRNGKey(0))
    keys = jax.random.split(jax.random.PRNGKey(2), batch)
    actions = jax.vmap(env.action_space().sample)(jax.random.split(jax.random.PRNGKey(3), batch))
    out, seconds = {}, {}
    for name, e in envs.items():
        t = time.perf_counter()
        out[name] = jax.block_until_ready(jax.jit(jax.vmap(e.step_without_reset))(keys, state, actions, levels))
        seconds[name] = round(time.perf_counter() - t, 1)
    diffs, unequal = {}, []
    for (path, a), b in zip(jax.tree_util.tree_flatten_with_path(out["default"])[0], jax.tree_util.tree_leaves(out[variant])):
        a, b, name = np.asarray(a), np.asarray(b), jax.tree_util.keystr(path)
        if a.size and np.issubdtype(a.dtype, np.floating):
            diffs[name] = float(np.max(np.abs(a - b)))
        elif not np.array_equal(a, b):
            unequal.append(name)
    touching = np.asarray(state.world.touching).reshape(batch, -1).any(1)
    return {"batch": batch, "after_steps": steps, "kernel": kernel, "variant": variant, "worlds_touching": int(touching.sum()),
            "max_abs_diff": dict(sorted(diffs.items(), key=lambda kv: -kv[1])), "unequal_non_float": unequal,
            "compile_and_run_s": seconds}


def main(argv=None) -> int:
    from shed_jax.runtime import provenance

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--steps", type=int, default=60, help="random-action steps before the compared step")
    p.add_argument("--kernel", default="xla", choices=("xla", "pallas", "interpret"))
    p.add_argument("--variant", default="lanes", choices=("lanes", "position_lanes", "lanes_both"))
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    rec = {**provenance("experiments.lanes_check", argv), **compare(a.batch, a.steps, a.kernel, a.variant)}
    with open(a.out, "w") as f:
        json.dump(rec, f, indent=1, allow_nan=False)
    print(json.dumps({k: rec[k] for k in ("worlds_touching", "unequal_non_float")}), max(rec["max_abs_diff"].values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
