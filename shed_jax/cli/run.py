"""``python -m shed_jax run``: one UED method on one environment, seeds vmapped, end to end.

The compiled outer loop (``shed_jax.loop``) runs in chunks of budget steps; between chunks the
host writes per-step metrics (``metrics.jsonl``), prints a one-line summary and updates a progress
bar. At the end it writes ``summary.json`` and plots (mean test return with standard error over
seeds against student env steps; per-test-level curves; the generated level parameters).
"""
from __future__ import annotations

import json
import math
import pathlib
import time

import numpy as np

TEST_SETS = ("lander-test", "walker-test-a", "walker-test-b")


def add_arguments(p) -> None:
    from shed_jax.presets import PRESETS

    p.add_argument("--env", default="lander", help="lander | lander-continuous | walker")
    p.add_argument("--method", default="shed", help="shed | hmdp | dr | paired | accel | accel-norevisit | plr")
    p.add_argument("--preset", default="auto", choices=("auto",) + PRESETS,
                   help="auto: 'paper' on a GPU, 'quick' on a CPU (the choice is printed)")
    p.add_argument("--seeds", type=int, default=None, help="number of vmapped seeds (default: quick 2, paper 5)")
    p.add_argument("--seed", type=int, default=0, help="root seed; seed i of the batch uses fold_in(root, i)")
    p.add_argument("--episodes", type=int, default=None, help="override the number of teacher episodes N_ep")
    p.add_argument("--steps-per-episode", type=int, default=None, help="override the budget steps per episode T")
    p.add_argument("--chunk", type=int, default=None, help="budget steps per compiled call (default: T)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the method's config (repeatable), e.g. --set eta=10")
    p.add_argument("--out", default=None, help="run directory (default runs/<env>-<method>-<preset>-<time>)")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF of the final student")


def _parse_overrides(items: list[str]) -> dict:
    out = {}
    for item in items:
        if "=" not in item:
            raise SystemExit(f"--set expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def test_levels(name: str, env):
    from shed_jax import eval_sets

    if name == "lander-test":
        return eval_sets.lander_test_set().to_params(env.default_params)
    if name == "walker-test-b":
        return eval_sets.walker_test_set_b().to_params(env.default_params)
    if name == "walker-test-a":
        return eval_sets.walker_test_set_a()
    raise ValueError(f"unknown test set {name!r}; known: {', '.join(TEST_SETS)}")


def build(exp):
    """Environment, student, method and test levels for an Experiment."""
    import envs
    from shed_jax.methods.registry import make_method
    from shed_jax.student import make_student

    env = envs.make(exp.env)
    student = make_student(env, exp.ppo)
    method = make_method(exp.method, env, student, dict(exp.method_config))
    return env, student, method, test_levels(exp.test_set, env)


def main(args) -> int:
    import jax
    from tqdm import tqdm

    from shed_jax import reporting
    from shed_jax.loop import make_run
    from shed_jax.presets import build_experiment

    backend = jax.default_backend()
    preset = args.preset
    if preset == "auto":
        preset = "paper" if backend == "gpu" else "quick"
        print(f"[shed_jax] backend={backend}: using the '{preset}' preset "
              f"({'GPU budgets from SPEC 6.3' if preset == 'paper' else 'a CPU-sized smoke run; pass --preset paper for the real budget'})")
    exp = build_experiment(args.env, args.method, preset, episodes=args.episodes,
                           steps_per_episode=args.steps_per_episode, method_overrides=_parse_overrides(args.set))
    num_seeds = args.seeds or (5 if preset == "paper" else 2)
    if num_seeds < 1:
        raise SystemExit("--seeds must be >= 1")
    out = pathlib.Path(args.out or f"runs/{exp.env}-{exp.method}-{preset}-{time.strftime('%Y%m%d-%H%M%S')}")
    out.mkdir(parents=True, exist_ok=True)
    if (out / "metrics.jsonl").exists():
        raise SystemExit(f"{out} already holds a run (metrics.jsonl); choose another --out")

    env, student, method, tests = build(exp)
    init, run = make_run(student, method, tests, exp.loop)
    total = exp.loop.total_steps
    chunk = args.chunk or exp.loop.steps_per_episode
    if chunk < 1:
        raise SystemExit("--chunk must be >= 1")
    config = {"experiment": exp.to_dict(), "seeds": num_seeds, "root_seed": args.seed, "backend": backend,
              "devices": [str(d) for d in jax.devices()], "chunk": chunk, "jax": jax.__version__}
    (out / "config.json").write_text(json.dumps(config, indent=2, default=str))
    print(f"[shed_jax] {exp.method} on {exp.env}: {exp.loop.num_episodes} episode(s) x {exp.loop.steps_per_episode} "
          f"budget steps, {num_seeds} seed(s), ~{exp.env_steps_per_budget_step:,} student env steps per budget step -> {out}")

    root = jax.random.PRNGKey(args.seed)
    keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(np.arange(num_seeds))
    state = jax.jit(jax.vmap(init))(keys)
    run_chunk = jax.jit(jax.vmap(run, in_axes=(0, None, None)), static_argnums=1)

    history: dict[str, list[np.ndarray]] = {}
    done = 0
    t0 = time.time()
    bar = tqdm(total=total, unit="step", desc=f"{exp.method}/{exp.env}", dynamic_ncols=True)
    while done < total:
        n = min(chunk, total - done)
        state, metrics = run_chunk(state, n, done)
        flat = reporting.flatten_tree(jax.device_get(metrics))
        for k, v in flat.items():
            history.setdefault(k, []).append(v)
        reporting.append_jsonl(out / "metrics.jsonl", reporting.step_records(flat, range(num_seeds)))
        done += n
        bar.update(n)
        steps_train = np.sum(np.concatenate(history["info/env_steps_train"], axis=1), axis=1).mean()
        tr = flat["test_return"][:, -1]
        teacher_r = np.nanmean(flat["info/teacher_reward"]) if np.any(np.isfinite(flat["info/teacher_reward"])) else math.nan
        bar.write(f"step {done:5d}/{total}  episode {int(flat['episode'][0, -1])}  student env steps/seed {steps_train:,.0f}  "
                  f"test return {np.nanmean(tr):8.1f} ± {reporting.mean_se(tr)[1]:.1f}  teacher reward {teacher_r:8.3f}  "
                  f"{steps_train * num_seeds / max(time.time() - t0, 1e-9):,.0f} train steps/s")
    bar.close()
    wall = time.time() - t0
    hist = {k: np.concatenate(v, axis=1) for k, v in history.items()}
    summary = summarize(exp, hist, wall, num_seeds)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    make_plots(exp, env, hist, out)
    if not args.no_gif:
        try:
            from shed_jax.visualize import student_gif

            path = student_gif(env, student, state, tests, out / "final_student.gif")
            print(f"[shed_jax] wrote {path}")
        except NotImplementedError as err:  # an env without a renderer
            print(f"[shed_jax] no GIF: {err}")
    print(json.dumps({k: summary[k] for k in ("final_test_return_mean", "final_test_return_se", "wall_time_s")}, indent=2))
    print(f"[shed_jax] results in {out}")
    return 0


def summarize(exp, hist: dict, wall: float, num_seeds: int) -> dict:
    from shed_jax import reporting

    T = exp.loop.steps_per_episode
    last = hist["test_return"][:, -1]
    m, se = reporting.mean_se(last)
    last_ep = hist["episode"][0] == hist["episode"][0, -1]
    train_steps = hist["info/env_steps_train"].astype(np.float64)
    return {
        "env": exp.env, "method": exp.method, "preset": exp.preset, "seeds": num_seeds,
        "budget_steps": int(hist["step"].shape[1]), "steps_per_episode": T,
        "final_test_return_mean": float(m), "final_test_return_se": float(se),
        "final_test_return_per_seed": [float(x) for x in last],
        "final_test_return_per_level": [float(x) for x in np.nanmean(hist["test_return_per_level"][:, -1], axis=0)],
        "student_env_steps_last_episode": float(train_steps[:, last_ep].sum(axis=1).mean()),
        "student_env_steps_total": float(train_steps.sum(axis=1).mean()),
        "eval_env_steps_total": float(hist["info/env_steps_eval"].astype(np.float64).sum(axis=1).mean()),
        "wall_time_s": wall,
        "wall_time_per_seed_s": wall / num_seeds,
    }


def make_plots(exp, env, hist: dict, out: pathlib.Path) -> None:
    from shed_jax import reporting

    episode = hist["episode"][0]
    last = episode == episode[-1]
    x = np.cumsum(hist["info/env_steps_train"][0, last].astype(np.float64))
    y = hist["test_return"][:, last]
    label = f"{exp.method} (last teacher episode)" if exp.loop.num_episodes > 1 else exp.method
    reporting.plot_curves({label: (x, y)}, out / "test_return.png", xlabel="student env steps", ylabel="mean test return",
                          title=f"{exp.method} on {exp.env}: test return (mean ± SE over seeds)")
    per_level = hist["test_return_per_level"][:, last]  # [S, steps, L]
    curves = {f"level {j}": (x, per_level[..., j]) for j in range(per_level.shape[-1])}
    reporting.plot_curves(curves, out / "test_return_per_level.png", xlabel="student env steps", ylabel="test return",
                          title=f"{exp.method} on {exp.env}: per test level")
    levels = hist.get("info/levels")
    if levels is not None and levels.ndim == 4 and levels.shape[-1] == env.param_space.dim:
        xs = np.arange(levels.shape[1])
        reporting.plot_parameters(xs, levels, env.param_space.names, out / "generated_levels.png",
                                  title=f"{exp.method} on {exp.env}: generated level parameters per budget step")
