"""Seconds per budget step of the walker's UED loop, and the protocol times they add up to.

For each method, builds the walker paper preset (5 vmapped seeds by default), compiles one budget
step of the outer loop (``shed_jax.loop.make_run``; the step index is traced, so one program serves
every step), and times single steps of the three kinds the protocol mixes:

* ``plain``: a budget step inside a teacher episode, no test set (the baselines test every 5th);
* ``episode_start``: the first step of a teacher episode (a fresh student; SHED evaluates it
  first to get the teacher's initial state), no test set;
* ``tested``: a step of a teacher episode in which the test set runs.

From these and the preset's schedule it estimates the whole protocol's wall time. With
``--ppo-results`` it also folds the flat-level PPO benchmark (``experiments.bench_ppo
--eval-every``) into the record: the first env step at which the median over seeds of the evaluation
return reaches 230, and how many seeds reach it within 10M steps.

    python -m experiments.walker_loop --methods shed,dr --out docs/results/walker_loop.json \
        --ppo-results runs/ppo/results.json
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import jax
import numpy as np


def time_steps(method: str, seeds: int, repeats: int, preset: str = "paper", env: str = "walker") -> dict:
    """Compile one budget step of ``method`` on a walker preset (``env``: ``walker`` on MJX or
    ``bipedal`` on physics2d, which share the presets) and time each step kind."""
    from shed_jax.experiment import build, seed_keys
    from shed_jax.loop import make_run
    from shed_jax.presets import build_experiment

    exp = build_experiment(env, method, preset)
    _, student, m, tests = build(exp)
    init, run = make_run(student, m, tests, exp.loop)
    spec = exp.loop
    T = spec.steps_per_episode
    step = jax.jit(jax.vmap(run, in_axes=(0, None, None)), static_argnums=1)
    state = jax.jit(jax.vmap(init))(seed_keys(0, seeds))
    t0 = time.perf_counter()
    state, _ = jax.block_until_ready(step(state, 1, 0))  # compile, and the episode-0 start with its test
    compile_and_first = time.perf_counter() - t0

    # tested steps, plain ones and an episode start (untested), in schedule order
    later = range(1, spec.total_steps)
    kinds = {"tested": [t for t in later if t % T and bool(spec.tests_at(t))][:repeats]}
    plain = [t for t in later if t % T and not bool(spec.tests_at(t))][:repeats]
    starts = [t for t in later if t % T == 0 and not bool(spec.tests_at(t))][:1]
    if starts:
        kinds["episode_start"] = starts * repeats
    if plain:
        kinds["plain"] = plain
    out = {}
    for kind, ts in kinds.items():
        times = []
        for t in ts:
            t1 = time.perf_counter()
            state, _ = jax.block_until_ready(step(state, 1, t))
            times.append(time.perf_counter() - t1)
        out[kind] = float(np.median(times))
    est = protocol_estimate(spec, out)
    return {
        "env": env, "method": method, "seeds": seeds, "steps_per_episode": T, "episodes": spec.num_episodes,
        "env_steps_per_budget_step": exp.env_steps_per_budget_step,
        "compile_and_first_step_s": compile_and_first,
        "step_s": out, **est,
    }


def protocol_estimate(spec, step_s: dict) -> dict:
    """Whole-protocol seconds from per-kind step times: every step costs ``plain``; tested steps
    add ``tested - plain`` and episode starts ``episode_start - plain`` (the first step of episode 0
    is tested and a start; it is counted as tested, a small underestimate)."""
    total = spec.total_steps
    tested = sum(bool(spec.tests_at(t)) for t in range(total))
    plain = step_s.get("plain", step_s["tested"])
    seconds = (total * plain + tested * (step_s["tested"] - plain)
               + spec.num_episodes * (step_s.get("episode_start", plain) - plain))
    return {"total_steps": total, "tested_steps": tested, "budget_step_s_mean": seconds / total,
            "protocol_s_estimate": seconds}


def ppo_flat(path: str, target: float = 230.0) -> dict:
    """The flat-level PPO record from a bench_ppo results.json (walker section, with evals)."""
    res = json.loads(pathlib.Path(path).read_text())
    sec = res["sections"]["walker"]
    steps = np.array([e["env_steps_per_seed"] for e in sec["evals"]])
    ret = np.array([e["per_seed"] for e in sec["evals"]])  # [evals, seeds]
    med = np.median(ret, axis=1)
    hit = np.flatnonzero(med >= target)
    by10m = ret[steps <= 10_000_000]
    return {
        "source": {"device": res.get("device"), "date": res.get("date"), "command": res.get("command")},
        "seeds": int(ret.shape[1]), "target": target, "eval_episodes_per_seed": 16,
        "eval_env_steps": steps.tolist(), "eval_median": med.tolist(),
        "median_steps_to_230": int(steps[hit[0]]) if hit.size else None,
        "seeds_at_230_by_10M": int(np.sum(np.any(by10m >= target, axis=0))) if by10m.size else 0,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", default="shed,dr", help="comma-separated UED methods")
    p.add_argument("--env", default="walker", choices=("walker", "bipedal"),
                   help="the MJX walker or the physics2d bipedal walker (the same presets)")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--repeats", type=int, default=2, help="timed steps of each kind (median)")
    p.add_argument("--preset", default="paper", choices=("paper", "quick"))
    p.add_argument("--ppo-results", default=None, help="a bench_ppo results.json to fold in as ppo_flat")
    p.add_argument("--profile", default=None, help="an experiments.profile_walker_step JSON to fold in as profile")
    p.add_argument("--loops-from", default=None,
                   help="take the loop timings from an earlier walker_loop JSON instead of measuring them "
                        "(its device, date and command are kept under loops_source)")
    p.add_argument("--named", action="append", default=[], metavar="METHOD=FILE[@DEVICE]",
                   help="a run's final_eval_named.json (run/sweep --final-eval named) to fold in as "
                        "named_solved_rate[METHOD] (repeatable); @DEVICE names the card it ran on when it is "
                        "not the record's")
    p.add_argument("--out", default="runs/walker_loop.json")
    args = p.parse_args(argv)
    record = {"device": jax.devices()[0].device_kind, "date": time.strftime("%Y-%m-%d", time.gmtime()),
              "command": "python -m experiments.walker_loop " + " ".join(argv if argv is not None else sys.argv[1:]),
              "jax": jax.__version__, "budget_step_seconds": {}, "loops": {},
              # DCD's named levels need whole runs with --final-eval; None until such runs are folded in
              "named_solved_rate": None}
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.ppo_results:
        record["ppo_flat"] = ppo_flat(args.ppo_results)
    for item in args.named:
        method, _, path = item.partition("=")
        path, _, device = path.partition("@")
        ev = json.loads(pathlib.Path(path).read_text())
        record["named_solved_rate"] = record["named_solved_rate"] or {}
        record["named_solved_rate"][method] = {r["label"]: r["solved_rate"] for r in ev["per_level"]}
        record.setdefault("named_sources", {})[method] = {"file": path, "seeds": ev["seeds"], "episodes": ev["episodes"],
                                                          **({"device": device} if device else {})}
    if args.profile:
        record["profile"] = json.loads(pathlib.Path(args.profile).read_text())
    if args.loops_from:  # compose the record from measured parts; nothing is measured here
        earlier = json.loads(pathlib.Path(args.loops_from).read_text())
        record["loops_source"] = {k: earlier.get(k) for k in ("device", "date", "command")}
        record["device"], record["date"] = earlier["device"], earlier["date"]
        record["loops"], record["budget_step_seconds"] = earlier["loops"], earlier["budget_step_seconds"]
        out.write_text(json.dumps(record, indent=2))
        print(f"wrote {out}")
        return 0
    from shed_jax import runtime

    runtime.call_site_free_locations()  # the kernels a run compiles (one per loop and grid), not one per call site
    for method in [m for m in args.methods.split(",") if m]:
        r = time_steps(method, args.seeds, args.repeats, args.preset, args.env)
        record["loops"][method] = r
        record["budget_step_seconds"][method] = r["budget_step_s_mean"]
        print(json.dumps(r), flush=True)
        out.write_text(json.dumps(record, indent=2))
    out.write_text(json.dumps(record, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
