"""Write docs/results/baselines.json from finished sweeps: the native baselines' lander finals and
their students on DCD's named walker levels.

Each ``--lander`` / ``--walker`` argument is a sweep output directory (``python -m shed_jax sweep
... --out DIR``); every row of its ``sweep.json`` becomes one entry, keyed by method, with the
sweep's ``--set`` values (e.g. ``level_switch=episode``) and its saved arguments (``sweep_args.json``)
kept beside it. Walker sweeps must have run
with ``--final-eval named``; their entry holds, per named level, the mean return over seeds and the
solved rate (return > 230), and ``dcd_six_solved_mean`` is the solved rate averaged over DCD's six
test levels (the comparison of DCD's table). The device is the one the sweeps ran on (sweeps do not record it).

    python -m experiments.baselines_record --device "NVIDIA H200" --date 2026-11-25 \\
        --lander runs/ep_plr --lander runs/ep_accel --walker runs/wdr --out docs/results/baselines.json
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

from shed_jax.eval_sets import DCD_TEST_LEVELS


def _sweep(path: str) -> tuple[dict, dict]:
    d = pathlib.Path(path)
    return json.loads((d / "sweep.json").read_text()), json.loads((d / "sweep_args.json").read_text())


def lander_entries(path: str) -> dict:
    sweep, args = _sweep(path)
    return {row["method"]: {"seeds": row["seeds"], "final_mean": row["final_test_return_mean"],
                            "final_se": row["final_test_return_se"], "set": args.get("set") or [],
                            "wall_time_s": row.get("group_wall_time_s"), "sweep_args": args}
            for row in sweep["rows"]}


def walker_entries(path: str) -> dict:
    sweep, args = _sweep(path)
    out = {}
    for row in sweep["rows"]:
        named = json.loads((pathlib.Path(path) / row["dir"] / "final_eval_named.json").read_text())
        levels = {r["label"]: {"return": r["mean"], "se": r["se"], "solved": r["solved_rate"]} for r in named["per_level"]}
        six = [levels[name]["solved"] for name in DCD_TEST_LEVELS if name in levels]
        out[row["method"]] = {"seeds": row["seeds"], "set": args.get("set") or [], "levels": levels,
                              "dcd_six_solved_mean": sum(six) / len(six) if len(six) == len(DCD_TEST_LEVELS) else None,
                              "test_set_b": {"mean": row["final_test_return_mean"], "se": row["final_test_return_se"]},
                              "wall_time_s": row.get("group_wall_time_s"), "sweep_args": args}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", required=True, help="the device the sweeps ran on")
    p.add_argument("--date", default=time.strftime("%Y-%m-%d", time.gmtime()), help="the date the sweeps ran")
    p.add_argument("--lander", action="append", default=[], metavar="SWEEP_DIR")
    p.add_argument("--walker", action="append", default=[], metavar="SWEEP_DIR")
    p.add_argument("--note", default="", help="a sentence kept in the record (what was not run, and why)")
    p.add_argument("--out", default="docs/results/baselines.json")
    args = p.parse_args(argv)
    record = {"device": args.device, "date": args.date,
              "command": "python -m experiments.baselines_record " + " ".join(sys.argv[1:] if argv is None else argv),
              "lander": {}, "walker": {}}
    for path in args.lander:
        record["lander"].update(lander_entries(path))
    for path in args.walker:
        record["walker"].update(walker_entries(path))
    if args.note:
        record["note"] = args.note
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
