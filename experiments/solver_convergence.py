"""How many of Box2D's passes a 2-D walker step needs, world by world: can a fused kernel stop early?

The fused solver kernels run one world per GPU thread in blocks of ``fused.BLOCK`` (128) worlds, and a
block stops a loop only when every world in it is done; a step's time is its slowest block's. This
plays Gymnasium's scripted gait on every named level (``envs.bipedal.demo.play``, the XLA solver on
this host) and records, per world and step:

* velocity passes (180): whether the carry reaches an exact fixed point (a pass that changes nothing,
  after which every pass changes nothing: a stop there would be bit-exact), and the last pass whose
  largest change of a body velocity exceeds each tolerance (a stop there would not be exact);
* position passes (60): the pass after which Box2D's own "solved" test holds (60 where it never does);
* the manifolds with contact points in the velocity passes (what packed slots must hold).

    python -m experiments.solver_convergence --steps 200 --out docs/results/bipedal_speed/RECORD.json

The block-level figures assume worlds independent: P(a block has a world that needs every pass) =
1 - (1 - p)^128 for a per-world rate p.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys

import numpy as np

TOLS = (1e-3, 1e-4, 1e-5, 1e-6)
VELOCITY, POSITION = "_velocity_pass_edges", "_position_pass_edges"


def measure(steps: int, seed: int = 0) -> dict:
    """Play ``steps`` steps on every named level and return the per-world-step arrays (numpy)."""
    import jax
    import jax.numpy as jnp
    from jax import lax

    from envs.bipedal import demo
    from envs.bipedal.env import BipedalWalker
    from envs.bipedal.parity import heuristic_controller
    from envs.physics2d import fused
    from envs.walker.levels import LEVELS
    from experiments.solver_kernel_bench import _name, _patched

    rec: dict[str, list] = {"fixed": [], "last_over": [], "manifolds": [], "solved_at": []}

    def keep(name, *xs):
        rec[name].append(np.stack([np.asarray(x).ravel() for x in xs], -1))

    def loop(n, body, consts, carry, *, mode="auto", unroll=1, done=None, lanes=1):
        name = _name(body)
        if name == POSITION and done is not None:
            def it(i, st):
                x, at = st
                y = body(consts, x)
                return y, jnp.where((at == n) & (done(y) > 0.5), i + 1, at)
            x, at = lax.fori_loop(0, n, it, (carry, jnp.int32(n)))
            jax.debug.callback(lambda a: keep("solved_at", a), at)
            return x
        if name != VELOCITY or "on" not in consts:  # (the reset's step has no manifolds: left out)
            return orig(n, body, consts, carry, mode=mode, unroll=unroll, done=done, lanes=lanes)
        on = jnp.stack(consts["on"]) > 0.5  # per contact point, two per manifold
        jax.debug.callback(lambda m: keep("manifolds", m), jnp.sum(on[0::2] | on[1::2]))

        def it(i, st):
            x, fixed, last = st
            y = body(consts, x)
            same = jnp.bool_(True)
            for a, b in zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)):
                same = same & (a == b)
            change = jnp.float32(0)
            for a, b in zip(jax.tree_util.tree_leaves(x[:2]), jax.tree_util.tree_leaves(y[:2])):  # velocities
                change = jnp.maximum(change, jnp.abs(a - b))
            fixed = jnp.where((fixed == n) & same, i, fixed)
            last = tuple(jnp.where(change > t, i + 1, v) for t, v in zip(TOLS, last))
            return y, fixed, last

        x, fixed, last = lax.fori_loop(0, n, it, (carry, jnp.int32(n), tuple(jnp.int32(0) for _ in TOLS)))
        jax.debug.callback(lambda f, *ls: (keep("fixed", f), keep("last_over", *ls)), fixed, *last)
        return x

    env = BipedalWalker()
    with _patched(loop) as orig:
        demo.play(env, sorted(LEVELS), steps, heuristic_controller(), None, seed)
    return {k: np.concatenate(v) for k, v in rec.items()}


def summarise(arrays: dict, velocity_passes: int, position_passes: int, block: int) -> dict:
    """The record's figures from ``measure``'s arrays."""
    pct = lambda x: {str(q): float(np.percentile(x, q)) for q in (50, 90, 99, 100)}  # noqa: E731
    block_p = lambda p: round(1.0 - (1.0 - p) ** block, 4)  # noqa: E731
    fixed = arrays["fixed"][:, 0]
    never_fixed = float(np.mean(fixed == velocity_passes))
    solved = arrays["solved_at"][:, 0]
    unsolved = float(np.mean(solved == position_passes))
    man = arrays["manifolds"][:, 0].astype(int)
    hist = np.bincount(man, minlength=8)
    out = {
        "world_steps": int(fixed.size),
        "velocity": {
            "passes": velocity_passes,
            "exact_fixed_point_never": round(never_fixed, 4),
            "exact_fixed_point_pass_percentiles": pct(fixed),
            "block_has_a_world_without_fixed_point": block_p(never_fixed),
            "last_pass_over_tolerance_percentiles": {str(t): pct(arrays["last_over"][:, j]) for j, t in enumerate(TOLS)},
            # a change over the tolerance in the last pass: no stop at that tolerance for that world
            "still_over_tolerance_at_the_last_pass": {str(t): round(float(np.mean(arrays["last_over"][:, j] == velocity_passes)), 4)
                                                      for j, t in enumerate(TOLS)},
        },
        "position": {
            "passes": position_passes,
            "world_steps": int(solved.size),  # the reset's step too, where it has position passes
            "never_solved": round(unsolved, 4),
            "solved_at_percentiles": pct(solved),
            "block_has_a_world_never_solved": block_p(unsolved),
        },
        "manifolds_with_points_histogram": [int(h) for h in hist],
        "manifolds_with_points_over": {str(m): round(float(np.mean(man > m)), 5) for m in (2, 3, 4, 5, 6)},
    }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.solver_convergence", description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=200, help="steps per level (default 200)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True, help="the JSON record to write")
    args = ap.parse_args(argv)
    if args.steps < 1:
        print(f"solver_convergence: --steps must be >= 1, got {args.steps}", file=sys.stderr)
        return 2
    import jax

    from envs.bipedal import model as M
    from envs.physics2d import fused
    from experiments.aot_cache import _cpu_model

    arrays = measure(args.steps, args.seed)
    record = {
        "what": "passes a 2-D walker step needs per world, Gymnasium's scripted gait on every named level",
        "device": f"cpu ({_cpu_model()}, {os.cpu_count()} cores), jax {jax.__version__}",
        "command": "python -m experiments.solver_convergence " + " ".join(sys.argv[1:] if argv is None else argv),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "block": fused.BLOCK,
        **summarise(arrays, M.VELOCITY_ITERATIONS, M.POSITION_ITERATIONS, fused.BLOCK),
    }
    with open(args.out, "w") as f:
        json.dump(record, f, indent=1)
    v, p = record["velocity"], record["position"]
    print(f"{record['world_steps']} world-steps; velocity passes: no exact fixed point in {v['exact_fixed_point_never']:.1%} "
          f"(a block of {fused.BLOCK}: {v['block_has_a_world_without_fixed_point']:.1%}); position passes never solved in "
          f"{p['never_solved']:.1%} (a block: {p['block_has_a_world_never_solved']:.1%}); wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
