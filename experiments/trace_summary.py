"""The command line of ``shed_jax.profiling``: summarise a ``jax.profiler`` trace, or turn a summary
(written by ``python -m shed_jax run --profile-chunk`` or by a carried piece's ``AOT_TRACE_CALL``)
into a record: its count classes named, the machine, command and date added.

    python -m experiments.trace_summary TRACE_DIR [--hlo PROGRAM.txt] [--out SUMMARY.json]
    python -m experiments.trace_summary SUMMARY.json --label 4000=evaluation ... --device D --command C --out RECORD.json
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import sys

from shed_jax.profiling import labelled, summarise_trace


def _labels(pairs: list[str]) -> dict[int, str]:
    labels = {}
    for pair in pairs:
        calls, sep, text = pair.partition("=")
        if not sep or not calls.isdigit() or not text:
            raise ValueError(f"--label takes CALLS=TEXT (a whole number of calls, then what ran that often), got '{pair}'")
        labels[int(calls)] = text
    return labels


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", help="the folder jax.profiler.start_trace wrote, or a summary (JSON) written "
                                   "by this tool or by aot_cache.py's AOT_TRACE_CALL, to label and record")
    ap.add_argument("--hlo", help="the traced program's HLO text (Compiled.as_text()), for op names")
    ap.add_argument("--label", action="append", default=[], metavar="CALLS=TEXT",
                    help="name the ops that ran CALLS times (e.g. 4000='the evaluation: 2 x 2,000 steps'); repeatable")
    ap.add_argument("--device", help="the machine the trace came from, for the record")
    ap.add_argument("--command", help="the command that took the trace, for the record")
    ap.add_argument("--date", help="the day the trace was taken (YYYY-MM-DD), for the record")
    ap.add_argument("--note", help="anything else the record should say")
    ap.add_argument("--out", help="write the summary here (JSON); printed otherwise")
    a = ap.parse_args(argv)
    try:
        labels = _labels(a.label)
        if os.path.isdir(a.source):
            summary = summarise_trace(a.source, open(a.hlo).read() if a.hlo else None)
        elif os.path.isfile(a.source):
            with open(a.source) as f:
                summary = json.load(f)
            if "by_calls" not in summary:
                raise ValueError(f"{a.source} is not a trace summary (no by_calls)")
        else:
            raise ValueError(f"{a.source} is neither a trace folder nor a summary file")
    except (OSError, ValueError) as err:
        print(f"trace_summary: {err}", file=sys.stderr)
        return 2
    if labels:
        summary = labelled(summary, labels)
    meta = {k: v for k, v in (("device", a.device), ("command", a.command), ("date", a.date), ("note", a.note)) if v}
    if meta:
        summary = {**meta, "recorded_by": "python -m experiments.trace_summary " + " ".join(
            shlex.quote(x) for x in (sys.argv[1:] if argv is None else argv)), **summary}
    text = json.dumps(summary, indent=1)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text + "\n")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
