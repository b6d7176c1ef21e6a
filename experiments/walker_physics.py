"""Which MJX physics options keep the walker faithful, and what each costs (docs/walker.md).

Three sections; each writes its part of ``OUT/walker_physics.json`` (device, date, command kept):

``c``      (CPU is enough) For each option set, the walker's qpos under a fixed drive-then-collapse
           action sequence on the flat level, MJX against MuJoCo's C engine (a) with the same
           options (implementation parity) and (b) with a converged reference (10 substeps, 50
           Newton iterations: what the physics should do). Max |Δqpos| over the first 20 and all
           compared control steps.
``train``  (GPU) For each option set, ``--seeds`` vmapped PPO students (the walker preset) trained on
           the flat level for ``--steps`` env steps each; the policy parameters and observation
           statistics go to ``OUT/students_<name>.msgpack``; the time per env step is recorded.
``eval``   (GPU) Every saved student set evaluated under every option set on DCD's six named
           levels (stochastic policy, ``--episodes`` per level and seed): mean return and solved
           rate (return >= 230). Also MJX's time per control step for each option set at the
           evaluation batch.

    python -m experiments.walker_physics --sections c --out runs/physics
    python -m experiments.walker_physics --sections train,eval --seeds 4 --steps 4000000 --out $OUT
"""
from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import platform
import sys
import time

import numpy as np

#: name -> WalkerOptions fields. "s5i4" is the default today.
OPTION_SETS = {
    "s5i4": dict(substeps=5, solver_iterations=4, ls_iterations=5),
    "s4i2": dict(substeps=4, solver_iterations=2, ls_iterations=5),
    "s3i2": dict(substeps=3, solver_iterations=2, ls_iterations=2),
    "s3i1": dict(substeps=3, solver_iterations=1, ls_iterations=2),
}
REFERENCE = dict(substeps=10, solver_iterations=50, ls_iterations=50)
SOLVED = 230.0


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sections", default="c,train,eval")
    p.add_argument("--options", default=",".join(OPTION_SETS), help="option-set names, comma-separated")
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--steps", type=int, default=4_000_000, help="env steps per seed of training")
    p.add_argument("--episodes", type=int, default=16, help="evaluation episodes per level and seed")
    p.add_argument("--students", default=None, help="directory holding students_<name>.msgpack (default: --out)")
    p.add_argument("--out", required=True)
    return p.parse_args(argv)


def _gait(n=100):
    t = np.arange(n)[:, None]
    gait = np.concatenate([np.sin(0.15 * t + [0.0, 1.0]), np.cos(0.15 * t + [0.0, 1.0])], 1)[:, [0, 2, 1, 3]] * 0.6
    gait[5:] = 0.0  # drive briefly, then a passive collapse onto the knees (contacts, joint limits)
    return gait.astype(np.float32)


def _c_rollout(env, s0, acts, options):
    """qpos after each control step in MuJoCo C, the model built with ``options``, from state ``s0``."""
    import mujoco

    import envs
    from envs.walker.env import _SPEEDS as speeds

    ref_env = envs.make("walker", **options)
    m = ref_env.mj_model
    data = np.clip((s0.profile - s0.z_base) / ref_env.options.z_span, 0, 1)
    m.hfield_data[:] = np.concatenate([data, data])
    m.geom_pos[ref_env._terrain_geom, 2] = s0.z_base
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = s0.qpos, s0.qvel
    out = []
    for a in acts:
        for _ in range(ref_env.options.substeps):
            d.ctrl[:] = np.clip(ref_env.options.kv * (speeds * np.sign(a) - d.qvel[3:]), -80 * np.abs(a), 80 * np.abs(a))
            mujoco.mj_step(m, d)
        out.append(d.qpos.copy())
    return np.stack(out)


def section_c(names):
    import jax
    import jax.numpy as jnp

    import envs
    from envs.walker.levels import LEVELS

    acts = _gait()
    level = LEVELS["BipedalWalker"](terrain_seed=2, fixed_terrain=True)
    rows = {}
    for name in names:
        env = envs.make("walker", **OPTION_SETS[name])
        _, s = jax.jit(env.reset)(jax.random.PRNGKey(9), level)
        step = jax.jit(env.step)
        q, st, done_at = [], s, None
        for i, a in enumerate(acts):
            _, st, _, d, _ = step(jax.random.PRNGKey(i), st, jnp.asarray(a), level)
            q.append(np.asarray(st.qpos))
            if done_at is None and bool(d):
                done_at = i
        n = len(acts) if done_at is None else done_at  # compare the episode up to its end
        q = np.stack(q)[:n]
        s0 = jax.tree_util.tree_map(np.asarray, s)
        same = np.abs(_c_rollout(env, s0, acts, OPTION_SETS[name])[:n] - q)
        ref = np.abs(_c_rollout(env, s0, acts, REFERENCE)[:n] - q)
        rows[name] = {"steps_compared": int(n), "vs_c_same_options": {"first20": float(same[:20].max()), "all": float(same.max())},
                      "vs_c_reference": {"first20": float(ref[:20].max()), "all": float(ref.max())}}
        print(name, json.dumps(rows[name]), flush=True)
    return {"reference": REFERENCE, "actions": "0.6·sin/cos gait for 5 steps, then zero (passive collapse)", "rows": rows}


def _student(options):
    import envs
    from shed_jax.student import PPOConfig, make_student

    return make_student(envs.make("walker", **options), PPOConfig.for_env("walker"))


def section_train(names, seeds, steps, out, rows, save):
    import jax
    import jax.numpy as jnp
    from flax import serialization

    from envs.walker.levels import LEVELS

    level = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], LEVELS["BipedalWalker"]())
    for name in names:
        student = _student(OPTION_SETS[name])
        updates = -(-steps // student.env_steps_per_update)
        keys = jax.random.split(jax.random.PRNGKey(0), seeds)
        init = jax.jit(jax.vmap(student.init))
        train = jax.jit(jax.vmap(lambda s, k: student.train(s, k, level, updates)))
        t0 = time.perf_counter()
        states = jax.block_until_ready(init(keys))
        compiled = train.lower(states, keys).compile()
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        states, metrics = jax.block_until_ready(compiled(states, keys))
        train_s = time.perf_counter() - t0
        ret = np.asarray(metrics["episode_return"])  # [seeds, updates], NaN where no episode ended
        tail = [float(np.nanmean(r[-max(1, updates // 10):])) for r in ret]
        blob = serialization.to_bytes({"params": states.params, "obs_norm": states.obs_norm})
        (out / f"students_{name}.msgpack").write_bytes(blob)
        rows[name] = {"options": OPTION_SETS[name], "seeds": seeds, "env_steps_per_seed": updates * student.env_steps_per_update,
                      "compile_s": round(compile_s, 1), "train_s": round(train_s, 1),
                      "ms_per_sequential_env_step": round(1e3 * train_s / (updates * student.config.num_steps), 2),
                      "final_train_return_per_seed": tail}
        print(name, json.dumps(rows[name]), flush=True)
        save()


def section_eval(names, seeds, episodes, src):
    import jax
    from flax import serialization

    from shed_jax import eval_sets

    levels = eval_sets.walker_test_set_a()
    labels = list(eval_sets.DCD_TEST_LEVELS)
    trained = [n for n in names if (src / f"students_{n}.msgpack").exists()]
    rows, latency = {}, {}
    for phys in names:
        student = _student(OPTION_SETS[phys])
        fresh = jax.jit(jax.vmap(student.init))(jax.random.split(jax.random.PRNGKey(0), seeds))
        evaluate = jax.jit(jax.vmap(lambda s, k: student.evaluate_with_info(s, k, levels, episodes)))
        keys = jax.random.split(jax.random.PRNGKey(123), seeds)
        compiled = evaluate.lower(fresh, keys).compile()
        for tr in trained:
            saved = serialization.from_bytes({"params": fresh.params, "obs_norm": fresh.obs_norm},
                                             (src / f"students_{tr}.msgpack").read_bytes())
            states = fresh.replace(params=saved["params"], obs_norm=saved["obs_norm"])
            t0 = time.perf_counter()
            rets, info = jax.block_until_ready(compiled(states, keys))
            dt = time.perf_counter() - t0
            rets = np.asarray(rets)  # [seeds, levels, episodes]
            run = int(np.max(np.asarray(info["steps_run"])))
            latency.setdefault(phys, []).append(1e3 * dt / max(run, 1))
            rows[f"trained_{tr}/physics_{phys}"] = {
                lab: {"return": float(rets[:, i].mean()), "solved": float((rets[:, i] >= SOLVED).mean()),
                      "return_se_over_seeds": float(rets[:, i].mean(-1).std(ddof=1) / np.sqrt(seeds)) if seeds > 1 else None}
                for i, lab in enumerate(labels)}
            print(f"trained {tr} / physics {phys}: " + ", ".join(
                f"{lab} {v['return']:.0f} ({v['solved']:.2f})" for lab, v in rows[f"trained_{tr}/physics_{phys}"].items()), flush=True)
    return {"levels": labels, "episodes": episodes, "seeds": seeds, "rows": rows,
            "ms_per_control_step": {k: round(float(np.median(v)), 2) for k, v in latency.items()},
            "batch": seeds * len(labels) * episodes}


def main(argv=None) -> int:
    args = _parse(argv)
    import jax

    names = [n for n in args.options.split(",") if n]
    unknown = [n for n in names if n not in OPTION_SETS]
    if unknown:
        print(f"walker_physics: error: unknown option set(s) {unknown}; known: {list(OPTION_SETS)}", file=sys.stderr)
        return 2
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "walker_physics.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    where = {"device": str(jax.devices()[0].device_kind), "cpu": platform.processor() or platform.machine(),
             "date": datetime.date.today().isoformat(),
             "command": "python -m experiments.walker_physics " + " ".join(argv or sys.argv[1:])}
    key = {"c": "c_engine", "train": "train", "eval": "eval"}
    def save():
        path.write_text(json.dumps(record, indent=1))

    for section in args.sections.split(","):
        if section in key:  # each section says where, when and how it ran (they may run on different machines)
            record.setdefault("ran", {})[key[section]] = where
        if section == "c":
            record["c_engine"] = section_c(names)
        elif section == "train":
            section_train(names, args.seeds, args.steps, out, record.setdefault("train", {}), save)
        elif section == "eval":
            record["eval"] = section_eval(names, args.seeds, args.episodes, pathlib.Path(args.students or out))
        else:
            print(f"walker_physics: error: unknown section {section!r}; known: c, train, eval", file=sys.stderr)
            return 2
        save()
    return 0


if __name__ == "__main__":
    sys.exit(main())
