"""Command line: ``python -m shed_jax <command> ...``.

Each command lives in ``shed_jax/cli/<command>.py`` and defines ``add_arguments(parser)`` and
``main(args) -> int``; they are imported only when used, so ``--help`` stays fast.

User errors are one line on stderr with exit code 2, bugs keep their traceback; ``--debug`` or
``SHED_JAX_DEBUG=1`` shows tracebacks for everything (shed_jax/cli/errors.py).
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import threading

from shed_jax.xla_cpu import apply_cpu_guard
from shed_jax.xla_gpu import apply_gpu_codegen

apply_cpu_guard()  # before any JAX computation (shed_jax/xla_cpu.py says why)
apply_gpu_codegen()  # fused multiply-adds on a GPU, as on a CPU (shed_jax/xla_gpu.py)

COMMANDS = {
    "demo": "roll out a built-in controller (or a saved 2-D walker student) on a few levels; print a table and write GIFs",
    "ppo": "train the PPO student on fixed levels",
    "run": "run a UED method (the paper's shed and hmdp, the learning teachers hmdp-x and shed-x, and the baselines dr, paired, accel, accel-norevisit, plr)",
    "eval": "evaluate a saved student on a level set",
    "sweep": "vmapped sweep over seeds x hyperparameters x methods",
}
DEBUG_HELP = "print the traceback of every error, user errors included (or set SHED_JAX_DEBUG=1)"


def main(argv=None) -> int:
    from shed_jax.cli import errors
    from shed_jax.runtime import missing_packages, missing_packages_line

    args_given = sys.argv[1:] if argv is None else list(argv)
    missing = missing_packages()
    if missing:  # before the commands' imports and any compile: not a traceback minutes into a run
        print(missing_packages_line(missing), file=sys.stderr)
        if not any(a in ("-h", "--help") for a in args_given):
            return errors.EXIT_USAGE  # help is still shown, for the commands that import without them

    parser = errors.Parser(prog="python -m shed_jax", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help=DEBUG_HELP)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    available, unavailable = {}, set()
    for name, help_text in COMMANDS.items():
        try:
            module = importlib.import_module(f"shed_jax.cli.{name}")
            if missing:  # its argument list may import what is missing (JAX, for the environments' names)
                module.add_arguments(argparse.ArgumentParser(add_help=False))
        except ModuleNotFoundError as err:
            if err.name != f"shed_jax.cli.{name}" and not missing:
                raise
            unavailable.add(name)  # not listed: its help needs the missing packages
            continue
        p = sub.add_parser(name, help=help_text, description=help_text)
        module.add_arguments(p)
        # SUPPRESS: the subcommand's default must not overwrite a --debug given before it
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=DEBUG_HELP)
        available[name] = module
    command = next((a for a in args_given if not a.startswith("-")), None)
    if command in unavailable:  # `COMMAND --help` without the packages: the line above says what to do
        return errors.EXIT_USAGE
    try:
        args = parser.parse_args(args_given)
    except SystemExit as err:  # --help (0) or a usage error argparse has printed as one line (2)
        return err.code if isinstance(err.code, int) else errors.EXIT_USAGE
    if args.command is None:
        parser.print_help()
        return 2
    from shed_jax.runtime import start_up

    start_up()  # compilation cache, backend line, GPU-unused warning (shed_jax/runtime.py)
    try:
        return int(available[args.command].main(args) or 0)
    except errors.UsageError as err:
        errors.report(err, args)
        return int(err.code)
    except SystemExit as err:  # a command's SystemExit("message"): a user error as well
        if isinstance(err.code, int):  # e.g. a second SIGTERM (143): returned, so that _exit ends the
            return err.code            # process at once while a worker thread is still inside XLA
        if err.code is None:
            raise
        errors.report(err, args)
        return errors.EXIT_USAGE
    except KeyboardInterrupt:  # Ctrl-C where a command does not handle it itself
        if errors.debug_enabled(args):
            raise
        print("\n[shed_jax] interrupted (SIGINT)", file=sys.stderr)
        return 130


def _exit(code: int) -> None:
    """Exit; at once (``os._exit``) after a signal stopped a start-up or while a compile of ``run`` still
    runs in its worker thread: XLA's threads may still be at work, and a normal interpreter shutdown
    would race them (``shed_jax/driver.py``, ``EXIT_AT_ONCE``)."""
    driver = sys.modules.get("shed_jax.driver")
    busy = [t.name for t in threading.enumerate() if t.name.startswith("shed_jax-") and t.is_alive()]
    if (driver is not None and driver.EXIT_AT_ONCE.is_set()) or busy:
        if busy:  # e.g. the final evaluation's compile begun during training, dropped by a time limit
            print(f"[shed_jax] exiting while {', '.join(busy)} still runs: its work is dropped", file=sys.stderr)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    _exit(main())
