"""How long a hierarchical teacher's evaluation rollout runs for a saved run's students: restore the
run's latest checkpoint, evaluate its students on the teacher's evaluation levels as the teacher
does (``performance``: every level, ``num_eval_episodes`` each, the teacher's step limit), and
record each row's episode length and the rollout's sequential steps (``steps_run``: it stops once
every row has ended its episode).

On a simulator paid by the sequential step those steps are what the teacher's evaluation costs:
SHED's budget step on the 2-D walker evaluates 5 seeds x 10 levels x 4 episodes = 200 rows, the
batch at which docs/bipedal.md times a step.

    python experiments/eval_length.py RUN_DIR --out F.json

With ``--toi-census`` it also counts, per batch-step of that rollout, the 2-D walker's time-of-impact
searches that found a candidate (``experiments/toi_census.py``): the share of sequential steps in which
``SolverConfig.toi_gate`` could skip the solve for the whole batch (the rollout's rows are one batch on
a GPU, the seeds included). The count's callback makes the rollout slower, not different.

Run it with the run's own sources first on the path for a carried run (its ``src.tgz`` unpacked in
DIR: ``PYTHONPATH=DIR python experiments/eval_length.py ...``); the record names the sources it used.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=pathlib.Path, help="a hierarchical teacher's run directory (shed, hmdp, ...)")
    ap.add_argument("--out", type=pathlib.Path, required=True, help="the JSON record to write")
    ap.add_argument("--seed", type=int, default=123, help="the evaluation's key (default 123)")
    ap.add_argument("--toi-census", action="store_true",
                    help="also count the batch-steps whose time-of-impact searches found a candidate (2-D walker)")
    ap.add_argument("--note", default="", help="a line for the record (e.g. which sources, and why)")
    args = ap.parse_args(argv)
    if not (args.run_dir / "config.json").is_file():
        print(f"eval_length: {args.run_dir} is not a run directory (no config.json)", file=sys.stderr)
        return 2

    import jax
    import numpy as np

    import shed_jax
    from shed_jax import evaluation
    from shed_jax.experiment import build, seed_keys
    from shed_jax.runtime import provenance

    records = None
    if args.toi_census:
        try:  # run as `python -m experiments.eval_length` from this repository
            from experiments import toi_census
        except ImportError:  # run as a file beside a carried run's own sources, which predate it
            import toi_census
        records = toi_census.record_searches()

    t0 = time.time()
    exp, env, student, tests, seeds, step, students = evaluation.restore_students(args.run_dir)
    _, _, method, _ = build(exp)
    if not hasattr(method, "eval_params"):
        print(f"eval_length: the run's method ({type(method).__name__}) has no teacher evaluation", file=sys.stderr)
        return 2
    episodes = exp.method_config.num_eval_episodes
    evaluate = jax.jit(jax.vmap(lambda s, k: student.evaluate_with_info(s, k, method.eval_params, episodes, method.eval_max)))
    t1 = time.time()
    rets, info = evaluate(students, seed_keys(args.seed, seeds))
    jax.block_until_ready(rets)
    t2 = time.time()
    lens = np.asarray(info["lengths"])  # [seeds, levels, episodes]
    limit = int(np.asarray(info["env_steps"]).reshape(-1)[0]) // (lens.shape[1] * lens.shape[2])
    record = {
        **provenance("experiments.eval_length", argv),
        # run as a file, so that a carried run's own sources can come first on the path
        "command": "python experiments/eval_length.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "what": "the teacher's evaluation rollout for a saved run's students: episode lengths and sequential steps",
        "run": str(args.run_dir), "budget_step": int(step), "seeds": int(seeds),
        "levels": int(lens.shape[1]), "episodes": int(lens.shape[2]), "rows": int(lens.size), "step_limit": limit,
        "steps_run_per_seed": np.asarray(info["steps_run"]).reshape(-1).tolist(),
        "longest_episode": int(lens.max()), "mean_episode": round(float(lens.mean()), 1),
        "rows_at_the_limit": round(float((lens >= limit).mean()), 3),
        "mean_length_per_level": lens.astype(np.float64).mean(axis=(0, 2)).round(1).tolist(),
        "mean_return_per_level": np.asarray(rets, np.float64).mean(axis=(0, 2)).round(1).tolist(),
        "seed": args.seed,
        "sources": str(pathlib.Path(shed_jax.__file__).resolve().parent.parent),
        "jax": jax.__version__, "restore_s": round(t1 - t0, 1), "compile_and_run_s": round(t2 - t1, 1),
        "note": args.note,
    }
    if records is not None:
        if not records:
            print(f"eval_length: --toi-census: the {exp.env} env ran no time-of-impact search", file=sys.stderr)
            return 2
        # sites in the order they first ran: the evaluation's reset of every row, then its steps (a
        # traced site that never ran, e.g. one traced only for its shapes, has no record)
        order = list(dict.fromkeys(site for site, _ in records))
        record["toi_census"] = toi_census.summarise([(order.index(site), f) for site, f in records],
                                                    names=("reset", "step"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"budget step {step}: {record['rows']} rows, steps run {record['steps_run_per_seed']}, longest episode "
          f"{record['longest_episode']} of {limit}, mean {record['mean_episode']}, {record['rows_at_the_limit']:.0%} at the limit")
    for site, c in (record.get("toi_census") or {}).items():
        print(f"time of impact, {site}: {c['candidate_share']:.1%} of the searches found a candidate; "
              f"{c['batch_steps_with_any']:.1%} of {c['batch_steps']} batch-steps had one")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
