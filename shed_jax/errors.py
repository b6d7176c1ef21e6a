"""The errors a run or sweep reports to its user, and the exit statuses they map to.

* :class:`UsageError`: a user error (a bad flag value, an unknown ``--set`` key, a directory that
  holds another run). ``str(err)`` is one line naming the field and what is allowed; ``err.code`` is
  the exit status (2, as argparse's usage errors). It is a ``SystemExit``, so code that does not
  catch it still stops without a traceback.
* :class:`WriteFailedError`: a file of a run could not be written (disk full, ...); its line names
  the stage and what is safe on disk; exit status 74.
* Checkpoint errors are ``shed_jax.checkpoint.CheckpointError`` (exit status 2 at the command line).

How ``python -m shed_jax`` prints them is ``shed_jax/cli/errors.py``; the exit statuses of every
command are listed in docs/running.md ("Exit codes").
"""
from __future__ import annotations

import errno
import os

EXIT_USAGE = 2  # bad input: a flag, a level file, a run directory or checkpoint that cannot be used
EXIT_CHECKPOINT = 2  # a checkpoint could not be used (missing, damaged, other configuration)
EXIT_NONFINITE = 3  # the non-finite guard stopped the run
EXIT_IO = 74  # a file could not be written (disk full, ...): what is safe on disk is named (EX_IOERR)
EXIT_STOPPED = 75  # --stop-after / --time-limit reached; resumable (EX_TEMPFAIL)


class UsageError(SystemExit):
    """A user error: ``str(err)`` is the one-line message, ``err.code`` the exit status (2 by default)."""

    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(code)
        self.message = " ".join(str(message).split())  # one line, whatever the parts held

    def __str__(self) -> str:
        return self.message


class WriteFailedError(UsageError):
    """A write of a run failed; the message names the stage and what is safe on disk (exit 74).

    The failed write's own exception is the ``__cause__``.
    """

    def __init__(self, message: str):
        super().__init__(message, EXIT_IO)


def one_line(text: str, limit: int = 400) -> str:
    """``text`` on one line, without TensorStore's spec dumps, cut to ``limit`` characters."""
    text = str(text).split("[tensorstore_spec=")[0]
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


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


def is_write_failure(err: BaseException) -> bool:
    """An OSError (raised, wrapped or chained) or a full disk described in text only."""
    return os_error_in(err) is not None or is_disk_full(err)


def io_reason(err: BaseException) -> str:
    """A short description of a failed write: 'disk full (No space left on device)' or the OSError."""
    found = os_error_in(err)
    if is_disk_full(err):
        return f"disk full ({os.strerror(found.errno) if found is not None else 'No space left on device'})"
    if found is not None:
        where = f" ({found.filename})" if found.filename else ""
        return f"{found.strerror or type(found).__name__}{where}"
    return one_line(f"{type(err).__name__}: {err}", limit=200)
