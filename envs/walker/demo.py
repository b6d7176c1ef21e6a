"""``python -m shed_jax demo --env walker``: a random or scripted policy on a few named levels.

Prints a per-level table (return, length, outcome, distance) and writes one GIF per level under
``runs/demo-walker/`` (or ``--out``). The rollout is one jitted ``lax.scan`` per level; frames are
drawn on the host afterwards from the recorded poses.
"""
from __future__ import annotations

import argparse
import pathlib

import numpy as np

DEFAULT_LEVELS = ("BipedalWalker", "Stump", "PitGap", "Stairs")
#: Levels shown when the shared CLI asks for a number of levels (``--levels N``).
DEMO_ORDER = ("BipedalWalker", "Stump", "PitGap", "Stairs", "Roughness", "Hardcore", "High-Stump", "Wide-PitGap", "Insane")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="shed_jax demo --env walker", description=__doc__)
    ap.add_argument("--levels", default=",".join(DEFAULT_LEVELS), help="comma-separated names from envs.walker.levels.LEVELS")
    ap.add_argument("--policy", choices=("random", "scripted"), default="scripted")
    ap.add_argument("--steps", type=int, default=300, help="max steps per level (first episode only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="runs/demo-walker")
    ap.add_argument("--frame-every", type=int, default=3)
    ap.add_argument("--no-gif", action="store_true")
    return ap


def scripted_action(t, qpos):
    """Open-loop alternating leg pumping (hips in antiphase, knees flexing): a sanity policy, not a
    controller. It shows contacts, joint limits and the terrain; on flat ground it stays up for
    300 steps (MuJoCo C check) but makes no forward progress."""
    import jax.numpy as jnp

    ph = 0.2 * t
    return jnp.stack([jnp.sin(ph), -0.6 + 0.4 * jnp.cos(ph), -jnp.sin(ph), -0.6 - 0.4 * jnp.cos(ph)]).astype(jnp.float32)


def make_rollout(env, steps: int, policy: str):
    """A jitted ``(params, key) -> (profile, per-step outputs)``: one scan of ``steps`` env steps;
    compiled once and reused for every level (levels share shapes)."""
    import jax
    import jax.numpy as jnp

    @jax.jit
    def run(params, key):
        k0, k1 = jax.random.split(key)
        obs, s = env.reset(k0, params)
        profile = s.profile

        def body(carry, inp):
            s = carry
            t, k = inp
            ka, ks = jax.random.split(k)
            a = jax.random.uniform(ka, (4,), minval=-1.0, maxval=1.0) if policy == "random" else scripted_action(t, s.qpos)
            o, s2, r, d, info = env.step(ks, s, a, params)
            return s2, (s.qpos, info["final_obs"], r, d, info["x"], info["terminated"])

        _, out = jax.lax.scan(body, s, (jnp.arange(steps), jax.random.split(k1, steps)))
        return profile, out

    def rollout(params, key):
        profile, (qpos, _, r, d, x, term) = jax.tree_util.tree_map(np.asarray, run(params, key))
        return profile, qpos, r, d, x, term

    return rollout


def run_demo(args=None) -> int:
    """Entry point; ``args`` is an argparse Namespace (from the CLI) or an argv list."""
    import jax

    import envs
    from envs.walker.levels import LEVELS
    from envs.walker.render import draw, save_gif

    if args is None or isinstance(args, (list, tuple)):
        args = parser().parse_args(args)
    defaults = vars(parser().parse_args([]))
    get = lambda name: getattr(args, name, None) if getattr(args, name, None) is not None else defaults[name]  # noqa: E731
    levels = get("levels")
    if isinstance(levels, int):  # the shared CLI passes a number of levels
        if levels < 1:
            raise ValueError(f"--levels must be >= 1, got {levels}")
        names = list(DEMO_ORDER[: min(levels, len(DEMO_ORDER))])
    else:
        names = [n for n in str(levels).split(",") if n]
    unknown = [n for n in names if n not in LEVELS]
    if unknown:
        raise ValueError(f"unknown walker level(s) {unknown}; known: {sorted(LEVELS)}")
    out = pathlib.Path(get("out"))
    out.mkdir(parents=True, exist_ok=True)
    env = envs.make("walker")
    rows = []
    rollout = make_rollout(env, get("steps"), get("policy"))
    for i, name in enumerate(names):
        params = LEVELS[name](terrain_seed=get("seed") + i, fixed_terrain=True)
        profile, qpos, r, d, x, term = rollout(params, jax.random.PRNGKey(get("seed") + i))
        n = int(np.argmax(d)) + 1 if d.any() else len(d)
        outcome = "crash" if d.any() and term[n - 1] and r[n - 1] == -100 else ("finish" if d.any() and term[n - 1] else ("time limit" if d.any() else "running"))
        rows.append((name, float(r[:n].sum()), n, outcome, float(x[n - 1] - qpos[0, 0])))
        if not get("no_gif"):
            frames = [draw(qpos[t], profile, env.grid, text=f"{name} t={t}") for t in range(0, n, get("frame_every"))]
            save_gif(frames, out / f"walker_{name}.gif", fps=max(1, 50 // get("frame_every")))
    print(f"{'level':<16}{'return':>10}{'length':>8}  {'outcome':<11}{'distance (m)':>12}")
    for name, ret, n, outcome, dist in rows:
        print(f"{name:<16}{ret:>10.1f}{n:>8d}  {outcome:<11}{dist:>12.2f}")
    if not get("no_gif"):
        print(f"GIFs in {out}/")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_demo())
