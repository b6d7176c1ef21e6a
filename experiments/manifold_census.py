"""How many of the 2-D walker's edge-manifold slots have points at once, per world-step.

The solver gives each leg polygon ``EDGE_CONTACTS`` (3) manifold slots, 12 in all, and the fused
velocity loop solves every slot in every one of Box2D's 180 passes, touched or not (a slot without
points changes nothing). This counts, after each step, the slots whose manifold has a point
(``WorldState.touching``), over three kinds of batch: random actions on levels sampled from the FULL
box, and Gymnasium's scripted gait on the flat and the Hardcore levels. The figure that matters for
a kernel with fewer slots (the active manifolds packed in their order) is the largest count seen,
and how often a batch of 200 holds a world above a given number of slots.

    python -m experiments.manifold_census --worlds 128 --steps 400 --seeds 2 --out FILE.json
"""
from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs.bipedal.heuristic import heuristic, heuristic_init
from envs.walker import levels as LV

MODES = ("random", "gait_flat", "gait_hardcore")


def slots_on(env, mode: str, worlds: int, steps: int, seed: int) -> np.ndarray:
    """[steps, worlds, polygons, slots] bool: which manifold slots have points after each step
    (``env.step``, auto-reset included)."""
    key = jax.random.PRNGKey(seed)
    if mode == "random":
        levels = env.param_space.sample(key, (worlds,))
    else:
        level = LV.LEVELS["Hardcore" if mode == "gait_hardcore" else "BipedalWalker"](terrain_seed=0)
        levels = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (worlds,) + jnp.shape(x)), level)
        levels = levels.replace(terrain_seed=jnp.arange(worlds, dtype=jnp.int32) + 1000 * seed)
    per_polygon = env.model.config.edge_contacts

    @jax.jit
    def go(key):
        obs, state = jax.vmap(env.reset)(jax.random.split(key, worlds), levels)
        h = jax.vmap(lambda _: heuristic_init())(jnp.arange(worlds))

        def body(c, k):
            obs, state, h = c
            k_act, k_step = jax.random.split(k)
            if mode == "random":
                a = jax.random.uniform(k_act, (worlds, 4), minval=-1.0, maxval=1.0)
            else:
                a, h = jax.vmap(heuristic)(h, obs)
            obs, state, _, done, _ = jax.vmap(env.step)(jax.random.split(k_step, worlds), state, a, levels)
            fresh = jax.vmap(lambda _: heuristic_init())(h.phase)
            h = jax.tree_util.tree_map(lambda x, y: jnp.where(done, x, y), fresh, h)
            on = state.world.touching.reshape(worlds, -1, per_polygon, 2).any(-1)
            return (obs, state, h), on

        return jax.lax.scan(body, (obs, state, h), jax.random.split(key, steps))[1]

    return np.asarray(go(jax.random.fold_in(key, 1)))


def summarise(on: np.ndarray, batch: int = 200) -> dict:
    """Counts of ``on`` [steps, worlds, polygons, slots]: histogram of slots on per world-step, the
    largest, per-polygon and per-slot rates, and for K slots the share of world-steps above K and of
    steps in which some world of ``batch`` independent ones would be."""
    count = on.sum((2, 3))  # [steps, worlds]
    per_polygon = on.sum(-1)
    above = {}
    for k in range(1, on.shape[2] * on.shape[3]):
        share = float((count > k).mean())
        per_step = (count > k).mean(1)  # each step's share of worlds above k
        above[str(k)] = {"world_steps": share, "batch_of_%d" % batch: float(1 - np.mean((1 - per_step) ** batch))}
        if share == 0.0:
            break
    return {"world_steps": int(count.size), "histogram": np.bincount(count.ravel(), minlength=on.shape[2] * on.shape[3] + 1).tolist(),
            "max": int(count.max()), "max_per_polygon": per_polygon.max((0, 1)).tolist(),
            "polygon_rate": per_polygon.astype(bool).mean((0, 1)).round(4).tolist(),
            "slot_rate": on.mean((0, 1)).round(4).tolist(), "above": above}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--worlds", type=int, default=128)
    p.add_argument("--steps", type=int, default=400)
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--modes", default=",".join(MODES), help="comma-separated, of " + ", ".join(MODES))
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    modes = [m for m in a.modes.split(",") if m]
    bad = [m for m in modes if m not in MODES]
    if bad or a.worlds < 1 or a.steps < 1 or a.seeds < 1:
        p.error(f"modes must be among {', '.join(MODES)} (got {', '.join(bad)}); worlds, steps and seeds >= 1" if bad
                else "worlds, steps and seeds must be >= 1")
    env = envs.make("bipedal")
    rec = {"device": f"{jax.devices()[0].device_kind} ({platform.processor() or platform.machine()})",
           "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
           "command": "python -m experiments.manifold_census " + " ".join(sys.argv[1:] if argv is None else argv),
           "slots": int(env.model.num_contacts // 2), "modes": {}}
    for mode in modes:
        on = np.concatenate([slots_on(env, mode, a.worlds, a.steps, s) for s in range(a.seeds)], 1)
        rec["modes"][mode] = s = summarise(on)
        print(f"{mode}: {s['world_steps']} world-steps, slots on {s['histogram']}, at most {s['max']}", flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump(rec, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
