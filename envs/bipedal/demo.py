"""``python -m shed_jax demo --env bipedal``: Gymnasium's scripted gait, or a saved student, on named levels.

The controller is Gymnasium's ``BipedalWalkerHeuristics`` gait (``envs.bipedal.heuristic``), or with
``--policy FILE`` the deterministic policy of a student saved by ``python -m shed_jax ppo --env
bipedal`` (``policy.msgpack``; its first seed). Every level runs its first episode, up to ``steps``
steps, in one vmapped and scanned program; the table gives return, length, how the episode ended
and the distance walked, and one GIF per level is drawn afterwards from the bodies the solver held
at each step (``env.render``).

    python -m shed_jax demo --env bipedal --levels 4
    python -m shed_jax demo --env bipedal --policy docs/results/bipedal_ppo_flat_h200_2026-12-02/policy.msgpack
    python -m envs.bipedal.demo --levels BipedalWalker,Stump --steps 1600 --frame-every 4
"""
from __future__ import annotations

import argparse
import pathlib

import numpy as np

from envs.walker.demo import DEMO_ORDER

#: the shared CLI's ``--policy`` is passed on to this demo
ACCEPTS_POLICY = True
DEFAULT_LEVELS = ("BipedalWalker", "Stump", "PitGap", "Stairs")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m envs.bipedal.demo", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--levels", default=",".join(DEFAULT_LEVELS), help="comma-separated names of envs.walker.levels.LEVELS")
    ap.add_argument("--policy", default=None, help="a policy.msgpack of 'python -m shed_jax ppo --env bipedal' "
                    "(its first seed, deterministic) instead of Gymnasium's gait")
    ap.add_argument("--steps", type=int, default=600, help="steps per level at most (the first episode only)")
    ap.add_argument("--seed", type=int, default=0, help="root PRNG seed (terrains and the start push)")
    ap.add_argument("--out", default="runs/demo-bipedal", help="where the GIFs go")
    ap.add_argument("--frame-every", type=int, default=3, help="draw every k-th step")
    ap.add_argument("--no-gif", action="store_true", help="print the table only")
    return ap


def make_rollout(env, steps: int, controller):
    """A jitted ``(keys [N], params [N], theta) -> (stats [N], bodies [T, N], start states [N])``: the first
    episode of ``controller`` (``envs.bipedal.parity``'s form) on each level, ``steps`` steps at most.
    ``stats``: return, length, fell (the -100 ending), terminated, done, x at the start and at the end.
    ``bodies``: the solver's bodies before each step, enough to draw a frame with the start state's
    terrain (``frame``)."""
    import jax
    import jax.numpy as jnp

    first, next_ = controller

    def one(key, params, theta):
        k0, k1 = jax.random.split(key)
        obs, state = env.reset(k0, params)
        stats0 = dict(ret=jnp.float32(0), length=jnp.int32(0), fell=jnp.bool_(False), terminated=jnp.bool_(False),
                      done=jnp.bool_(False), x0=env.hull_origin(state.world)[0], x=jnp.float32(0))

        def body(carry, k):
            obs, s, h, a, stats = carry
            obs2, s2, reward, done, info = env.step_without_reset(k, s, a, params)
            end = done & ~stats["done"]
            stats = {**stats, **{name: jnp.where(end, value, stats[name]) for name, value in dict(
                ret=info["episode_return"], length=info["episode_length"], terminated=info["terminated"],
                fell=info["terminated"] & (reward == -100.0)).items()}}
            # where the episode goes on, x follows it; at its end it stays
            stats["x"] = jnp.where(stats["done"], stats["x"], info["x"])
            stats["done"] = stats["done"] | done
            a2, h2 = next_(theta, h, obs2)
            return (obs2, s2, h2, a2, stats), s.world.bodies

        a, h = first(theta, obs)
        (_, s, _, _, stats), bodies = jax.lax.scan(body, (obs, state, h, a, stats0), jax.random.split(k1, steps))
        # not ended within ``steps``: the return and length so far
        stats["ret"] = jnp.where(stats["done"], stats["ret"], s.episode_return)
        stats["length"] = jnp.where(stats["done"], stats["length"], s.time)
        return stats, bodies, state

    return jax.jit(jax.vmap(one, in_axes=(0, 0, None), out_axes=(0, 1, 0)))


def frame(env, start, bodies, text: str | None = None) -> np.ndarray:
    """One RGB frame: ``start`` (one level's start state, for its terrain) with the solver's ``bodies`` of a step."""
    state = start.replace(world=start.world.replace(bodies=bodies))
    img = env.render(state)
    if text:
        from PIL import Image, ImageDraw

        im = Image.fromarray(img)
        ImageDraw.Draw(im).text((4, 4), text, fill=(0, 0, 0))
        img = np.asarray(im)
    return img


def outcome(stats: dict, i: int) -> str:
    if not stats["done"][i]:
        return "running"
    if stats["fell"][i]:
        return "fell"
    return "finished" if stats["terminated"][i] else "time limit"


def run_demo(args=None) -> int:
    """Entry point; ``args`` is an argparse Namespace (from the shared CLI) or an argv list."""
    from envs.bipedal.env import BipedalWalker
    from envs.bipedal.parity import heuristic_controller, policy_controller
    from envs.rendering import unstack
    from envs.walker.levels import LEVELS
    from shed_jax.cli.errors import UsageError

    if args is None or isinstance(args, (list, tuple)):
        args = parser().parse_args(args)
    defaults = vars(parser().parse_args([]))
    get = lambda name: getattr(args, name, None) if getattr(args, name, None) is not None else defaults[name]  # noqa: E731
    levels = get("levels")
    if isinstance(levels, int):  # the shared CLI passes a number of levels
        names = list(DEMO_ORDER[: max(1, min(levels, len(DEMO_ORDER)))])
    else:
        names = [n for n in str(levels).split(",") if n]
    unknown = [n for n in names if n not in LEVELS]
    if unknown or not names:
        raise UsageError(f"unknown level(s) {', '.join(unknown) or '(none given)'}; known: {', '.join(sorted(LEVELS))}")
    steps, every = int(get("steps")), int(get("frame_every"))
    if steps < 1 or every < 1:
        raise UsageError(f"--steps and --frame-every must be >= 1, got {steps} and {every}")

    env = BipedalWalker()
    theta, who = None, "Gymnasium's scripted gait"
    controller = heuristic_controller()
    if get("policy"):
        path = pathlib.Path(get("policy"))
        if not path.is_file():
            raise UsageError(f"--policy {path}: no such file (a policy.msgpack of 'python -m shed_jax ppo --env bipedal')")
        from shed_jax.student import PPOConfig, make_student
        from shed_jax.training import load_policy

        student = make_student(env, PPOConfig.for_env("bipedal").replace(num_envs=1))
        try:
            theta = unstack(load_policy(student, path), 0)
        except (ValueError, KeyError, TypeError) as err:
            raise UsageError(f"--policy {path} is not a saved 2-D walker student: {str(err).splitlines()[0]}") from None
        controller, who = policy_controller(student), f"the student in {path} (seed 0, deterministic)"

    print(f"{who} on {len(names)} named level(s), first episode, {steps} steps at most (compiling first)...", flush=True)
    stats, bodies, starts = play(env, names, steps, controller, theta, int(get("seed")))
    report(env, names, stats, bodies, starts, None if get("no_gif") else pathlib.Path(get("out")), every)
    return 0


def play(env, names, steps: int, controller, theta=None, seed: int = 0):
    """``make_rollout`` on the named levels, level i with key i of ``PRNGKey(seed)``; numpy stats."""
    import jax
    import jax.numpy as jnp

    from envs.walker.levels import LEVELS

    params = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[LEVELS[n]() for n in names])
    keys = jax.random.split(jax.random.PRNGKey(seed), len(names))
    stats, bodies, starts = make_rollout(env, steps, controller)(keys, params, theta)
    return jax.tree_util.tree_map(np.asarray, stats), bodies, starts


def report(env, names, stats, bodies, starts, out: pathlib.Path | None, every: int) -> None:
    """Print the table; with ``out``, write one GIF per level, a frame every ``every`` steps up to its end."""
    from envs.rendering import save_gif, unstack

    print(f"{'level':<16}{'return':>10}{'length':>8}  {'outcome':<11}{'distance (m)':>13}")
    for i, name in enumerate(names):
        dist = float(stats["x"][i] - stats["x0"][i])
        print(f"{name:<16}{float(stats['ret'][i]):>10.1f}{int(stats['length'][i]):>8d}  {outcome(stats, i):<11}{dist:>13.2f}")
    if out is None:
        return
    for i, name in enumerate(names):
        start = unstack(starts, i)
        n = max(1, int(stats["length"][i]))
        frames = [frame(env, start, unstack(unstack(bodies, t), i), f"{name} t={t}") for t in range(0, n, every)]
        save_gif(frames, str(out / f"bipedal_{name}.gif"), fps=max(1, 50 // every))
    print(f"GIFs in {out}/ (one per level, a frame every {every} step(s))")


if __name__ == "__main__":
    from shed_jax.cli import errors as cli_errors  # a module: its ``report`` must not replace this one's

    try:
        code = run_demo()
    except cli_errors.UsageError as err:  # one line, as ``python -m shed_jax demo`` prints it
        cli_errors.report(err)
        code = err.code
    raise SystemExit(code)
