"""How the command line reports what went wrong: one line for the user's mistakes, tracebacks for bugs.

* A user error (``shed_jax.errors.UsageError``: a bad flag value, an unknown ``--set`` key, a
  directory that holds another run; a checkpoint that cannot be used; a failed write) is one line on
  stderr, ``shed_jax: error: ...``, naming the field and what is allowed, with the error's exit code
  (2 for usage errors, as argparse's). ``python -m shed_jax`` (``shed_jax/__main__.py``) prints it.
* Anything else is a bug and keeps its traceback (exit 1).
* ``--debug`` or ``SHED_JAX_DEBUG=1`` prints the traceback of user errors too.

The exit codes of all commands are listed in docs/running.md ("Exit codes").
"""
from __future__ import annotations

import argparse
import os
import sys
import traceback

from shed_jax.errors import EXIT_USAGE, UsageError, one_line  # noqa: F401 - the commands' vocabulary

PREFIX = "shed_jax: error:"
DEBUG_ENV = "SHED_JAX_DEBUG"


def debug_enabled(args=None) -> bool:
    """``--debug`` on the command line or ``SHED_JAX_DEBUG`` set to anything but '', '0', 'false', 'no'."""
    if args is not None and getattr(args, "debug", False):
        return True
    return os.environ.get(DEBUG_ENV, "").strip().lower() not in ("", "0", "false", "no")


def report(err: BaseException, args=None, prefix: str = PREFIX) -> None:
    """Print ``err`` as one line on stderr (after its traceback when debugging)."""
    if debug_enabled(args):
        traceback.print_exception(err, file=sys.stderr)
    print(f"{prefix} {one_line(str(err), limit=2000)}", file=sys.stderr, flush=True)


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``shed_jax: error: argument --seeds: ... (see ... --help)``, exit 2."""

    def error(self, message):  # noqa: D401 - argparse's hook
        self.exit(EXIT_USAGE, f"{PREFIX} {one_line(message)} (`{self.prog} --help` lists the options)\n")


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (counts: seeds, episodes, steps, chunk sizes, ...)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite number >= 0 (durations)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text!r}") from None
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value
