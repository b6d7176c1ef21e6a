"""Command line: ``python -m shed_jax <command> ...``.

Each command lives in ``shed_jax/cli/<command>.py`` and defines ``add_arguments(parser)`` and
``main(args) -> int``; they are imported only when used, so ``--help`` stays fast.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from shed_jax.xla_cpu import apply_cpu_guard

apply_cpu_guard()  # before any JAX computation (shed_jax/xla_cpu.py says why)

COMMANDS = {
    "demo": "roll out a built-in controller on generated levels; print a table and write a GIF",
    "ppo": "train the PPO student on fixed levels",
    "run": "run a UED method (shed, hmdp, dr, paired, accel, accel-norevisit, plr)",
    "eval": "evaluate a saved student on a level set",
    "sweep": "vmapped sweep over seeds x hyperparameters x methods",
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m shed_jax", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    available = {}
    for name, help_text in COMMANDS.items():
        try:
            module = importlib.import_module(f"shed_jax.cli.{name}")
        except ModuleNotFoundError as err:
            if err.name != f"shed_jax.cli.{name}":
                raise
            continue
        p = sub.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(p)
        available[name] = module
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    from shed_jax.runtime import start_up

    start_up()  # compilation cache, backend line, GPU-unused warning (shed_jax/runtime.py)
    return int(available[args.command].main(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
