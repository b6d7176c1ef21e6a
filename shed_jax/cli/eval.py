"""``python -m shed_jax eval``: evaluate the students of a saved run on a level set.

    python -m shed_jax eval --run runs/lander-shed-paper-20250101-120000 --levels test --episodes 100

Loads the run's latest checkpoint (or ``--step``), rebuilds its experiment from the configuration
saved with it, evaluates every seed's student for ``--episodes`` episodes per level and prints one
row per level (mean ± SE over seeds, solved rate, CVaR 10 %; ``shed_jax/evaluation.py`` defines
them and the level sets). Writes ``DIR/eval_<levels>.json``.
"""
from __future__ import annotations

import json
import pathlib

from shed_jax.errors import EXIT_USAGE

EXIT_BAD_INPUT = EXIT_USAGE


def add_arguments(p) -> None:
    p.add_argument("--run", required=True, metavar="DIR", help="run directory (with checkpoints/)")
    p.add_argument("--levels", default="test", metavar="test|named|FILE",
                   help="level set: the run's test set, the env's named levels, or a JSON file (default test)")
    p.add_argument("--episodes", type=int, default=10, help="episodes per level and seed (default 10)")
    p.add_argument("--max-steps", type=int, default=None, help="episode cap (default: each level's own time limit)")
    p.add_argument("--deterministic", action="store_true", help="greedy actions (default: sample the policy)")
    p.add_argument("--seed", type=int, default=0, help="evaluation key; seed i of the run uses fold_in(seed, i)")
    p.add_argument("--solved-threshold", type=float, default=None,
                   help="return above which an episode counts as solved (default: lander 200, walker 230)")
    p.add_argument("--step", type=int, default=None, help="checkpoint step to load (default: the latest)")
    p.add_argument("--out", default=None, help="output JSON (default DIR/eval_<levels>.json)")


def main(args) -> int:
    from shed_jax.checkpoint import CheckpointError
    from shed_jax.cli import errors
    from shed_jax.evaluation import LevelFileError

    if args.episodes < 1:
        raise errors.UsageError(f"--episodes must be an integer >= 1, got {args.episodes}")
    if args.max_steps is not None and args.max_steps < 1:
        raise errors.UsageError(f"--max-steps must be an integer >= 1, got {args.max_steps}")
    try:
        return _main(args)
    except CheckpointError as err:
        errors.report(err, args)
        return EXIT_BAD_INPUT
    except LevelFileError as err:
        errors.report(err, args, prefix=f"{errors.PREFIX} --levels:")
        return EXIT_BAD_INPUT


def _main(args) -> int:
    from shed_jax import evaluation

    run_dir = pathlib.Path(args.run)
    exp, env, student, tests, num_seeds, step, students = evaluation.restore_students(run_dir, args.step)
    from shed_jax.driver import heartbeat_wait

    resolved = evaluation.resolve_levels(args.levels, env, exp, tests)
    print(f"[shed_jax] evaluating {run_dir} at budget step {step}: {len(resolved[1])} level(s) x {num_seeds} seed(s) x "
          f"{args.episodes} episode(s) (compiling first)...", flush=True)
    body, text = evaluation.evaluate_students(exp, env, student, students, num_seeds, resolved, episodes=args.episodes,
                                              max_steps=args.max_steps, deterministic=args.deterministic,
                                              seed=args.seed, solved_threshold=args.solved_threshold, wait=heartbeat_wait)
    threshold = body["solved_threshold"]
    print(f"[shed_jax] {exp.method} on {exp.env}, {run_dir} at budget step {step}: {num_seeds} seed(s) x "
          f"{args.episodes} episode(s) per level, {'deterministic' if args.deterministic else 'stochastic'} policy, "
          f"levels {args.levels!r}" + ("" if threshold is not None else " (no solved threshold for this env: pass --solved-threshold)"))
    print(text)
    from shed_jax.runtime import provenance

    result = {"run": str(run_dir), "checkpoint_step": step, **provenance("shed_jax"), **body, "levels_arg": args.levels}
    out = pathlib.Path(args.out) if args.out else run_dir / f"eval_{body['levels']}.json"
    out.write_text(json.dumps(result, indent=2))
    print(f"[shed_jax] wrote {out}")
    return 0
