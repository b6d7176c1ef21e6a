"""A carried run's piece log (a device call's ``run.log``) made readable for its folder's ``pieceN.log``:
carriage returns become line breaks (tqdm redraws its bar with them), JAX's tracing-cache explanations
(``JAX_EXPLAIN_CACHE_MISSES``) are removed, and of the compiler's debug output
(``JAX_DEBUG_LOG_MODULES=jax._src.compiler``, which ``run_piece.sh`` sets under ``AOT_GATE=1``, each
line printed up to three times by JAX's handlers) only the persistent-cache hits and misses are kept,
once each. Progress bars stay: ``experiments.piece_record`` times the pieces from them. A first line
says what was removed.

    python -m experiments.piece_log RUN_LOG docs/results/FOLDER/piece3.log --name piece3
"""
from __future__ import annotations

import argparse
import pathlib
import sys

_EXPLAINED = "TRACING CACHE MISS"
_COMPILER = "DEBUG:jax._src.compiler:"  # the short form of the compiler's debug lines; the others repeat it
_KEPT_DEBUG = ("cache hit", "CACHE MISS")


def readable(text: str) -> tuple[list[str], int, int]:
    """The log's lines to keep, and how many lines of tracing explanations and of debug output went."""
    kept: list[str] = []
    explained = debug = 0
    in_explanation = False
    for line in text.replace("\r", "\n").split("\n"):
        if in_explanation and line.startswith("  "):  # an explanation's indented body
            explained += 1
            continue
        in_explanation = False
        if _EXPLAINED in line:
            explained += 1
            in_explanation = True
            continue
        if line.startswith("DEBUG:"):
            if not (line.startswith(_COMPILER) and any(k in line for k in _KEPT_DEBUG)) or (kept and kept[-1] == line):
                debug += 1
                continue
        if not line.strip():
            continue
        kept.append(line)
    return kept, explained, debug


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.piece_log", description=__doc__.split("\n\n")[0])
    p.add_argument("run_log", help="the run.log a piece returned")
    p.add_argument("out", help="where the readable log goes (e.g. the run folder's pieceN.log)")
    p.add_argument("--name", required=True, help="the piece's name for the first line (e.g. piece3)")
    a = p.parse_args(argv)
    src = pathlib.Path(a.run_log)
    if not src.is_file():
        print(f"piece_log: no log at {src}", file=sys.stderr)
        return 2
    kept, explained, debug = readable(src.read_text(errors="replace"))
    removed = []
    if explained:
        removed.append(f"{explained} lines of JAX's tracing-cache explanations")
    if debug:
        removed.append(f"{debug} lines of JAX's compiler debug output (its cache hits and misses kept once each)")
    head = f"[{a.name}: the run's log, carriage returns as line breaks"
    head += (", with " + " and ".join(removed) + " removed]") if removed else "]"
    pathlib.Path(a.out).write_text("\n".join([head, *kept]) + "\n")
    print(f"piece_log: {a.out}: {len(kept)} lines kept, {explained + debug} removed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
