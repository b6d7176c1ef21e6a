"""Import ``mujoco.mjx`` without the two lines it prints when NVIDIA Warp is not installed.

``mujoco.mjx.warp``, which MJX imports itself, tries the optional ``warp`` package and *prints* (it
neither logs nor warns) ``Failed to import warp: No module named 'warp'`` and ``Failed to import
mujoco_warp: No module named 'warp'``. The walker runs MJX's JAX implementation (``impl="jax"``),
which needs no Warp, so exactly these two lines are dropped; anything else printed during the
import (a Warp that is installed but broken, say) passes through unchanged.
"""
from __future__ import annotations

import contextlib
import io
import re
import sys

_WARP_MISSING = re.compile(r"Failed to import (mujoco_)?warp: No module named 'warp'")


def import_mjx():
    """``mujoco.mjx``, imported once with the Warp-missing lines filtered from stdout."""
    if "mujoco.mjx" in sys.modules:
        return sys.modules["mujoco.mjx"]
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            from mujoco import mjx
    finally:
        lines = captured.getvalue().splitlines(keepends=True)
        sys.stdout.write("".join(line for line in lines if not _WARP_MISSING.fullmatch(line.rstrip("\n"))))
    return mjx
