"""Seeds x learning-rate sweep of the PPO student in ONE vmapped, once-compiled call.

    python -m experiments.ppo_sweep --env cartpole --lrs 1e-4 3e-4 1e-3 3e-3 --seeds 4 \
        --total-steps 100000 --out runs/ppo_sweep_cartpole

The grid is flattened to a batch of (key, PPOHyperparams) pairs; `train_seeds` vmaps the student
over it, so one XLA program trains every run. Writes OUT/sweep.json (per-lr final returns and
curves) and OUT/sweep_curves.png (mean and standard error over seeds, one curve per lr).
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np


def main(argv=None) -> int:
    import envs
    from shed_jax import reporting
    from shed_jax.training import resolve_level, smoothed, train_seeds
    from shed_jax.student import PPOConfig, PPOHyperparams, make_student

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="cartpole", choices=envs.registered())
    p.add_argument("--level", default=None)
    p.add_argument("--lrs", type=float, nargs="+", default=[1e-4, 3e-4, 1e-3, 3e-3])
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--total-steps", type=int, default=100_000)
    p.add_argument("--chunks", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=os.environ.get("OUT", "runs/ppo_sweep"))
    args = p.parse_args(argv)

    env = envs.make(args.env)
    config = PPOConfig.for_env(args.env)
    student = make_student(env, config)
    level = resolve_level(env, args.level)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    S, L = args.seeds, len(args.lrs)
    seed_keys = jax.random.split(jax.random.PRNGKey(args.seed), S)
    keys = jnp.tile(seed_keys, (L, 1))  # row i = lr i // S, seed i % S (same seeds for every lr)
    hps = PPOHyperparams.stack([config.hparams.replace(lr=lr) for lr in args.lrs for _ in range(S)])
    num_updates = -(-args.total_steps // student.env_steps_per_update)
    t0 = time.perf_counter()
    states, metrics, timing = train_seeds(student, keys, hps, level, num_updates, args.chunks)
    wall = time.perf_counter() - t0

    x = (np.arange(timing["updates"]) + 1) * student.env_steps_per_update
    ret = smoothed(metrics["episode_return"], 10).reshape(L, S, -1)
    curves = {f"lr={lr:g}": (x, ret[i]) for i, lr in enumerate(args.lrs)}
    reporting.plot_curves(curves, out / "sweep_curves.png", xlabel="env steps per run",
                          ylabel="training episode return (10-update avg)",
                          title=f"PPO lr sweep on {args.env}: {S} seeds x {L} lrs, one compile")
    final = ret[:, :, -1]
    result = {
        "env": args.env, "level": args.level, "seeds": S, "lrs": args.lrs,
        "final_return": {f"{lr:g}": final[i].tolist() for i, lr in enumerate(args.lrs)},
        "final_return_mean": {f"{lr:g}": float(np.nanmean(final[i])) for i, lr in enumerate(args.lrs)},
        "env_steps_per_run": timing["env_steps_per_seed"], "runs": S * L,
        "compile_s": timing["compile_s"], "train_s": timing["train_s"], "wall_s": wall,
        "env_steps_per_s": timing["env_steps_per_s"], "device": str(jax.devices()[0]),
        "curves": {k: np.nanmean(v[1], axis=0)[:: max(1, len(x) // 200)].tolist() for k, v in curves.items()},
        "curve_env_steps": x[:: max(1, len(x) // 200)].tolist(),
    }
    (out / "sweep.json").write_text(json.dumps(result, indent=2))
    for k, v in result["final_return_mean"].items():
        print(f"lr {k}: final mean return {v:.1f}")
    print(f"{S * L} runs in one program: compile {timing['compile_s']:.1f}s, train {timing['train_s']:.1f}s, "
          f"{timing['env_steps_per_s']:.3g} env steps/s; wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
