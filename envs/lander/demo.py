"""`python -m shed_jax demo --env lander|lander-continuous`: the heuristic on generated levels.

Levels are drawn from ``env.param_space`` (wind on for the first half); every level runs one
episode in a single vmapped, scanned program; a table is printed and a GIF of level 0 is written.
"""
from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs.lander.heuristic import heuristic
from envs.rendering import save_gif, trajectory_frames


def rollout(env, levels, key, max_steps: int):
    """Heuristic episodes on every level: per-step states (T, N, ...) and per-level first-episode stats."""
    n = levels.gravity.shape[0]

    def one(key, params):
        k0, k1 = jax.random.split(key)
        obs, state = env.reset(k0, params)

        def body(carry, k):
            obs, state, finished, stats = carry
            obs, nstate, _, done, info = env.step(k, state, heuristic(obs, env.continuous), params)
            first = done & ~finished
            stats = jax.tree_util.tree_map(lambda o, v: jnp.where(first, v, o), stats, dict(
                ret=info["episode_return"], length=info["episode_length"], landed=info["landed"],
                crashed=info["crashed"] & ~info["landed"]))
            return (obs, nstate, finished | done, stats), (state, finished)

        stats0 = dict(ret=jnp.float32(0), length=jnp.int32(0), landed=jnp.bool_(False), crashed=jnp.bool_(False))
        (_, _, finished, stats), (states, fin) = jax.lax.scan(
            body, (obs, state, jnp.bool_(False), stats0), jax.random.split(k1, max_steps))
        stats["finished"] = finished
        return stats, states

    return jax.jit(jax.vmap(one, out_axes=(0, 1)))(jax.random.split(key, n), levels)


def run_demo(args) -> int:
    env = envs.make(args.env)
    n = int(args.levels)
    if n < 1:
        raise ValueError(f"--levels must be >= 1, got {n}")
    key = jax.random.PRNGKey(int(args.seed))
    k_lv, k_run = jax.random.split(key)
    levels = env.param_space.sample(k_lv, (n,))
    levels = levels.replace(enable_wind=jnp.arange(n) < (n + 1) // 2)
    max_steps = int(np.asarray(env.default_params.max_steps))
    stats, states = rollout(env, levels, k_run, max_steps)
    stats = jax.tree_util.tree_map(np.asarray, stats)
    print(f"{'level':>5} {'gravity':>8} {'wind':>5} {'wind_pw':>7} {'turb':>5} {'return':>8} {'length':>6}  outcome")
    for i in range(n):
        outcome = ("landed" if stats["landed"][i] else "crashed" if stats["crashed"][i] else "timeout")
        print(f"{i:5d} {float(levels.gravity[i]):8.2f} {str(bool(levels.enable_wind[i])):>5} "
              f"{float(levels.wind_power[i]):7.2f} {float(levels.turbulence_power[i]):5.2f} "
              f"{float(stats['ret'][i]):8.1f} {int(stats['length'][i]):6d}  {outcome}")
    out = args.out or os.path.join("runs", f"demo-{args.env}")
    length = int(stats["length"][0]) or max_steps
    frames = trajectory_frames(lambda s: env.render(s), states, env_index=0, stop=length + 1, every=2)
    path = save_gif(frames, os.path.join(out, "level0.gif"), fps=25)
    print(f"wrote {path} ({len(frames)} frames)")
    return 0
