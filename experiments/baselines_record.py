"""Write docs/results/baselines.json from finished runs: the native baselines' lander finals and
their students on DCD's named levels of the MJX walker (``--walker``) and the 2-D walker (``--bipedal``).

Each argument is a sweep output directory (``python -m shed_jax sweep ... --out DIR``: every row of
its ``sweep.json`` becomes one entry) or the directory of one ``python -m shed_jax run`` (one entry);
entries are keyed by method, with the sweep's ``--set`` values (e.g. ``level_switch=episode``; for a
run, what it sets apart from its preset) and its saved arguments kept beside them. A directory of
another environment than its flag names is refused. Walker runs must have run with ``--final-eval
named``; their entry holds, per named level, the mean return over seeds and the solved rate (return >
230), and ``dcd_six_solved_mean`` is the solved rate averaged over DCD's six test levels (the
comparison of DCD's table). The device is the one the runs ran on (sweeps do not record it).
With ``--keep``, the entries already in ``--out`` that these sweeps do not measure again stay; every
entry then names the run that measured it by index into ``runs`` (device, date, command, note).

    python -m experiments.baselines_record --device "NVIDIA H200" --date 2026-11-25 \\
        --lander runs/ep_plr --lander runs/ep_accel --walker runs/wdr --out docs/results/baselines.json
    python -m experiments.baselines_record --keep --device "NVIDIA H100 80GB HBM3" --walker runs/wpaired
    python -m experiments.baselines_record --device "NVIDIA H200" --bipedal runs/bipedal_dr --out OUT.json
"""
from __future__ import annotations

import argparse
import functools
import json
import pathlib
import shlex
import sys
import time

from shed_jax.eval_sets import DCD_TEST_LEVELS


ENVS = ("lander", "walker", "bipedal")
NAMED_LEVEL_ENVS = ("walker", "bipedal")  # whose entries hold the students' returns on DCD's named levels


def _json(path: pathlib.Path, kind=dict):
    """A JSON file that must hold a ``kind``; ValueError naming the file otherwise."""
    value = json.loads(path.read_text())
    if not isinstance(value, kind):
        raise ValueError(f"{path} holds a JSON {type(value).__name__}, not a {kind.__name__}")
    return value


def _need(d: dict, keys, where) -> None:
    missing = [k for k in keys if k not in d]
    if missing:
        raise ValueError(f"{where} lacks {', '.join(missing)}")


def _rows(path: str, env: str) -> tuple[list[dict], dict]:
    """The rows (``sweep.json``'s form: method, seeds, dir, final test return, wall time) and saved
    arguments of a sweep output or of one ``shed_jax run`` directory; ValueError where it is
    neither, or holds another environment than ``env``. A run's ``set`` is what it sets apart from
    its preset, None where this version no longer has that preset."""
    d = pathlib.Path(path)
    if (d / "sweep.json").is_file():
        sweep, args = _json(d / "sweep.json"), _json(d / "sweep_args.json")
        _need(sweep, ("rows",), d / "sweep.json")
        rows = sweep["rows"]
        for row in rows:
            _need(row, ("method", "seeds", "dir", "final_test_return_mean", "final_test_return_se"), d / "sweep.json")
        from experiments.teacher_runs import sweep_env

        found = sweep_env(d, d / rows[0]["dir"]) if rows else args.get("env")  # older sweeps: the point says
    elif (d / "summary.json").is_file() and (d / "config.json").is_file():
        from experiments.teacher_runs import run_settings

        summary, config = _json(d / "summary.json"), _json(d / "config.json")
        _need(summary, ("method", "seeds", "final_test_return_mean", "final_test_return_se"), d / "summary.json")
        _need(config, ("experiment", "seeds", "root_seed"), d / "config.json")
        found = config["experiment"].get("env")
        rows = [{"method": summary["method"], "seeds": summary["seeds"], "dir": ".",
                 "final_test_return_mean": summary["final_test_return_mean"],
                 "final_test_return_se": summary["final_test_return_se"],
                 "group_wall_time_s": summary.get("wall_time_s")}]
        args = {"env": found, "run": str(d), "preset": config["experiment"].get("preset"),
                "set": run_settings(config), "seeds": config["seeds"], "root_seed": config["root_seed"]}
    else:
        raise ValueError(f"{path} is neither a sweep output (sweep.json) nor a finished run (summary.json, config.json)")
    if found != env:
        where = f"pass it with --{found}" if found in ENVS else f"its environment is {found!r}"
        raise ValueError(f"{path} holds runs on {found!r}, not {env!r}: {where}")
    return rows, args


def lander_entries(path: str) -> dict:
    rows, args = _rows(path, "lander")
    return {row["method"]: {"seeds": row["seeds"], "final_mean": row["final_test_return_mean"],
                            "final_se": row["final_test_return_se"], "set": args.get("set") or [],
                            "wall_time_s": row.get("group_wall_time_s"), "sweep_args": args}
            for row in rows}


def named_level_entries(path: str, env: str) -> dict:
    rows, args = _rows(path, env)
    out = {}
    for row in rows:
        named_file = pathlib.Path(path) / row["dir"] / "final_eval_named.json"
        if not named_file.is_file():
            raise ValueError(f"{named_file} is missing: {env} runs need --final-eval named")
        named = _json(named_file)
        _need(named, ("per_level",), named_file)
        levels = {r["label"]: {"return": r["mean"], "se": r["se"], "solved": r["solved_rate"]} for r in named["per_level"]}
        summary_file = pathlib.Path(path) / row["dir"] / "summary.json"
        summary = _json(summary_file) if summary_file.is_file() else {}
        six = [levels[name]["solved"] for name in DCD_TEST_LEVELS if name in levels]
        config_file = pathlib.Path(path) / row["dir"] / "config.json"  # the preset as resolved (a sweep's may say auto)
        preset = _json(config_file).get("experiment", {}).get("preset") if config_file.is_file() else args.get("preset")
        out[row["method"]] = {"seeds": row["seeds"], "preset": preset, "set": args.get("set", []), "levels": levels,
                              "student_env_steps_per_seed": summary.get("student_env_steps_last_episode"),
                              "env_steps_per_seed": budget_steps(summary),
                              "dcd_six_solved_mean": sum(six) / len(six) if len(six) == len(DCD_TEST_LEVELS) else None,
                              "test_set_b": {"mean": row["final_test_return_mean"], "se": row["final_test_return_se"]},
                              "all_named": named.get("overall"), "final_eval_command": named.get("command"),
                              "wall_time_s": row.get("group_wall_time_s"), "sweep_args": args}
    return out


def budget_steps(summary: dict) -> float | None:
    """The env steps a run spent per seed in its last episode with the level scoring of PLR and
    ACCEL counted (``eval_env_steps_total``: DCD's accounting, where scoring a new level spends the
    budget); None without ``student_env_steps_last_episode``. The dcd preset runs one episode, so
    the totals are that episode's."""
    trained = summary.get("student_env_steps_last_episode")
    if trained is None or summary.get("student_env_steps_total") != trained:
        return trained  # several episodes (or no totals): the last episode's training steps
    return trained + summary.get("eval_env_steps_total", 0.0)


@functools.cache
def dcd_steps_per_seed() -> int:
    """The dcd preset's student steps per seed (DCD's 6.6e8), read from the preset table."""
    from shed_jax.presets import build_experiment

    exp = build_experiment("bipedal", "dr", "dcd")
    return exp.env_steps_per_budget_step * exp.loop.total_steps


def dcd_problem(entry: dict) -> str | None:
    """Why a named-level entry is not a run at DCD's budget as the preset has it, or None."""
    steps = dcd_steps_per_seed()
    if entry.get("preset") != "dcd":
        return f"preset {entry.get('preset')}"
    if entry.get("set") != []:
        return f"settings apart from the preset: {entry.get('set')}"
    # DR and the teachers' students spend the budget on training steps; PLR and ACCEL on training and
    # on scoring new levels (DCD's accounting). Means over seeds, so a float sum: exact to a step.
    trained, spent = entry.get("student_env_steps_per_seed"), entry.get("env_steps_per_seed")
    if not any(x is not None and abs(x - steps) <= 1.0 for x in (trained, spent)):
        return (f"{trained} student steps per seed ({spent} with level scoring), not {steps:,}")
    return None


def entries(path: str, env: str) -> dict:
    return named_level_entries(path, env) if env in NAMED_LEVEL_ENVS else lander_entries(path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", required=True, help="the device the sweeps ran on")
    p.add_argument("--date", default=time.strftime("%Y-%m-%d", time.gmtime()), help="the date the sweeps ran")
    p.add_argument("--lander", action="append", default=[], metavar="DIR")
    p.add_argument("--walker", action="append", default=[], metavar="DIR")
    p.add_argument("--bipedal", action="append", default=[], metavar="DIR")
    p.add_argument("--note", default="", help="a sentence kept in the record (what was not run, and why)")
    p.add_argument("--out", default="docs/results/baselines.json")
    p.add_argument("--dcd-into", default=None, metavar="RECORD",
                   help="also write the --bipedal entries, runs at --preset dcd only, as the 'dcd' block of this "
                        "record (docs/results/bipedal.json: {method: {level: {return, se, solved}}}), keeping its other keys")
    p.add_argument("--keep", action="store_true",
                   help="keep the entries of --out that these sweeps do not measure again (each entry names its run)")
    args = p.parse_args(argv)
    command = "python -m experiments.baselines_record " + shlex.join(sys.argv[1:] if argv is None else argv)
    out = pathlib.Path(args.out)
    old = json.loads(out.read_text()) if args.keep and out.exists() else {}
    runs = old.get("runs") or ([{k: old[k] for k in ("device", "date", "command", "note") if k in old}] if old else [])
    run = len(runs)
    runs.append({"device": args.device, "date": args.date, "command": command, **({"note": args.note} if args.note else {})})
    record = {"device": args.device, "date": args.date, "command": command, "runs": runs}
    for env in ENVS:
        kept = {m: dict(e, run=e.get("run", 0)) for m, e in old.get(env, {}).items()}
        for path in getattr(args, env):
            try:
                kept.update({m: dict(e, run=run) for m, e in entries(path, env).items()})
            except (ValueError, OSError, KeyError, TypeError) as err:  # JSONDecodeError is a ValueError
                p.error(f"--{env} {path}: {err}")
        if kept or env in ("lander", "walker"):
            record[env] = kept
    if args.note:
        record["note"] = args.note
    record["note_runs"] = "run: index into runs, the run (device, date, command) that measured the entry"
    if args.dcd_into:
        dcd = {m: e for m, e in record.get("bipedal", {}).items() if e["run"] == run}
        problems = {m: dcd_problem(e) for m, e in dcd.items()}
        wrong = sorted(f"{m} ({why})" for m, why in problems.items() if why)
        if not dcd or wrong:
            p.error(f"--dcd-into takes --bipedal runs at --preset dcd as it stands; got {', '.join(wrong) or 'none'}")
        target = pathlib.Path(args.dcd_into)
        try:
            env_record = _json(target) if target.exists() else {}
        except (ValueError, OSError) as err:
            p.error(f"--dcd-into {target}: {err}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {out}")
    if args.dcd_into:  # methods recorded by earlier calls stay; one measured again is replaced
        env_record["dcd"] = {**env_record.get("dcd", {}), **{m: e["levels"] for m, e in dcd.items()}}
        env_record["dcd_source"] = {**env_record.get("dcd_source", {}), **{
            m: {"record": str(out), "device": args.device, "date": args.date, "seeds": e["seeds"]} for m, e in dcd.items()}}
        target.write_text(json.dumps(env_record, indent=1) + "\n")
        print(f"wrote the 'dcd' block of {target}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
