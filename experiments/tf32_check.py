"""Does an environment's step depend on the float32 matmul precision (TF32 on recent NVIDIA GPUs)?

JAX computes float32 matrix products at ``default`` precision unless told otherwise, and on
Ampere-or-newer GPUs that means TF32 (10 mantissa bits). A physics step that multiplies matrices
can then give different numbers on a GPU than on a CPU. This script rolls out the same batch of
random levels with the same random actions twice, once at ``default`` and once at ``highest``
precision, reports the largest difference (and the first step's), and times a step both ways.
On a CPU both are float32 and the rollouts are equal. An env that pins its own physics precision
(the walker's ``WalkerOptions.matmul_precision``) gets that option set to the same value as well;
otherwise both rollouts would run the same pinned program.

    python -m experiments.tf32_check --env walker --batch 256 --steps 200 --out $OUT
"""
from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np


def check(env_name: str, batch: int = 256, steps: int = 200, seed: int = 11) -> dict:
    """Rollouts at default and highest matmul precision: differences, and seconds per step for each."""
    import envs

    def make(precision):
        # an env that pins its own physics precision (the walker's options) gets it set as well
        env = envs.make(env_name)
        pinned = hasattr(getattr(env, "options", None), "matmul_precision")
        return envs.make(env_name, matmul_precision=precision) if pinned else env

    def rollout(env, key):
        levels = env.param_space.sample(jax.random.PRNGKey(seed + 1), (batch,))
        space = env.action_space()
        obs, state = jax.vmap(env.reset)(jax.random.split(key, batch), levels)

        def body(c, k):
            obs, state = c
            ka, ks = jax.random.split(k)
            a = jax.vmap(space.sample)(jax.random.split(ka, batch))
            obs, state, r, _, _ = jax.vmap(env.step)(jax.random.split(ks, batch), state, a, levels)
            return (obs, state), (obs, r)

        return jax.lax.scan(body, (obs, state), jax.random.split(key, steps))[1]

    out, seconds = {}, {}
    for precision in ("default", "highest"):
        with jax.default_matmul_precision(precision):
            env = make(precision)
            fn = jax.jit(lambda key: rollout(env, key))
            result = jax.block_until_ready(fn(jax.random.PRNGKey(seed)))  # compile, and the result kept
            best = float("inf")
            for _ in range(3):
                t = time.perf_counter()
                jax.block_until_ready(fn(jax.random.PRNGKey(seed)))
                best = min(best, time.perf_counter() - t)
            seconds[precision] = best / steps
            out[precision] = jax.device_get(result)
    (obs_d, r_d), (obs_h, r_h) = out["default"], out["highest"]
    diff = np.abs(obs_d.astype(np.float64) - obs_h)
    per_step = diff.reshape(steps, -1).max(axis=1)
    over = np.nonzero(per_step > 1e-4)[0]
    return dict(env=env_name, device=str(jax.devices()[0]), batch=batch, steps=steps,
                bitwise_equal=bool(np.array_equal(obs_d, obs_h) and np.array_equal(r_d, r_h)),
                first_step_obs_diff=float(per_step[0]), max_abs_obs_diff=float(diff.max()),
                max_abs_reward_diff=float(np.abs(r_d.astype(np.float64) - r_h).max()),
                first_step_over_tol=int(over[0]) if over.size else None, tol=1e-4,
                s_per_step_default=seconds["default"], s_per_step_highest=seconds["highest"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="default vs highest matmul precision in an env's step")
    p.add_argument("--env", default="lander")
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--out", default=os.environ.get("OUT", "."))
    a = p.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    row = check(a.env, a.batch, a.steps)
    print(json.dumps(row, indent=1))
    with open(os.path.join(a.out, f"tf32_check_{a.env}.json"), "w") as f:
        json.dump(row, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
