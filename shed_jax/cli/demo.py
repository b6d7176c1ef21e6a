"""`python -m shed_jax demo`: roll out an environment's built-in controller on a few levels.

Each environment module listed in DEMOS exposes ``run_demo(args) -> int``; it prints a per-level
table (return, length, outcome; the lander's also its generated parameters, the walkers' the
distance walked on named levels) and writes GIFs under --out. A
module that can play a saved student instead of its built-in controller sets ``ACCEPTS_POLICY``.
"""
from __future__ import annotations

import importlib

DEMOS = {"lander": "envs.lander.demo", "lander-continuous": "envs.lander.demo", "walker": "envs.walker.demo",
         "bipedal": "envs.bipedal.demo"}


def add_arguments(parser) -> None:
    parser.add_argument("--env", choices=sorted(DEMOS), default="lander", help="environment to demo")
    parser.add_argument("--levels", type=int, default=8,
                        help="number of levels: generated ones on the lander (wind on for half), the first named ones on the walkers")
    parser.add_argument("--seed", type=int, default=0, help="root PRNG seed")
    parser.add_argument("--out", default=None, help="output directory (default runs/demo-<env>/)")
    parser.add_argument("--policy", default=None, metavar="FILE",
                        help="a saved student (policy.msgpack of 'python -m shed_jax ppo') instead of the built-in "
                             "controller; --env bipedal only")


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
    if args.policy is not None and not getattr(module, "ACCEPTS_POLICY", False):
        from shed_jax.cli.errors import UsageError

        takes = sorted(name for name, m in DEMOS.items() if getattr(importlib.import_module(m), "ACCEPTS_POLICY", False))
        raise UsageError(f"--policy: the {args.env} demo plays its built-in controller only; --policy works with "
                         f"--env {', '.join(takes)}")
    return int(module.run_demo(args) or 0)
