"""`python -m shed_jax ppo`: train the PPO student on one fixed level, S seeds vmapped.

    python -m shed_jax ppo --env lander --total-steps 3000000 --seeds 8 --out runs/ppo_lander

Writes DIR/summary.json and DIR/learning_curve.png (``shed_jax.training.train_fixed_level``).
"""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    import envs

    parser.add_argument("--env", required=True, choices=envs.registered(), help="registered environment")
    parser.add_argument("--level", default=None, help="named level from the env module's LEVELS (default: the env's default level)")
    parser.add_argument("--total-steps", type=int, default=1_000_000, help="env steps of training per seed")
    parser.add_argument("--seeds", type=int, default=1, help="number of vmapped seeds")
    parser.add_argument("--seed", type=int, default=0, help="root seed")
    parser.add_argument("--chunks", type=int, default=20, help="progress/record chunks (the same compiled call each)")
    parser.add_argument("--eval-episodes", type=int, default=16, help="episodes per seed for the final evaluation")
    parser.add_argument("--lr", type=float, default=None, help="override the preset learning rate")
    parser.add_argument("--num-envs", type=int, default=None, help="override the preset number of envs")
    parser.add_argument("--ppo", action="append", default=[], metavar="KEY=VALUE",
                        help="override a field of the student's PPOConfig or PPOHyperparams (repeatable), as for run, "
                             "e.g. --ppo reset_draw=per_step")
    parser.add_argument("--out", default=None, help="output directory (default runs/ppo_<env>)")


def ppo_config(args):
    """The student config the command trains (``training.fixed_level_config``); UsageError naming a bad value."""
    from shed_jax.errors import UsageError
    from shed_jax.training import fixed_level_config

    try:
        return fixed_level_config(args)
    except ValueError as err:
        raise UsageError(str(err)) from None


def main(args) -> int:
    import envs
    from shed_jax.errors import UsageError
    from shed_jax.training import resolve_level, train_fixed_level

    if args.total_steps < 1 or args.seeds < 1:
        raise UsageError(f"--total-steps and --seeds must be >= 1, got {args.total_steps} and {args.seeds}")
    try:  # a bad --level is the user's: one line, before anything is built or compiled
        resolve_level(envs.make(args.env), args.level)
    except ValueError as e:
        raise UsageError(f"--level: {e}") from None
    ppo_config(args)  # a bad --ppo/--lr/--num-envs: one line, before anything is built
    train_fixed_level(args)
    return 0
