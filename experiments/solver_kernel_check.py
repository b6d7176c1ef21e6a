"""Does the fused solver kernel give the XLA solver's numbers? Run on the device that uses it.

Three checks, fused kernel ("pallas" on GPU, or "interpret") against plain XLA loops:
  1. one step from the same states (taken along an XLA rollout of random actions): max |diff|;
  2. the same rollout run with each solver: the step at which observations first differ by more
     than 1e-4 (the lander is chaotic, so rounding differences grow; this shows how fast);
  3. Gymnasium's heuristic over all parity settings (envs/lander/parity.py): mean return, landing
     and crash rates and length per setting, for both solvers.

    python -m experiments.solver_kernel_check --kernel pallas --episodes 1000 --out $OUT
"""
from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs.lander import parity
from envs.lander.env import make_params


def rollout(env, params, n: int, steps: int, seed: int = 0):
    """Random-action rollout of n landers; returns the state at every step and the observations."""
    obs, st = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(seed), n), params)
    space = env.action_space()

    def one(st, k):
        ka, ks = jax.random.split(k)
        a = jax.vmap(space.sample)(jax.random.split(ka, n))
        obs, st2, r, d, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(jax.random.split(ks, n), st, a, params)
        return st2, (st, a, ks, obs)

    return jax.jit(lambda s: jax.lax.scan(one, s, jax.random.split(jax.random.PRNGKey(seed + 1), steps))[1])(st)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kernel", default="pallas", choices=["pallas", "interpret"])
    p.add_argument("--landers", type=int, default=256)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--episodes", type=int, default=1000, help="heuristic episodes per parity setting")
    p.add_argument("--out", default=os.environ.get("OUT", "."))
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)  # up front: a bad path fails before the work, not after it
    ref_env = envs.make("lander", solver_kernel="xla")
    ker_env = envs.make("lander", solver_kernel=args.kernel)
    params = make_params(enable_wind=True)  # wind and turbulence on: every force path in play
    res = dict(device=str(jax.devices()[0]), kernel=args.kernel, landers=args.landers, steps=args.steps)

    states, actions, keys, obs_ref = rollout(ref_env, params, args.landers, args.steps)
    step = lambda env: jax.jit(jax.vmap(jax.vmap(env.step, in_axes=(0, 0, 0, None)),  # noqa: E731
                                        in_axes=(0, 0, 0, None)))
    keys_n = jax.vmap(lambda k: jax.random.split(k, args.landers))(keys)
    o_ref = step(ref_env)(keys_n, states, actions, params)[0]
    o_ker = step(ker_env)(keys_n, states, actions, params)[0]
    diff = np.abs(np.asarray(o_ref) - np.asarray(o_ker))
    res["one_step_max_abs_diff"] = float(diff.max())
    res["one_step_frac_exact"] = float(np.mean(diff == 0))

    obs_ker = rollout(ker_env, params, args.landers, args.steps)[3]
    dev = np.abs(np.asarray(obs_ref) - np.asarray(obs_ker)).max(axis=(1, 2))
    over = np.nonzero(dev > 1e-4)[0]
    res["rollout_first_step_over_1e-4"] = int(over[0]) if over.size else None
    res["rollout_max_abs_diff_at"] = {int(t): float(dev[t]) for t in (0, 9, 49, 99, args.steps - 1) if t < args.steps}
    print(json.dumps(res), flush=True)
    path = os.path.join(args.out, f"solver_kernel_check_{args.kernel}.json")

    def save():  # after every part, so a time limit keeps what was measured
        with open(path, "w") as f:
            json.dump(res, f, indent=1)

    save()
    for name, kernel in (("kernel", args.kernel), ("xla", "xla")):
        t = time.time()
        res[f"heuristic_{name}"] = parity.jax_stats(False, parity.SETTINGS, episodes=args.episodes, seed=0,
                                                   solver_kernel=kernel)
        res[f"heuristic_{name}_s"] = time.time() - t
        print(json.dumps({name: res[f"heuristic_{name}"]}), flush=True)
        save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
