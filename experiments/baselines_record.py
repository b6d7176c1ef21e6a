"""Write docs/results/baselines.json from finished sweeps: the native baselines' lander finals and
their students on DCD's named walker levels.

Each ``--lander`` / ``--walker`` argument is a sweep output directory (``python -m shed_jax sweep
... --out DIR``); every row of its ``sweep.json`` becomes one entry, keyed by method, with the
sweep's ``--set`` values (e.g. ``level_switch=episode``) and its saved arguments (``sweep_args.json``)
kept beside it. Walker sweeps must have run
with ``--final-eval named``; their entry holds, per named level, the mean return over seeds and the
solved rate (return > 230), and ``dcd_six_solved_mean`` is the solved rate averaged over DCD's six
test levels (the comparison of DCD's table). The device is the one the sweeps ran on (sweeps do not record it).
With ``--keep``, the entries already in ``--out`` that these sweeps do not measure again stay; every
entry then names the run that measured it by index into ``runs`` (device, date, command, note).

    python -m experiments.baselines_record --device "NVIDIA H200" --date 2026-11-25 \\
        --lander runs/ep_plr --lander runs/ep_accel --walker runs/wdr --out docs/results/baselines.json
    python -m experiments.baselines_record --keep --device "NVIDIA H100 80GB HBM3" --walker runs/wpaired
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
    p.add_argument("--keep", action="store_true",
                   help="keep the entries of --out that these sweeps do not measure again (each entry names its run)")
    args = p.parse_args(argv)
    command = "python -m experiments.baselines_record " + " ".join(sys.argv[1:] if argv is None else argv)
    out = pathlib.Path(args.out)
    old = json.loads(out.read_text()) if args.keep and out.exists() else {}
    runs = old.get("runs") or ([{k: old[k] for k in ("device", "date", "command", "note") if k in old}] if old else [])
    run = len(runs)
    runs.append({"device": args.device, "date": args.date, "command": command, **({"note": args.note} if args.note else {})})
    record = {"device": args.device, "date": args.date, "command": command, "runs": runs, "lander": {}, "walker": {}}
    for env, paths, entries in (("lander", args.lander, lander_entries), ("walker", args.walker, walker_entries)):
        kept = {m: dict(e, run=e.get("run", 0)) for m, e in old.get(env, {}).items()}
        for path in paths:
            kept.update({m: dict(e, run=run) for m, e in entries(path).items()})
        record[env] = kept
    if args.note:
        record["note"] = args.note
    record["note_runs"] = "run: index into runs, the run (device, date, command) that measured the entry"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
