"""Parity harness: Gymnasium's heuristic in our lander (vmapped) and in Gymnasium LunarLander-v3.

Both sides report, per setting, the statistics docs/design.md §13.1 (and docs/lander.md "Parity") compares: mean / std return, the +100
landing rate, the -100 crash rate, mean length (and the truncation rate). Our side runs every
episode of every setting of one action type in a single compiled program (a queue of episodes on
vmapped lanes, `jax_episodes`).

    python -m envs.lander.parity --episodes 1000 --out runs/parity.json      # both sides
    python -m envs.lander.parity --gym-only --episodes 1000 --out tests/test_lander_parity_reference.json
    python -m envs.lander.parity --jax-only --settings "g -1" --iterations 180/60   # one row, Box2D's passes
"""
from __future__ import annotations

import argparse
import functools
import json
import re
import time

import jax
import jax.numpy as jnp
import numpy as np

from envs.core import restart_where
from envs.lander.env import LunarLander, make_params
from envs.lander.heuristic import heuristic

# name -> (gravity, enable_wind, wind_power, turbulence_power)
SETTINGS = {
    "default": (-10.0, False, 15.0, 1.5),
    "wind 15/1.5": (-10.0, True, 15.0, 1.5),
    "wind 5/0.5": (-10.0, True, 5.0, 0.5),
    "g -5": (-5.0, False, 15.0, 1.5),
    "g -11.99": (-11.99, False, 15.0, 1.5),
    "g -1": (-1.0, False, 15.0, 1.5),
}


def summarize(returns, lengths, landed, crashed, truncated) -> dict:
    r = np.asarray(returns, np.float64)
    return dict(
        episodes=int(r.size), mean=float(r.mean()), std=float(r.std()), se=float(r.std() / np.sqrt(r.size)),
        landed=float(np.mean(landed)), crashed=float(np.mean(crashed)), truncated=float(np.mean(truncated)),
        length=float(np.mean(lengths)),
    )


def jax_episodes(continuous: bool, levels, key, max_steps: int = 1000, lanes: int = 64, **env_kwargs):
    """First episode of the heuristic on every level (params with leading axis n). Numpy dict of (n,).

    ``key`` is one key, split into one per episode, or already an (n, 2) array of per-episode keys
    (to repeat one row of a larger run with the keys it had there). Episode ``i`` resets with the
    first half of its key and takes its step keys, one per step, from the second half split
    ``max_steps`` ways, so its result does not depend on the lane that runs it or on the other
    episodes (across lane counts, up to XLA's rounding, which the lander's contacts amplify).

    The episodes run as a queue on ``lanes`` vmapped lanes: a lane whose episode ends takes the
    next episode from the queue, and the program stops when the queue is empty and every lane is
    idle. Episodes last 130 to 600 steps on average and a few run to the limit, so a batch of every
    episode run to ``max_steps`` did about 3.5x the work (a minute per action type on a 2-core CPU).
    """
    n = levels.gravity.shape[0]
    keys = key if jnp.ndim(key) == 2 else jax.random.split(key, n)
    if keys.shape[0] != n:
        raise ValueError(f"{keys.shape[0]} episode keys for {n} levels")
    run = _episodes_program(bool(continuous), int(n), int(max_steps), min(int(lanes), n),
                            tuple(sorted(env_kwargs.items())), jax.jit)
    return jax.tree_util.tree_map(np.asarray, run(keys, levels))


@functools.lru_cache(maxsize=16)
def _episodes_program(continuous: bool, n: int, max_steps: int, lanes: int, env_kwargs: tuple, jit):
    """``jax_episodes``' program for ``n`` levels, jitted by ``jit``, built once per setting: later calls
    with the same setting (other levels or keys) skip its tracing as well as its compile. ``jit`` is
    whatever ``jax.jit`` is at the call, part of the key (the tests swap it for one with other
    compiler options)."""
    env = LunarLander(continuous=continuous, **dict(env_kwargs))
    take = lambda tree, idx: jax.tree_util.tree_map(lambda x: x[idx], tree)  # noqa: E731

    def run(keys, levels):
        reset_keys, step_root = jax.vmap(lambda k: tuple(jax.random.split(k)))(keys)
        step_keys = jax.vmap(lambda k: jax.random.split(k, max_steps))(step_root)  # (n, max_steps, 2)
        reset = jax.vmap(env.reset)
        step = jax.vmap(env.step_without_reset)
        episode = jnp.arange(lanes)  # each lane's episode; n for an idle lane
        obs, state = reset(reset_keys[:lanes], take(levels, episode))
        out = dict(ret=jnp.zeros(n, jnp.float32), length=jnp.zeros(n, jnp.int32), landed=jnp.zeros(n, bool),
                   crashed=jnp.zeros(n, bool), truncated=jnp.zeros(n, bool))

        def body(carry):
            episode, t, obs, state, params, queued, out = carry
            live = episode < n
            row = jnp.minimum(episode, n - 1)
            action = jax.vmap(lambda o: heuristic(o, continuous))(obs)
            obs, state, _, done, info = step(step_keys[row, t], state, action, params)
            ended = live & done
            slot = jnp.where(ended, episode, n)  # writes of the other lanes fall outside and are dropped
            out = {k: out[k].at[slot].set(v, mode="drop") for k, v in dict(
                ret=info["episode_return"], length=info["episode_length"], landed=info["landed"],
                crashed=info["crashed"] & ~info["landed"], truncated=info["truncated"]).items()}
            # a lane also moves on after max_steps steps without an end (levels with a longer limit),
            # leaving that episode's zeros, as a scan of max_steps steps did
            moves = ended | (live & (t + 1 >= max_steps))
            following = queued + jnp.cumsum(moves) - 1  # the lanes that move on take the next episodes in order
            episode = jnp.where(moves, jnp.where(following < n, following, n), episode)
            fresh = moves & (episode < n)

            def restart(args):
                row = jnp.minimum(episode, n - 1)
                new_params = take(levels, row)
                return jax.vmap(restart_where)(fresh, (*reset(reset_keys[row], new_params), new_params), args)

            obs, state, params = jax.lax.cond(fresh.any(), restart, lambda a: a, (obs, state, params))
            t = jnp.where(moves, 0, jnp.minimum(t + 1, max_steps - 1))
            return episode, t, obs, state, params, queued + moves.sum(), out

        carry = (episode, jnp.zeros(lanes, jnp.int32), obs, state, take(levels, episode), jnp.int32(lanes), out)
        return jax.lax.while_loop(lambda c: (c[0] < n).any(), body, carry)[-1]

    return jit(run)


def jax_stats(continuous: bool, settings=SETTINGS, episodes: int = 100, seed: int = 0, max_steps: int = 1000,
              lanes: int = 64, **env_kwargs) -> dict:
    names = list(settings)
    g, w, wp, tp = (np.repeat(np.asarray([settings[s][i] for s in names]), episodes) for i in range(4))
    levels = make_params(max_steps=np.full(g.shape, max_steps), gravity=g, enable_wind=w.astype(bool),
                         wind_power=wp, turbulence_power=tp)
    out = jax_episodes(continuous, levels, jax.random.PRNGKey(seed), max_steps, lanes, **env_kwargs)
    res = {}
    for k, name in enumerate(names):
        sl = slice(k * episodes, (k + 1) * episodes)
        res[name] = summarize(out["ret"][sl], out["length"][sl], out["landed"][sl], out["crashed"][sl],
                              out["truncated"][sl])
    return res


def gym_stats(continuous: bool, settings=SETTINGS, episodes: int = 100, seed: int = 0, max_steps: int = 1000) -> dict:
    import gymnasium as gym

    from envs.lander.heuristic import heuristic as h

    res = {}
    for name, (g, wind, wp, tp) in settings.items():
        env = gym.make("LunarLander-v3", continuous=continuous, gravity=g, enable_wind=wind, wind_power=wp,
                       turbulence_power=tp, max_episode_steps=max_steps)
        rets, lens, landed, crashed, trunc = [], [], [], [], []
        for ep in range(episodes):
            obs, _ = env.reset(seed=seed + ep)
            total, n = 0.0, 0
            while True:
                a = _np_heuristic(obs, continuous)
                obs, r, term, tr, _ = env.step(a)
                total += r
                n += 1
                if term or tr:
                    break
            rets.append(total)
            lens.append(n)
            landed.append(term and r == 100)
            crashed.append(term and r == -100)
            trunc.append(tr and not term)
        env.close()
        res[name] = summarize(rets, lens, landed, crashed, trunc)
    return res


def _np_heuristic(s, continuous):
    """Gymnasium's heuristic on a numpy observation (same rules as heuristic.py, no JAX dispatch)."""
    angle_targ = np.clip(s[0] * 0.5 + s[2], -0.4, 0.4)
    hover_targ = 0.55 * abs(s[0])
    angle_todo = (angle_targ - s[4]) * 0.5 - s[5]
    hover_todo = (hover_targ - s[1]) * 0.5 - s[3] * 0.5
    if s[6] or s[7]:
        angle_todo = 0.0
        hover_todo = -s[3] * 0.5
    if continuous:
        return np.clip(np.array([hover_todo * 20 - 1, -angle_todo * 20], np.float32), -1, 1)
    if hover_todo > abs(angle_todo) and hover_todo > 0.05:
        return 2
    if angle_todo < -0.05:
        return 3
    if angle_todo > 0.05:
        return 1
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--gym-only", action="store_true")
    p.add_argument("--jax-only", action="store_true")
    p.add_argument("--settings", default=None, metavar="NAME[,NAME...]",
                   help=f"comma-separated rows to run (default all): {', '.join(SETTINGS)}")
    p.add_argument("--iterations", default=None, metavar="V/P",
                   help="our solver's velocity/position passes (default the lander's own; Box2D in Gymnasium: 180/60)")
    p.add_argument("--solver-kernel", default="auto", choices=("auto", "xla"),
                   help="our solver loops: auto (one Pallas kernel per loop on a GPU) or xla (plain loops)")
    p.add_argument("--lanes", type=int, default=64,
                   help="vmapped lanes that run the queue of episodes (default 64, for a CPU; on a GPU, 1024 or more)")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.lanes < 1:
        p.error(f"--lanes must be a positive integer; got {args.lanes}")
    settings = SETTINGS
    if args.settings:
        names = [n.strip() for n in args.settings.split(",")]
        unknown = [n for n in names if n not in SETTINGS]
        if unknown:
            p.error(f"unknown setting(s) {unknown}; known: {list(SETTINGS)}")
        settings = {n: SETTINGS[n] for n in names}
    env_kwargs = {"solver_kernel": args.solver_kernel}
    if args.iterations:
        m = re.fullmatch(r"(\d+)/(\d+)", args.iterations)
        if not m or int(m[1]) < 1 or int(m[2]) < 1:
            p.error(f"--iterations must be V/P with positive integers, e.g. 180/60; got {args.iterations!r}")
        env_kwargs.update(velocity_iterations=int(m[1]), position_iterations=int(m[2]))
    result = {"episodes": args.episodes, "seed": args.seed, "max_steps": 1000, "settings": list(settings),
              "iterations": args.iterations, "solver_kernel": args.solver_kernel}
    for continuous in (False, True):
        mode = "continuous" if continuous else "discrete"
        if not args.jax_only:
            t = time.time()
            result.setdefault("gym", {})[mode] = gym_stats(continuous, settings, episodes=args.episodes, seed=args.seed)
            print(f"gym {mode}: {time.time() - t:.1f}s", flush=True)
        if not args.gym_only:
            t = time.time()
            result.setdefault("jax", {})[mode] = jax_stats(continuous, settings, episodes=args.episodes, seed=args.seed,
                                                           lanes=args.lanes, **env_kwargs)
            print(f"jax {mode}: {time.time() - t:.1f}s", flush=True)
    for side in ("gym", "jax"):
        for mode, rows in result.get(side, {}).items():
            for name, r in rows.items():
                print(f"{side:4s} {mode:10s} {name:12s} mean {r['mean']:7.1f} std {r['std']:6.1f} "
                      f"+100 {r['landed']:.2f} -100 {r['crashed']:.2f} trunc {r['truncated']:.2f} len {r['length']:6.1f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
