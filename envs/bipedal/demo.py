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
    from shed_jax.cli.errors import Parser  # one-line usage errors, as the shared CLI's

    ap = Parser(prog="python -m envs.bipedal.demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--levels", default=",".join(DEFAULT_LEVELS),
                    help="comma-separated names of envs.walker.levels.LEVELS, or a number N: the first N of "
                         + ", ".join(DEMO_ORDER))
    ap.add_argument("--policy", default=None, help="a policy.msgpack of 'python -m shed_jax ppo --env bipedal' "
                    "(its first seed, deterministic) instead of Gymnasium's gait")
    ap.add_argument("--steps", type=int, default=600, help="steps per level at most (the first episode only)")
    ap.add_argument("--seed", type=int, default=0, help="root PRNG seed (terrains and the start push; a level's "
                    "draw depends on its name, not its place in --levels)")
    ap.add_argument("--out", default="runs/demo-bipedal", help="where the GIFs go")
    ap.add_argument("--frame-every", type=int, default=3, help="draw every k-th step (and the last)")
    ap.add_argument("--no-gif", action="store_true", help="print the table only")
    return ap


def level_names(levels) -> list[str]:
    """``--levels``: a count N (the first N of ``DEMO_ORDER``) or comma-separated names; UsageError
    naming the unknown ones."""
    from envs.walker.levels import LEVELS
    from shed_jax.cli.errors import UsageError

    text = str(levels).strip()
    if text.isdigit():
        if int(text) < 1:
            raise UsageError(f"--levels must be >= 1 or level names, got {text}")
        return list(DEMO_ORDER[: min(int(text), len(DEMO_ORDER))])
    names = [n for n in text.split(",") if n]
    unknown = [n for n in names if n not in LEVELS]
    if unknown or not names:
        raise UsageError(f"unknown level(s) {', '.join(unknown) or '(none given)'}; known: {', '.join(sorted(LEVELS))}")
    return names


def make_rollout(env, steps: int, controller):
    """A jitted ``(keys [N], params [N], theta) -> (stats [N], trace [T, N], bodies [T + 1, N], start
    states [N])``: the first episode of ``controller`` (``envs.bipedal.parity``'s form) on each level,
    ``steps`` steps at most. ``stats``: return, length, fell (the -100 ending), terminated, done, the
    hull's x at the start and at the episode's end (or after the last step). ``trace``: each step's
    reward, done and x. ``bodies[t]``: the solver's bodies after t steps, enough to draw a frame with
    the start state's terrain (``frame``)."""
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
            return (obs2, s2, h2, a2, stats), (dict(reward=reward, done=done, x=info["x"]), s2.world.bodies)

        a, h = first(theta, obs)
        (_, s, _, _, stats), (trace, bodies) = jax.lax.scan(body, (obs, state, h, a, stats0), jax.random.split(k1, steps))
        # not ended within ``steps``: the return and length so far
        stats["ret"] = jnp.where(stats["done"], stats["ret"], s.episode_return)
        stats["length"] = jnp.where(stats["done"], stats["length"], s.time)
        bodies = jax.tree_util.tree_map(lambda b0, b: jnp.concatenate([b0[None], b]), state.world.bodies, bodies)
        return stats, trace, bodies, state

    return jax.jit(jax.vmap(one, in_axes=(0, 0, None), out_axes=(0, 1, 1, 0)))


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
    """How level i's episode ended: fell (the -100 ending), finished (past the finish line), time limit
    (the level's ``max_steps``), or running (still going after the demo's ``steps``)."""
    if not stats["done"][i]:
        return "running"
    if stats["fell"][i]:
        return "fell"
    return "finished" if stats["terminated"][i] else "time limit"


def frame_steps(length: int, every: int) -> list[int]:
    """The steps drawn: every ``every``-th from the start state, and the state after the last step."""
    ts = list(range(0, length + 1, every))
    return ts if ts[-1] == length else ts + [length]


def run_demo(args=None) -> int:
    """Entry point; ``args`` is an argparse Namespace (from the shared CLI) or an argv list."""
    from envs.bipedal.env import BipedalWalker
    from envs.bipedal.parity import heuristic_controller, policy_controller
    from envs.rendering import unstack
    from shed_jax.cli.errors import UsageError

    if args is None or isinstance(args, (list, tuple)):
        args = parser().parse_args(args)
    defaults = vars(parser().parse_args([]))
    get = lambda name: getattr(args, name, None) if getattr(args, name, None) is not None else defaults[name]  # noqa: E731
    names = level_names(get("levels"))
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
        from shed_jax.training import load_policy, policy_student

        try:
            student = policy_student(env, "bipedal", path)
            theta = unstack(load_policy(student, path), 0)
        except ValueError as err:  # another student, environment or no policy at all: named by load_policy
            raise UsageError(f"--policy: {err}") from None
        controller, who = policy_controller(student), f"the student in {path} (seed 0, deterministic)"

    print(f"{who} on {len(names)} named level(s), first episode, {steps} steps at most (compiling first)...", flush=True)
    stats, _, bodies, starts = play(env, names, steps, controller, theta, int(get("seed")))
    report(env, names, stats, bodies, starts, None if get("no_gif") else pathlib.Path(get("out")), every)
    return 0


def play(env, names, steps: int, controller, theta=None, seed: int = 0):
    """``make_rollout`` on the named levels; a level's key is ``PRNGKey(seed)`` folded with its index
    in the sorted level table, so its terrain does not depend on the other levels asked for. Returns
    numpy ``stats`` and ``trace``, and the bodies and start states as JAX arrays."""
    import jax
    import jax.numpy as jnp

    from envs.walker.levels import LEVELS

    params = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[LEVELS[n]() for n in names])
    table = sorted(LEVELS)
    keys = jnp.stack([jax.random.fold_in(jax.random.PRNGKey(seed), table.index(n)) for n in names])
    stats, trace, bodies, starts = make_rollout(env, steps, controller)(keys, params, theta)
    return jax.tree_util.tree_map(np.asarray, stats), jax.tree_util.tree_map(np.asarray, trace), bodies, starts


def report(env, names, stats, bodies, starts, out: pathlib.Path | None, every: int) -> None:
    """Print the table; with ``out``, write one GIF per level (``frame_steps``)."""
    from envs.rendering import save_gif, unstack

    print(f"{'level':<16}{'return':>10}{'length':>8}  {'outcome':<11}{'distance (m)':>13}")
    for i, name in enumerate(names):
        dist = float(stats["x"][i] - stats["x0"][i])
        print(f"{name:<16}{float(stats['ret'][i]):>10.1f}{int(stats['length'][i]):>8d}  {outcome(stats, i):<11}{dist:>13.2f}")
    if out is None:
        return
    for i, name in enumerate(names):
        start = unstack(starts, i)
        frames = [frame(env, start, unstack(unstack(bodies, t), i), f"{name} t={t}")
                  for t in frame_steps(int(stats["length"][i]), every)]
        save_gif(frames, str(out / f"bipedal_{name}.gif"), fps=max(1, 50 // every))
    print(f"GIFs in {out}/ (one per level, a frame every {every} step(s) and the last)")


if __name__ == "__main__":
    from shed_jax.cli import errors as cli_errors  # a module: its ``report`` must not replace this one's

    try:
        code = run_demo()
    except cli_errors.UsageError as err:  # one line, as ``python -m shed_jax demo`` prints it
        cli_errors.report(err)
        code = err.code
    raise SystemExit(code)
