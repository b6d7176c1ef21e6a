"""Why episodes end, ours against Gymnasium, at one gravity: the g -1 parity gap (docs/lander.md).

For N episodes of Gymnasium's heuristic on each side (discrete, no wind, 1000-step limit) it prints
the mean return and how the episodes end: landed (+100), out of bounds (|x| >= 1), hull contact,
or truncated. It also prints the first step with a leg on the ground, and the vertical speed and
the angle (observation units) at that step, and how many truncated episodes had touched down.

    python -m experiments.lander_crash_causes --episodes 1000 --gravity -1 --seed 1

Ours runs as one vmapped scan (a few minutes on the 2-core CPU for 1000 episodes); Gymnasium uses
seeds 0..N-1 and needs the test extra (gymnasium[box2d]).
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from envs.lander.env import LunarLander, make_params
from envs.lander.heuristic import heuristic
from envs.lander.parity import _np_heuristic

MAX_STEPS = 1000


def first_episode_summary(obs, rew, done) -> dict:
    """``obs [N, T, 8]`` (the observation after each step), ``rew [N, T]``, ``done [N, T]``: the
    statistics of every row's first episode."""
    ends = dict(landed=0, out_of_bounds=0, hull=0, truncated=0, truncated_after_contact=0)
    returns, first_contact, vy, angle = [], [], [], []
    for i in range(obs.shape[0]):
        d = np.flatnonzero(done[i])
        e = d[0] if len(d) else obs.shape[1] - 1
        returns.append(rew[i, : e + 1].sum())
        legs = np.flatnonzero((obs[i, : e + 1, 6] > 0) | (obs[i, : e + 1, 7] > 0))
        first_contact.append(legs[0] if len(legs) else -1)
        if len(legs):
            vy.append(obs[i, legs[0], 3])
            angle.append(abs(obs[i, legs[0], 4]))
        if rew[i, e] == 100:
            ends["landed"] += 1
        elif rew[i, e] == -100:
            ends["out_of_bounds" if abs(obs[i, e, 0]) >= 1 else "hull"] += 1
        else:
            ends["truncated"] += 1
            ends["truncated_after_contact"] += bool(len(legs))  # touched down, but never came to rest
    n = obs.shape[0]
    fc = np.asarray(first_contact)
    r = np.asarray(returns)
    return dict(mean_return=float(r.mean()), se=float(r.std() / np.sqrt(n)), **{k: v / n for k, v in ends.items()},
                no_leg_contact=float(np.mean(fc < 0)), first_contact_median=float(np.median(fc[fc >= 0])),
                vy_at_contact=float(np.mean(vy)), abs_angle_at_contact=float(np.mean(angle)))


def gym_rollouts(n: int, gravity: float):
    import gymnasium as gym

    env = gym.make("LunarLander-v3", gravity=gravity, max_episode_steps=MAX_STEPS)
    obs_t = np.zeros((n, MAX_STEPS, 8), np.float32)
    rew_t = np.zeros((n, MAX_STEPS), np.float32)
    done_t = np.zeros((n, MAX_STEPS), bool)
    for ep in range(n):
        obs, _ = env.reset(seed=ep)
        for k in range(MAX_STEPS):
            obs, r, term, trunc, _ = env.step(_np_heuristic(obs, False))
            obs_t[ep, k], rew_t[ep, k], done_t[ep, k] = obs, r, term or trunc
            if term or trunc:
                break
    return obs_t, rew_t, done_t


def jax_rollouts(n: int, gravity: float, seed: int):
    env = LunarLander(continuous=False)
    levels = make_params(max_steps=np.full(n, MAX_STEPS), gravity=np.full(n, gravity, np.float32),
                         enable_wind=np.zeros(n, bool), wind_power=np.zeros(n, np.float32),
                         turbulence_power=np.zeros(n, np.float32))

    def one(key, params):
        k0, k1 = jax.random.split(key)
        obs, state = env.reset(k0, params)

        def body(carry, k):
            obs, state = carry
            nxt, state, r, d, info = env.step(k, state, heuristic(obs, False), params)
            return (nxt, state), (jnp.where(d, info["final_obs"], nxt), r, d)

        _, out = jax.lax.scan(body, (obs, state), jax.random.split(k1, MAX_STEPS))
        return out

    out = jax.jit(jax.vmap(one))(jax.random.split(jax.random.PRNGKey(seed), n), levels)
    return tuple(np.asarray(x) for x in out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--gravity", type=float, default=-1.0)
    p.add_argument("--seed", type=int, default=1, help="root key of our side")
    args = p.parse_args(argv)
    for name, rollouts in (("gymnasium", lambda: gym_rollouts(args.episodes, args.gravity)),
                           ("ours", lambda: jax_rollouts(args.episodes, args.gravity, args.seed))):
        s = first_episode_summary(*rollouts())
        print(f"{name:9s} " + " ".join(f"{k} {v:.3f}" for k, v in s.items()), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
