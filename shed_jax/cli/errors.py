"""How the command line reports what went wrong: one line for the user's mistakes, tracebacks for bugs.

* A user error (a bad flag value, an unknown ``--set`` key, a directory that holds another run, a
  checkpoint that cannot be used) is one line on stderr, ``shed_jax: error: ...``, naming the field
  and what is allowed, with exit code 2 (as argparse's usage errors). The commands raise
  :class:`UsageError` for these; ``python -m shed_jax`` (``shed_jax/__main__.py``) prints it.
* Anything else is a bug and keeps its traceback (exit 1).
* ``--debug`` or ``SHED_JAX_DEBUG=1`` prints the traceback of user errors too.

The exit codes of all commands are listed in docs/running.md ("Exit codes").
"""
from __future__ import annotations

import argparse
import errno
import os
import sys
import traceback

EXIT_USAGE = 2  # bad input: a flag, a level file, a run directory or checkpoint that cannot be used
EXIT_IO = 74  # a file could not be written (disk full, ...): what is safe on disk is named (EX_IOERR)

PREFIX = "shed_jax: error:"
DEBUG_ENV = "SHED_JAX_DEBUG"


class UsageError(SystemExit):
    """A user error: ``str(err)`` is the one-line message, ``err.code`` the exit status (2 by default).

    A ``SystemExit`` so that code which does not catch it still stops without a traceback.
    """

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(code)
        self.message = " ".join(str(message).split())  # one line, whatever the parts held

    def __str__(self) -> str:
        return self.message


def debug_enabled(args=None) -> bool:
    """``--debug`` on the command line or ``SHED_JAX_DEBUG`` set to anything but '', '0', 'false', 'no'."""
    if args is not None and getattr(args, "debug", False):
        return True
    return os.environ.get(DEBUG_ENV, "").strip().lower() not in ("", "0", "false", "no")


def one_line(text: str, limit: int = 400) -> str:
    """``text`` on one line, without TensorStore's spec dumps, cut to ``limit`` characters."""
    text = str(text).split("[tensorstore_spec=")[0]
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def report(err: BaseException, args=None, prefix: str = PREFIX) -> None:
    """Print ``err`` as one line on stderr (after its traceback when debugging)."""
    if debug_enabled(args):
        traceback.print_exception(err, file=sys.stderr)
    print(f"{prefix} {one_line(str(err), limit=2000)}", file=sys.stderr, flush=True)


def os_error_in(err: BaseException | None) -> OSError | None:
    """The OSError that caused ``err``: itself, or one in its cause/context chain or exception group.

    orbax raises errors of its own (or a bare ``Exception``) around the ``OSError`` of a failed write.
    """
    seen = set()
    stack = [err]
    while stack:
        e = stack.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno is not None:
            return e
        stack.extend(getattr(e, "exceptions", ()) or ())
        stack.extend((e.__cause__, e.__context__))
    return None


def is_disk_full(err: BaseException | None) -> bool:
    """Whether ``err`` comes from a full disk or quota (ENOSPC/EDQUOT), raised directly or wrapped."""
    found = os_error_in(err)
    if found is not None and found.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    e, seen = err, set()
    while e is not None and id(e) not in seen:  # wrapped as text only (e.g. by TensorStore)
        seen.add(id(e))
        if "No space left on device" in str(e) or "Disk quota exceeded" in str(e):
            return True
        e = e.__cause__ or e.__context__
    return False


def io_reason(err: BaseException) -> str:
    """A short description of a failed write: 'disk full (No space left on device)' or the OSError."""
    found = os_error_in(err)
    if is_disk_full(err):
        return f"disk full ({os.strerror(found.errno) if found is not None else 'No space left on device'})"
    if found is not None:
        where = f" ({found.filename})" if found.filename else ""
        return f"{found.strerror or type(found).__name__}{where}"
    return one_line(f"{type(err).__name__}: {err}", limit=200)


# ---------------------------------------------------------------------------------------------
# argparse helpers
# ---------------------------------------------------------------------------------------------

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
