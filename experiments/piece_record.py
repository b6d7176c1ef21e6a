"""A carried run's pieces as one JSON record, read from their logs (``pieceN.log`` in the run's folder,
each a device call's ``run.log``): the GPU, the budget steps each piece took the run through and
how long they took, the "compiled in" seconds, and which programs came from a stand-in
(``experiments/aot_cache.py``) or wrote one.

    python -m experiments.piece_record docs/results/bipedal_paper_shed/pieces --pieces 15 16 17 \
        --out docs/results/stand_ins/bipedal_shed_h100_pieces_2026-12-06.json
"""
from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import re
import sys

_GPU = re.compile(r"backend gpu: (\d+) x ([^;]+);")
_JAX = re.compile(r"\[shed_jax\] jax ([0-9.]+),")
_RESUME = re.compile(r"resuming \S+ from budget step (\d+)/(\d+)")
# the line every piece prints as its run starts or resumes; in a run's first piece, the only start it has
_START = re.compile(r"\[shed_jax\] \S+ on \S+: .*?(\d+) seed\(s\)")
_STOP = re.compile(r"stopped at budget step (\d+)/(\d+)")
_DONE = re.compile(r"training done \((\d+)/(\d+) budget steps\)")  # the last piece: no stop, the run's end
_COMPILED = re.compile(r"\[shed_jax\] compiled in ([0-9.]+) s")
_READ = re.compile(r"aot_cache: ([0-9a-f]{16})\.\.\. read from its stand-in in ([0-9.]+) s, not traced")
_WRITTEN = re.compile(r"aot_cache: ([0-9a-f]{16})\.\.\. stand-in written")
_NOT_USED = re.compile(r"aot_cache: ([0-9a-f]{16})\.\.\. stand-in not (?:used|written) \((.*?)\)(?:; tracing it)?$", re.M)
_FAILED = re.compile(r"aot_cache: ([0-9a-f]{16})\.\.\. not (lowered|compiled), so no stand-in \((.*?)\)$", re.M)
_BAR = re.compile(r"(\d+)/(\d+) \[(?:(\d+):)?(\d+):(\d+)<")


def parse(text: str) -> dict:
    """One piece's facts from its log (a resumed run's, or the run's first piece: from budget step 0);
    ValueError naming what the log lacks."""
    text = text.replace("\r", "\n")
    resume, stop, done = _RESUME.search(text), _STOP.search(text), _DONE.search(text)
    stop = stop or done
    started = _START.search(text)
    if (resume is None and started is None) or stop is None:
        raise ValueError("the log names no resumed budget step or run start, or no stop or end of training "
                         "(a piece cut off before it saved is not one this reads)")
    start = int(resume.group(1)) if resume else 0
    end, total = int(stop.group(1)), int(stop.group(2))
    bars = _BAR.findall(text)
    if not bars:
        raise ValueError("the log holds no progress bar")
    h, m, s = bars[-1][2], bars[-1][3], bars[-1][4]
    elapsed = int(h or 0) * 3600 + int(m) * 60 + int(s)
    gpu = _GPU.search(text)
    jax = _JAX.search(text)
    compiled = [float(x) for x in _COMPILED.findall(text)]
    return {
        "gpu": f"{gpu.group(1)} x {gpu.group(2).strip()}" if gpu else None,
        "jax": jax.group(1) if jax else None,
        "seeds": int(started.group(1)) if started else None,
        "budget_steps": [start, end],
        "of": total,
        "finished": stop is done,  # the run's training ended in this piece (its final evaluation may follow)
        "steps": end - start,
        # the progress bar's clock starts once the first chunk is compiled (or read), so this leaves out the compile
        "bar_elapsed_s": elapsed,
        "s_per_step": round(elapsed / (end - start), 3) if end > start else None,
        "compiled_in_s": compiled[0] if compiled else None,
        "stand_ins_read": [{"key": k, "s": float(t)} for k, t in _READ.findall(text)],
        "stand_ins_written": _WRITTEN.findall(text),
        "stand_ins_passed_over": [{"key": k, "why": why} for k, why in _NOT_USED.findall(text)],
        "programs_failed": [{"key": k, "stage": stage, "why": why} for k, stage, why in _FAILED.findall(text)],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.piece_record", description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=pathlib.Path, help="the carried run's folder, holding pieceN.log")
    ap.add_argument("--pieces", type=int, nargs="+", required=True, help="the piece numbers to read")
    ap.add_argument("--out", type=pathlib.Path, required=True, help="the JSON record to write")
    args = ap.parse_args(argv)
    pieces = {}
    for n in args.pieces:
        path = args.folder / f"piece{n}.log"
        if not path.is_file():
            print(f"piece_record: {path} does not exist", file=sys.stderr)
            return 2
        try:
            pieces[str(n)] = parse(path.read_text(encoding="utf-8", errors="replace"))
        except ValueError as err:
            print(f"piece_record: {path}: {err}", file=sys.stderr)
            return 2
    record = {
        "what": "a carried run's pieces, each one device call, read from their logs",
        # the GPUs that ran the pieces, as their logs name them (not this host, which only reads the logs)
        "device": ", ".join(sorted({p["gpu"] for p in pieces.values() if p["gpu"]})) or None,
        "folder": str(args.folder),
        "command": "python -m experiments.piece_record " + " ".join(sys.argv[1:] if argv is None else argv),
        "date": datetime.date.today().isoformat(),
        "pieces": pieces,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    for n, p in pieces.items():
        read = ", ".join(f"{r['key']} {r['s']} s" for r in p["stand_ins_read"]) or "none"
        print(f"piece {n}: {p['budget_steps'][0]} -> {p['budget_steps'][1]} ({p['steps']} steps, {p['s_per_step']} s/step), "
              f"compiled in {p['compiled_in_s']} s, stand-ins read: {read}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
