"""Latency of the lander inside the UED loop: the loop is latency-bound, not throughput-bound.

One SHED budget step (paper preset) runs about 2,300 *sequential* lander steps (10 PPO rollouts of
128 steps, a 500-step evaluation and a 500-step test) on small batches (40 training envs, 80-100
evaluation episodes), so what matters there is the time of one step at a small batch, not steps/s at
a huge batch. This script measures, for one solver-loop unroll factor (the knob that trades compile
time for fewer device-loop iterations):

* ``env``: seconds per sequential step of ``jit(vmap(step))`` in a ``lax.scan``, at a few batches
  (``--step without-reset``: ``step_without_reset``, the same step without the auto-reset's
  ``reset_env``, which every env computes at every step under ``vmap``: the difference is its cost);
* ``ppo``: seconds per PPO update (one rollout and its epochs) with the env's student preset
  (``--ppo KEY=VALUE``: overrides, e.g. ``reset_draw=per_rollout``; ``--student rollout`` times
  one training rollout alone);
* ``eval``: seconds for ``student.evaluate`` on 10 levels x 8 episodes x 500 steps.

    python -m experiments.bench_latency --unroll 1 --out $OUT

Run it once per unroll value (and per XLA_FLAGS setting) in separate processes; writes
latency_u<unroll>[_<tag>].json.
"""
from __future__ import annotations

import argparse
import json
import os
import time

import jax

from shed_jax.runtime import provenance


def _timed(fn, *args, repeats=3):
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t)
    return compile_s, best


def env_latency(env, batch: int, steps: int, step_fn=None) -> dict:
    """Seconds per sequential step (best of 3 after the compile) of ``vmap(step_fn)`` in a
    ``lax.scan`` of ``steps``, random actions; ``step_fn`` defaults to ``env.step``."""
    compile_s, best = _timed(random_action_scan(env, batch, steps, step_fn), jax.random.PRNGKey(0))
    return dict(batch=batch, steps=steps, compile_s=compile_s, s_per_step=best / steps)


def random_action_scan(env, batch: int, steps: int, step_fn=None, final_state: bool = False):
    """A jitted ``run(key)``: ``batch`` envs on uniformly sampled levels reset, then ``steps`` sequential
    ``vmap(step_fn)`` with random actions in a ``lax.scan``; returns the summed reward, or with
    ``final_state`` the batch's last state."""
    step_fn = env.step if step_fn is None else step_fn
    levels = env.param_space.sample(jax.random.PRNGKey(1), (batch,))
    space = env.action_space()

    @jax.jit
    def run(key):
        obs, state = jax.vmap(env.reset)(jax.random.split(key, batch), levels)

        def body(c, k):
            obs, state = c
            ka, ks = jax.random.split(k)
            a = jax.vmap(space.sample)(jax.random.split(ka, batch))
            obs, state, r, d, _ = jax.vmap(step_fn)(jax.random.split(ks, batch), state, a, levels)
            return (obs, state), r.sum()

        (_, state), r = jax.lax.scan(body, (obs, state), jax.random.split(key, steps))
        return state if final_state else r.sum()

    return run


STUDENT_PARTS = ("rollout", "update", "eval")


def student_latency(env, env_name: str, ppo_overrides: dict | None = None, parts=("update", "eval")) -> dict:
    """Seconds (best of 3 after the compile) of the student's ``parts``: ``rollout`` (one training
    rollout, num_envs x num_steps, the env stepping alone), ``update`` (``train`` for one update: the
    levels' reset, a rollout and the epochs) and ``eval`` (10 levels x 8 episodes x 500 steps). Each
    part is its own program, so each costs a compile."""
    from shed_jax.student import PPOConfig, make_student

    student = make_student(env, PPOConfig.for_env(env_name).with_overrides(ppo_overrides))
    levels = env.param_space.sample(jax.random.PRNGKey(1), (5,))
    eval_levels = env.param_space.sample(jax.random.PRNGKey(2), (10,))
    s0 = jax.jit(student.init)(jax.random.PRNGKey(0))
    out = {"num_envs": student.config.num_envs, "num_steps": student.config.num_steps}  # one rollout's shape
    if "rollout" in parts:
        assigned = jax.jit(student.assign_levels)(s0, jax.random.PRNGKey(5), levels)
        out["rollout_compile_s"], out["rollout_s"] = _timed(jax.jit(student.rollout), assigned, jax.random.PRNGKey(6))
    if "update" in parts:
        train = jax.jit(lambda s, k: student.train(s, k, levels, 1)[0])
        out["ppo_compile_s"], out["ppo_update_s"] = _timed(train, s0, jax.random.PRNGKey(3))
    if "eval" in parts:
        evaluate = jax.jit(lambda s, k: student.evaluate(s, k, eval_levels, 8, 500))
        out["eval_compile_s"], out["eval_10x8x500_s"] = _timed(evaluate, s0, jax.random.PRNGKey(4))
    return out


def main(argv=None) -> int:
    from shed_jax.xla_gpu import apply_gpu_codegen

    apply_gpu_codegen()  # as python -m shed_jax compiles (before the backend starts)
    import envs

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--unroll", type=int, default=1)
    p.add_argument("--velocity-iterations", type=int, default=None, help="physics2d solver override (lander, bipedal)")
    p.add_argument("--position-iterations", type=int, default=None, help="physics2d solver override (lander, bipedal)")
    p.add_argument("--terrain-unroll", type=int, default=None,
                   help="walkers: columns per iteration of the terrain generator's loop (an auto-reset's terrain)")
    p.add_argument("--solver-kernel", default="auto", choices=["auto", "xla", "pallas", "interpret"],
                   help="physics2d solver loops (lander, bipedal): fused Pallas kernel or plain XLA (auto: Pallas on GPU)")
    p.add_argument("--step", default="step", choices=["step", "without-reset"],
                   help="time env.step (with its auto-reset) or env.step_without_reset")
    p.add_argument("--env", default="lander")
    p.add_argument("--batches", default="40,400,4096")
    p.add_argument("--steps", type=int, default=256)
    p.add_argument("--tag", default="")
    p.add_argument("--skip-student", action="store_true")
    p.add_argument("--student", default="update,eval",
                   help=f"the student timings to take, comma-separated, of {', '.join(STUDENT_PARTS)}")
    p.add_argument("--ppo", nargs="*", default=[], metavar="KEY=VALUE",
                   help="student preset overrides for the ppo/eval timings, e.g. reset_draw=per_rollout")
    p.add_argument("--out", default=os.environ.get("OUT", "."))
    args = p.parse_args(argv)
    from shed_jax.student.config import PPOConfig, parse_overrides

    try:  # up front: a bad override fails in one line before the work, not after it
        ppo = parse_overrides(args.ppo)
        PPOConfig.for_env(args.env).with_overrides(ppo)
    except ValueError as e:
        p.error(str(e))
    parts = tuple(x for x in args.student.split(",") if x)
    if not parts or set(parts) - set(STUDENT_PARTS):
        p.error(f"--student takes a comma-separated list of {', '.join(STUDENT_PARTS)}, got {args.student!r}")
    os.makedirs(args.out, exist_ok=True)  # likewise a bad path
    solver = {k: v for k, v in (("velocity_iterations", args.velocity_iterations),
                                ("position_iterations", args.position_iterations)) if v is not None}
    if args.solver_kernel != "auto":  # an env without the option (the MJX walker) refuses it by name
        solver["solver_kernel"] = args.solver_kernel
    if args.terrain_unroll is not None:  # an env without a terrain (the lander) refuses it by name
        solver["terrain_unroll"] = args.terrain_unroll
    unroll = {"unroll": args.unroll} if args.unroll != 1 else {}  # likewise: the MJX walker takes none
    env = envs.make(args.env, **unroll, **solver)
    res = dict(**provenance("experiments.bench_latency", argv), unroll=args.unroll, env=args.env, tag=args.tag,
               **solver, xla_flags=os.environ.get("XLA_FLAGS", ""), env_rows=[])
    res["solver_kernel"] = args.solver_kernel
    res["step"] = args.step
    step_fn = env.step if args.step == "step" else env.step_without_reset
    for b in (int(x) for x in args.batches.split(",") if x):  # "": no env rows (student timings only)
        row = env_latency(env, b, args.steps, step_fn)
        res["env_rows"].append(row)
        print(json.dumps(row), flush=True)
    if not args.skip_student:
        res.update(student_latency(env, args.env, ppo, parts), ppo_overrides=ppo)
        print(json.dumps({k: v for k, v in res.items() if k != "env_rows"}), flush=True)
    name = f"latency_u{args.unroll}{'_' + args.tag if args.tag else ''}.json"
    with open(os.path.join(args.out, name), "w") as f:
        json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
