"""`python -m shed_jax demo`: roll out an environment's built-in controller on generated levels.

Each environment module listed in DEMOS exposes ``run_demo(args) -> int``; it prints a per-level
table (level parameters, return, length, outcome) and writes a GIF of one episode under --out.
"""
from __future__ import annotations

import importlib

DEMOS = {"lander": "envs.lander.demo", "lander-continuous": "envs.lander.demo", "walker": "envs.walker.demo"}


def add_arguments(parser) -> None:
    parser.add_argument("--env", choices=sorted(DEMOS), default="lander", help="environment to demo")
    parser.add_argument("--levels", type=int, default=8, help="number of generated levels (wind on for half)")
    parser.add_argument("--seed", type=int, default=0, help="root PRNG seed")
    parser.add_argument("--out", default=None, help="output directory (default runs/demo-<env>/)")


def main(args) -> int:
    if args.levels < 1:
        from shed_jax.cli.errors import UsageError

        raise UsageError(f"--levels must be >= 1, got {args.levels}")
    module_name = DEMOS[args.env]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name is not None and module_name.startswith(err.name):
            print(f"demo for {args.env!r} is not available: module {module_name} is missing")
            return 1
        raise
    if not hasattr(module, "run_demo"):
        print(f"demo for {args.env!r} is not available: {module_name} has no run_demo(args)")
        return 1
    return int(module.run_demo(args) or 0)
