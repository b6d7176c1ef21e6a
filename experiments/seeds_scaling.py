"""A budget step's time against the number of seeds in one program, from fresh runs' first pieces.

A run's seeds are one vmapped program. On the 2-D walker a budget step is mostly the teacher's
evaluation: 2,000 sequential steps of a few hundred walkers, whose time is latency rather than work
(the fused physics kernels took as long per step at 200 walkers as at 5,120 in a trace on an H100,
docs/log/benchmarks.md, 2026-12-07). More seeds should then cost a budget step much less than
proportionally. This reads
the run logs of ``experiments/seeds_scaling.sh`` (one fresh run per seed count, the same method,
preset and sources) and writes the record: per seed count the budget steps run, the seconds per
budget step (the progress bar's clock, which starts once the first chunk is compiled or read), and
the seconds per budget step and seed.

    python -m experiments.seeds_scaling LOG [LOG ...] --out RECORD.json [--note TEXT]
"""
from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import sys

from experiments.piece_record import parse


def rows(logs: dict[str, str]) -> list[dict]:
    """One row per log (name -> text), by seed count; ValueError naming a log that lacks what is read."""
    out = []
    for name, text in logs.items():
        try:
            p = parse(text)
        except ValueError as err:
            raise ValueError(f"{name}: {err}") from None
        if p["seeds"] is None or p["s_per_step"] is None:
            raise ValueError(f"{name}: the log names no seed count, or no budget step was run")
        out.append({"log": name, "seeds": p["seeds"], "gpu": p["gpu"], "budget_steps": p["budget_steps"],
                    "steps": p["steps"], "bar_elapsed_s": p["bar_elapsed_s"], "s_per_step": p["s_per_step"],
                    "s_per_step_per_seed": round(p["s_per_step"] / p["seeds"], 4), "compiled_in_s": p["compiled_in_s"]})
    out.sort(key=lambda r: r["seeds"])
    base = out[0] if out else None
    for r in out:  # against the fewest seeds: how much longer a budget step, how much cheaper a seed
        r["step_time_vs_fewest"] = round(r["s_per_step"] / base["s_per_step"], 3)
        r["seed_cost_vs_fewest"] = round(r["s_per_step_per_seed"] / base["s_per_step_per_seed"], 3)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.seeds_scaling", description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", type=pathlib.Path, nargs="+", help="the run logs of experiments/seeds_scaling.sh")
    ap.add_argument("--out", type=pathlib.Path, required=True, help="the JSON record to write")
    ap.add_argument("--note", default=None, help="what was run (method, preset, sources), for the record")
    args = ap.parse_args(argv)
    missing = [str(p) for p in args.logs if not p.is_file()]
    if missing:
        print(f"seeds_scaling: no such log: {', '.join(missing)}", file=sys.stderr)
        return 2
    try:
        table = rows({p.name: p.read_text(encoding="utf-8", errors="replace") for p in args.logs})
    except ValueError as err:
        print(f"seeds_scaling: {err}", file=sys.stderr)
        return 2
    record = {
        "what": "seconds per budget step against the seeds of one program, fresh runs' first pieces",
        "device": ", ".join(sorted({r["gpu"] for r in table if r["gpu"]})) or None,  # the logs' GPU, not this host
        "command": "python -m experiments.seeds_scaling " + " ".join(sys.argv[1:] if argv is None else argv),
        "date": datetime.date.today().isoformat(),
        "note": args.note,
        "rows": table,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    for r in table:
        print(f"{r['seeds']:>3} seeds: {r['steps']} budget steps, {r['s_per_step']} s per step, "
              f"{r['s_per_step_per_seed']} s per step and seed ({r['seed_cost_vs_fewest']}x the fewest's)")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
