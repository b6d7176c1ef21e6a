"""Where a walker budget step's time goes, part by part, on the device JAX sees.

Times, for ``--seeds`` vmapped students of the walker paper preset on ``--levels`` uniformly
sampled levels: one rollout, one PPO update (epochs x minibatches), the teacher's evaluation
(10 evaluation levels x 4 episodes) and the test set (test set B, 10 x 10), each compiled alone,
and both as one fused rollout; evaluations report how many steps they ran before every episode had
ended. Run it after a few updates of training (``--warm-updates``) so episode lengths are those of a
learning student. ``--latency-batches`` adds seconds per sequential env step (random actions) of
``step`` (auto-reset), ``step_without_reset`` and ``reset`` alone, at each batch.

    python -m experiments.profile_walker_step --seeds 5 --warm-updates 6 --out runs/profile_walker.json

``--env bipedal`` profiles the 2-D walker (``envs/bipedal``, the same paper preset). ``--from-run
RUN_DIR`` takes a hierarchical teacher's saved run instead: its experiment, its latest students (mid
episode, on the levels the teacher gave them) and its own evaluation set, episodes and step limit, so
that the evaluations run as long as that run's do (students that stand run them to the step limit;
``--warm-updates`` students fall within a few hundred steps). For a carried run, put its own sources
first on the path and run this file, as ``experiments/eval_length.py`` says. On a GPU the kernels are
padded to the run's training batch first, as a run pads them (``runtime.pad_kernels_to``).
``--parts`` picks what to time (a device call too short for every compile can take the PPO update
alone: without the rollout it runs on a zero trajectory of the rollout's shapes, which compiles no
environment step). The record is rewritten after each part, so a call stopped by its time limit keeps
the parts it finished.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np


PARTS = ("rollout", "update", "teacher_eval", "test")


def _timed(fn, *args, repeats=2):
    out = jax.block_until_ready(fn(*args))  # compile + first call
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=5, help="vmapped students (default 5; with --from-run, the run's)")
    p.add_argument("--env", default="walker", choices=("walker", "bipedal"),
                   help="the MJX walker or the 2-D walker on physics2d (default walker); ignored with --from-run")
    p.add_argument("--from-run", type=pathlib.Path, default=None, metavar="RUN_DIR",
                   help="a hierarchical teacher's saved run: its latest students and its own evaluation")
    p.add_argument("--levels", type=int, default=4)
    p.add_argument("--warm-updates", type=int, default=6)
    p.add_argument("--ppo", nargs="*", default=[], metavar="KEY=VALUE", help="PPO overrides (student.config)")
    p.add_argument("--latency-batches", default="", help="comma-separated batches for the per-step latencies")
    p.add_argument("--latency-only", action="store_true", help="only the per-step latencies")
    p.add_argument("--no-test-set", action="store_true",
                   help="leave out the test set and the fused evaluation (a budget step that does not test)")
    p.add_argument("--parts", default=",".join(PARTS), metavar="LIST",
                   help=f"comma-separated parts to time, of {','.join(PARTS)} (default all); an update without "
                        "the rollout is timed on a zero trajectory of the rollout's shapes, so it compiles no environment")
    p.add_argument("--out", default="runs/profile_walker.json")
    args = p.parse_args(argv)
    parts = [x for x in args.parts.split(",") if x]
    bad = sorted(set(parts) - set(PARTS))
    if bad or not parts:
        print(f"profile_walker_step: --parts takes a comma-separated list of {', '.join(PARTS)}; got {args.parts!r}", file=sys.stderr)
        return 2
    if args.no_test_set:
        parts = [x for x in parts if x != "test"]
    if args.from_run is not None and args.ppo:
        print("profile_walker_step: --ppo cannot change a saved run's students (--from-run); leave one out", file=sys.stderr)
        return 2

    from shed_jax import eval_sets
    from shed_jax.experiment import build, seed_keys
    from shed_jax.presets import build_experiment
    from shed_jax.student.config import parse_overrides

    if args.from_run is None:  # fresh students of the paper preset, on the walker's own evaluation set
        exp = build_experiment(args.env, "shed", "paper", ppo_overrides=parse_overrides(args.ppo) or None)
        env, student, _, tests = build(exp)
        seeds, students, run = args.seeds, None, {}
        evals, eval_episodes, eval_max = eval_sets.walker_eval_set(10).to_params(env.default_params), 4, 2000
        test_episodes, test_max = 10, 2000
    else:  # a saved run's students, its teacher's evaluation and its test set as its loop runs them
        if not (args.from_run / "config.json").is_file():
            print(f"profile_walker_step: {args.from_run} is not a run directory (no config.json)", file=sys.stderr)
            return 2
        from shed_jax import evaluation

        exp, env, student, tests, seeds, budget_step, students = evaluation.restore_students(args.from_run)
        _, _, method, _ = build(exp)
        if not hasattr(method, "eval_params"):
            print(f"profile_walker_step: the run's method ({type(method).__name__}) has no teacher evaluation", file=sys.stderr)
            return 2
        run = {"run": str(args.from_run), "budget_step": int(budget_step)}
        evals, eval_episodes, eval_max = method.eval_params, exp.method_config.num_eval_episodes, method.eval_max
        test_episodes, test_max = exp.loop.test_episodes, exp.loop.test_max_steps
    rec = {"device": jax.devices()[0].device_kind, "date": time.strftime("%Y-%m-%d", time.gmtime()),
           # run as a file beside a carried run's sources, or as a module of this repository
           "command": ("python -m experiments.profile_walker_step " if __package__ else "python experiments/profile_walker_step.py ")
           + " ".join(argv if argv is not None else sys.argv[1:]),
           "env": exp.env, "xla_flags": os.environ.get("XLA_FLAGS", ""), **run}
    if args.latency_batches:
        rec["latency"] = [step_latency(env, int(b)) for b in args.latency_batches.split(",")]
        for row in rec["latency"]:
            print(json.dumps(row), flush=True)
        _write(rec, args.out)  # kept if the profile below is stopped by a time limit
    if args.latency_only:
        return 0
    from shed_jax import runtime

    if hasattr(runtime, "pad_kernels_to"):  # a carried run's sources from before 2026-12-04 have no padding
        rec["kernel_worlds"] = runtime.pad_kernels_to(seeds * student.train_envs)
    keys = seed_keys(0, seeds)
    s = students
    if s is None:
        levels = env.param_space.sample(jax.random.PRNGKey(1), (args.levels,))
        s = jax.jit(jax.vmap(lambda k: student.assign_levels(student.init(k), k, levels)))(keys)
        s, _ = jax.jit(jax.vmap(lambda st, k: student.run_updates(st, k, args.warm_updates)))(s, keys)
    rec.update({"seeds": seeds, "num_envs": student.config.num_envs, "num_steps": student.config.num_steps,
                "epochs": student.config.update_epochs, "minibatches": student.config.num_minibatches,
                "eval_levels": int(jax.tree_util.tree_leaves(evals)[0].shape[0]), "eval_episodes": eval_episodes,
                "eval_max_steps": eval_max, "test_episodes": test_episodes, "test_max_steps": test_max})
    rec["parts"] = parts
    rollout = jax.jit(jax.vmap(student.rollout))
    if "rollout" in parts:
        rec["rollout_s"], (s2, traj) = _timed(rollout, s, keys)
        _write(rec, args.out)
    elif "update" in parts:  # the rollout's output shapes, traced but never compiled
        s2 = s
        traj = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(rollout, s, keys)[1])
        rec["update_on_zero_trajectory"] = True
    if "update" in parts:
        update = jax.jit(jax.vmap(student.update))
        rec["update_s"], _ = _timed(update, s2, keys, traj)
        _write(rec, args.out)
    if "rollout" in parts and "update" in parts:
        rec["train_s_per_budget_step"] = exp.method_config.updates_per_step * (rec["rollout_s"] + rec["update_s"])

    def ev(levels_, episodes, max_steps):
        return jax.jit(jax.vmap(lambda st, k: student.evaluate_with_info(st, k, levels_, episodes, max_steps)))

    if "teacher_eval" in parts:
        rec["teacher_eval_s"], (_, info) = _timed(ev(evals, eval_episodes, eval_max), s, keys)
        rec["teacher_eval_steps_run"] = np.asarray(info["steps_run"]).tolist()
        _write(rec, args.out)  # kept if the test set's programs below are stopped by a time limit
    if "test" in parts:
        rec["test_eval_s"], (_, info) = _timed(ev(tests, test_episodes, test_max), s, keys)
        rec["test_eval_steps_run"] = np.asarray(info["steps_run"]).tolist()
        fused = jax.jit(jax.vmap(lambda st, k: student.evaluate_many(
            st, [(k, evals, eval_episodes, eval_max), (jax.random.fold_in(k, 1), tests, test_episodes, test_max)])))
        rec["fused_eval_s"], out = _timed(fused, s, keys)
        rec["fused_eval_steps_run"] = np.asarray(out[0][1]["steps_run"]).tolist()
    print(json.dumps(rec), flush=True)
    return _write(rec, args.out)


def _write(rec: dict, path: str) -> int:
    out = pathlib.Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rec, indent=2))
    return 0


def step_latency(env, batch: int, steps: int = 128) -> dict:
    """Seconds per sequential step of ``vmap(step)``, ``vmap(step_without_reset)``
    (``experiments.bench_latency.env_latency``) and ``vmap(reset)`` alone, in scans of ``steps``."""
    from experiments.bench_latency import _timed as best_of_3, env_latency

    levels = env.param_space.sample(jax.random.PRNGKey(1), (batch,))

    @jax.jit
    def resets(key):
        def body(acc, k):
            obs, _ = jax.vmap(env.reset)(jax.random.split(k, batch), levels)
            return acc + obs.sum(), None
        return jax.lax.scan(body, jnp.float32(0), jax.random.split(key, steps))[0]

    return {"batch": batch, "steps": steps,
            "step_s": env_latency(env, batch, steps)["s_per_step"],
            "step_without_reset_s": env_latency(env, batch, steps, env.step_without_reset)["s_per_step"],
            "reset_s": best_of_3(resets, jax.random.PRNGKey(4))[1] / steps}


if __name__ == "__main__":
    raise SystemExit(main())
