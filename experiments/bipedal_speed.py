"""Put the bipedal walker's measured speed into its record (``docs/results/bipedal.json``).

Reads ``experiments.bench_latency --env bipedal`` records (and ``experiments.profile_bipedal_step``
records: their ``default`` variant's rows, timed the same way) and writes, keeping the record's other keys:
``speed.rows`` (one per batch and record: ms per sequential step, env steps per second, where and
when; the solver passes, the step timed and the terrain unroll), ``speed.student_rows`` (one per record
and student part timed with ``--student``: a training rollout or a whole PPO update, with its env
steps per second), ``ms_per_step_batch200`` (the best at a batch
of 200) and ``steps_per_second_best`` (the best batch). Both headline figures use only rows at
Box2D's solver passes and of the full ``env.step``: fewer passes (which break parity,
docs/bipedal.md) or a step without its auto-reset split the step's cost, they are not a faster
walker. Usage: ``python -m experiments.bipedal_speed LATENCY.json [...] --out docs/results/bipedal.json``.
"""
from __future__ import annotations

import argparse
import json
import pathlib

from envs.bipedal.model import POSITION_ITERATIONS, VELOCITY_ITERATIONS


PROFILE = "experiments.profile_bipedal_step"


def speed_rows(records: list[dict]) -> list[dict]:
    """One row per (record, batch): ``ms_per_step`` and ``steps_per_second`` = batch / seconds per step."""
    rows = []
    for rec in records:
        if PROFILE in rec.get("command", ""):  # profile_bipedal_step: rows of solver variants; "default" is the walker
            rows += [{"batch": r["batch"], "ms_per_step": r["ms_per_step"], "steps_per_second": r["steps_per_second"],
                      "compile_s": r["compile_s"], "solver_kernel": "auto",
                      "step": {"step_without_reset": "without-reset"}.get(rec["step"], rec["step"]), "terrain_unroll": 1,
                      "velocity_iterations": VELOCITY_ITERATIONS, "position_iterations": POSITION_ITERATIONS,
                      **{k: rec.get(k) for k in ("device", "date", "command", "note")}}
                     for r in rec["rows"] if r["variant"] == "default"]
            continue
        for r in rec["env_rows"]:
            rows.append({"batch": r["batch"], "ms_per_step": 1e3 * r["s_per_step"],
                         "steps_per_second": r["batch"] / r["s_per_step"], "compile_s": r["compile_s"],
                         "solver_kernel": rec.get("solver_kernel", "auto"),
                         "step": rec.get("step", "step"), "terrain_unroll": rec.get("terrain_unroll", 1),
                         "velocity_iterations": rec.get("velocity_iterations", VELOCITY_ITERATIONS),
                         "position_iterations": rec.get("position_iterations", POSITION_ITERATIONS),
                         **{k: rec.get(k) for k in ("device", "date", "command", "note")}})
    return rows


STUDENT_TIMINGS = (("rollout", "rollout_s", "rollout_compile_s"), ("update", "ppo_update_s", "ppo_compile_s"))


def student_rows(records: list[dict]) -> list[dict]:
    """One row per (record, student part timed): seconds for one training rollout (the env stepping under
    the policy) or one whole PPO update, and env steps per second = num_envs x num_steps / seconds.
    Records from before bench_latency kept the rollout's shape get it from today's student preset with
    the record's overrides (``shape_from``: "preset")."""
    from shed_jax.student import PPOConfig

    rows = []
    for rec in records:
        parts = [(name, rec[t], rec.get(c)) for name, t, c in STUDENT_TIMINGS if rec.get(t) is not None]
        if not parts:
            continue
        if rec.get("num_envs") is not None:
            envs_, steps, source = rec["num_envs"], rec["num_steps"], "record"
        else:
            cfg = PPOConfig.for_env(rec["env"]).with_overrides(rec.get("ppo_overrides"))
            envs_, steps, source = cfg.num_envs, cfg.num_steps, "preset"
        for name, secs, compile_s in parts:
            rows.append({"part": name, "s": secs, "compile_s": compile_s, "num_envs": envs_, "num_steps": steps,
                         "shape_from": source, "env_steps_per_second": envs_ * steps / secs,
                         "ppo_overrides": rec.get("ppo_overrides") or {},
                         **{k: rec.get(k) for k in ("device", "date", "command", "note")}})
    return rows


def summary(rows: list[dict]) -> dict:
    rows = [r for r in rows if r["step"] == "step"
            and (r["velocity_iterations"], r["position_iterations"]) == (VELOCITY_ITERATIONS, POSITION_ITERATIONS)]
    at200 = [r["ms_per_step"] for r in rows if r["batch"] == 200]
    return {"ms_per_step_batch200": min(at200) if at200 else None,
            "steps_per_second_best": max((r["steps_per_second"] for r in rows), default=None)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("latency", nargs="+", help="bench_latency records (latency_*.json) of the bipedal env, "
                                              "or profile_bipedal_step records")
    p.add_argument("--out", required=True, help="the bipedal record to update")
    args = p.parse_args(argv)
    records = []
    for f in args.latency:
        path = pathlib.Path(f)
        if not path.is_file():
            p.error(f"{f}: no such file")
        try:
            rec = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            p.error(f"{f}: not JSON ({e})")
        if PROFILE in rec.get("command", "") and rec.get("rows"):  # the profiler's records are all of the bipedal env
            records.append(rec)
            continue
        timed = rec.get("env_rows") or any(rec.get(t) is not None for _, t, _ in STUDENT_TIMINGS)
        if rec.get("env") != "bipedal" or not timed:
            p.error(f"{f}: not a bench_latency record of the bipedal env with a timing (env {rec.get('env')!r}, "
                    f"{len(rec.get('env_rows') or [])} batch rows, no student part)")
        records.append(rec)
    rows = speed_rows(records)
    if not rows:  # the headline figures come from env rows: never overwrite them with nothing
        p.error("no input has batch rows (env steps timed); give the latency records with them too")
    out = pathlib.Path(args.out)
    rec = json.loads(out.read_text()) if out.is_file() else {}
    s = summary(rows)
    rec.update(s, speed={"rows": rows, "student_rows": student_rows(records), "sources": list(args.latency)})
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rec, indent=1) + "\n")
    print(f"ms per step at batch 200: {s['ms_per_step_batch200']}; best steps/s: {s['steps_per_second_best']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
