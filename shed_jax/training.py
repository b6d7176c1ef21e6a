"""PPO on fixed levels: one student per seed (and hyperparameter set), vmapped, trained in chunks.

``train_seeds`` is the compiled training (``vmap`` over seeds of ``student.run_updates``), called on
consecutive chunks of updates for a progress bar and compiled once, ahead of time, so the compile
time is reported apart from the steps/s. ``train_fixed_level`` is ``python -m shed_jax ppo``: train,
evaluate, write ``summary.json``, ``learning_curve.png`` and ``policy.msgpack`` (``save_policy``; read
back with ``load_policy``, e.g. to evaluate the policies in another engine). experiments/ppo_sweep.py
and experiments/bench_ppo.py use these too.
"""
from __future__ import annotations

import json
import math
import pathlib
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np


def resolve_level(env, name: str | None):
    """One level (unbatched params): the env's default, or LEVELS[name] (a params object or a builder)."""
    if name is None:
        return env.default_params
    from shed_jax.evaluation import find_levels

    levels = find_levels(env)
    if levels is None:
        raise ValueError(f"{env.name} defines no named LEVELS; omit --level")
    if name not in levels:
        raise ValueError(f"{env.name}: unknown level {name!r}; known: {', '.join(levels)}")
    level = levels[name]
    return level() if callable(level) else level


def save_policy(path, states) -> None:
    """Write the policies of vmapped student ``states`` (every seed's network parameters and
    observation statistics; not the optimiser or env state) to ``path`` as flax msgpack."""
    from flax import serialization

    from shed_jax.student import Policy

    pathlib.Path(path).write_bytes(serialization.to_bytes(Policy(params=states.params, obs_norm=states.obs_norm)))


def policy_student(env, preset: str, path):
    """The student a saved ``policy.msgpack`` was trained as, with one env slot (for acting, not
    training): the env's PPO preset ``preset`` with the ``config`` of the ``summary.json`` that
    ``python -m shed_jax ppo`` writes beside the file (its ``--ppo`` settings, e.g. hidden sizes or
    log-std bounds); the preset alone when there is no such summary. ValueError of one line when the
    summary cannot be read as one."""
    from shed_jax import configs
    from shed_jax.student import PPOConfig, make_student

    config = PPOConfig.for_env(preset)
    summary = pathlib.Path(path).with_name("summary.json")
    if summary.is_file():
        try:
            saved = json.loads(summary.read_text()).get("config")
        except (ValueError, AttributeError) as err:
            raise ValueError(f"{summary}: not a summary of 'python -m shed_jax ppo' ({err})") from None
        if saved is not None:
            config = configs.with_overrides(config, {k: v for k, v in saved.items() if k != "hparams"}, f"{summary}: ")
    return make_student(env, config.replace(num_envs=1, num_minibatches=1))


def load_policy(student, path, seeds: int | None = None):
    """The inverse of ``save_policy``: a vmapped ``Policy`` of ``student`` (``seeds`` of them, default:
    as many as the file holds), ready for ``student.act`` / ``student.evaluate``; no env is reset.
    ValueError naming the first array that differs where the file is not such a policy (another
    student config, environment or seed count; flax itself does not compare shapes)."""
    from flax import serialization

    data = pathlib.Path(path).read_bytes()
    try:
        stored = serialization.msgpack_restore(data)
        leaves = jax.tree_util.tree_leaves(stored)
    except Exception as err:  # msgpack's own errors name no class worth keeping
        raise ValueError(f"{path} is not a flax msgpack file ({type(err).__name__}: {err})") from None
    if not isinstance(stored, dict) or not leaves:
        raise ValueError(f"{path} holds no saved policy (a flax msgpack of 'params' and 'obs_norm')")
    if seeds is None:
        seeds = int(np.shape(leaves[0])[0]) if np.ndim(leaves[0]) else 0
    fresh = jax.vmap(student.init_policy)(jax.random.split(jax.random.PRNGKey(0), max(seeds, 1)))
    want = serialization.to_state_dict(fresh)
    got_paths = dict(jax.tree_util.tree_flatten_with_path(stored)[0])
    for key_path, leaf in jax.tree_util.tree_flatten_with_path(want)[0]:
        name = jax.tree_util.keystr(key_path)
        if key_path not in got_paths:
            raise ValueError(f"{path} is not a policy of this student: it lacks {name}")
        if np.shape(got_paths[key_path]) != np.shape(leaf):
            raise ValueError(f"{path} is not a policy of this student: {name} has shape "
                             f"{np.shape(got_paths[key_path])}, expected {np.shape(leaf)} ({seeds} seed(s))")
    return serialization.from_state_dict(fresh, stored)


def train_seeds(student, keys, hparams, level, num_updates: int, chunks: int, progress: bool = True, on_chunk=None,
                start_chunk: int = 0, restore=None):
    """Train one student per row of `keys` (and of `hparams`, which has the same leading axis).

    Returns (states, metrics with leaves [B, updates_done], timing dict). `num_updates` is
    rounded up to a multiple of the chunk size so every chunk is the same compiled call.
    ``on_chunk(c, states, metrics_of_chunk)`` runs after each chunk; if it returns True the
    training stops there (an early stop, e.g. once a target return is reached), and the timing
    and metrics cover the chunks done. To continue an interrupted run, pass ``start_chunk`` (the
    chunks already done) and ``restore(states) -> states``, which puts the saved learning state
    into the freshly initialised (and freshly reset) states; the chunk keys are the same as in
    the uninterrupted run.
    """
    from tqdm import tqdm

    chunks = max(1, min(chunks, num_updates))
    per_chunk = math.ceil(num_updates / chunks)
    levels = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], level)

    def init_one(key, hp):
        k_init, k_assign = jax.random.split(key)
        return student.assign_levels(student.init(k_init, hp), k_assign, levels)

    def chunk_one(state, key):
        return student.run_updates(state, key, per_chunk)

    t0 = time.perf_counter()
    states = jax.jit(jax.vmap(init_one))(keys, hparams)
    if restore is not None:
        states = restore(states)
    chunk_keys = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, 1), chunks))(keys)  # [B, chunks]
    if start_chunk < chunks:  # else nothing is left to train (a finished run, restored to be evaluated)
        compiled = jax.jit(jax.vmap(chunk_one)).lower(states, chunk_keys[:, 0]).compile()
    jax.block_until_ready(states)
    compile_s = time.perf_counter() - t0
    history = []
    t1 = time.perf_counter()
    bar = tqdm(range(start_chunk, chunks), desc=f"ppo {student.env.name}", disable=not progress)
    for c in bar:
        states, m = compiled(states, chunk_keys[:, c])
        m = jax.device_get(m)
        history.append(m)
        with warnings.catch_warnings():  # chunks in which no episode ended give NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            ret = np.nanmean(m["episode_return"][:, -max(1, per_chunk // 4):], axis=1)
        bar.set_postfix(ret=f"{np.nanmedian(ret):.1f}", steps=f"{(c + 1) * per_chunk * student.env_steps_per_update:.3g}")
        if on_chunk is not None and on_chunk(c, states, m):
            break
    run_s = time.perf_counter() - t1
    metrics = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=1), *history) if history else {}
    run_updates = len(history) * per_chunk
    timing = {
        "compile_s": compile_s,
        "train_s": run_s,
        "updates": (start_chunk + len(history)) * per_chunk,  # in total, earlier runs included
        "updates_this_run": run_updates,
        "env_steps_per_seed": (start_chunk + len(history)) * per_chunk * student.env_steps_per_update,
        "env_steps_per_s": run_updates * student.env_steps_per_update * keys.shape[0] / run_s if run_updates else float("nan"),
    }
    return states, metrics, timing


def smoothed(x: np.ndarray, window: int) -> np.ndarray:
    """NaN-aware trailing moving average along the last axis (updates without finished episodes are NaN)."""
    x = np.asarray(x, np.float64)
    ok = np.isfinite(x)
    c = np.cumsum(np.where(ok, x, 0.0), axis=-1)
    n = np.cumsum(ok, axis=-1)
    c = np.concatenate([np.zeros(x.shape[:-1] + (1,)), c], axis=-1)
    n = np.concatenate([np.zeros(x.shape[:-1] + (1,)), n], axis=-1)
    idx = np.arange(x.shape[-1]) + 1
    lo = np.maximum(idx - window, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (c[..., idx] - c[..., lo]) / (n[..., idx] - n[..., lo])


def fixed_level_config(args):
    """The env's PPO preset with the ``ppo`` command's ``--ppo KEY=VALUE`` items, ``--num-envs`` and
    ``--lr`` applied (ValueError naming a bad field or value)."""
    from shed_jax.student import PPOConfig
    from shed_jax.student.config import parse_overrides

    overrides = parse_overrides(getattr(args, "ppo", None) or [])
    for key, value in (("num_envs", args.num_envs), ("lr", args.lr)):
        if value is not None:
            if key in overrides:
                raise ValueError(f"--{key.replace('_', '-')} and --ppo {key}=... both given; give one")
            overrides[key] = value
    return PPOConfig.for_env(args.env).with_overrides(overrides)


def train_fixed_level(args) -> dict:
    """``python -m shed_jax ppo``: ``args`` has its flags as attributes; writes ``args.out`` (default
    runs/ppo_<env>) and returns the summary."""
    import envs
    from shed_jax import reporting, runtime
    from shed_jax.student import PPOHyperparams, make_student

    env = envs.make(args.env)
    config = fixed_level_config(args)
    hp = config.hparams
    student = make_student(env, config)
    level = resolve_level(env, args.level)
    out = pathlib.Path(args.out or f"runs/ppo_{args.env}")
    out.mkdir(parents=True, exist_ok=True)

    num_updates = math.ceil(args.total_steps / student.env_steps_per_update)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.seeds)
    hps = PPOHyperparams.stack([hp] * args.seeds)
    t0 = time.perf_counter()
    states, metrics, timing = train_seeds(student, keys, hps, level, num_updates, args.chunks)
    # the policy first: the evaluation compiles a program of its own (minutes for a walker), and a run
    # stopped during it must not lose what it trained
    save_policy(out / "policy.msgpack", states)
    print(f"trained; wrote {out / 'policy.msgpack'}; final evaluation: {args.eval_episodes} episodes per seed "
          "(its compile comes first)", flush=True)

    levels = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], level)
    eval_keys = jax.vmap(lambda k: jax.random.fold_in(k, 2))(keys)
    evaluate = jax.jit(jax.vmap(lambda s, k: student.evaluate(s, k, levels, args.eval_episodes)))
    final = np.asarray(evaluate(states, eval_keys))[:, 0, :]  # [seeds, episodes]
    wall = time.perf_counter() - t0

    x = (np.arange(timing["updates"]) + 1) * student.env_steps_per_update
    curve = smoothed(metrics["episode_return"], 10)
    reporting.plot_curves(
        {args.env + (f" / {args.level}" if args.level else ""): (x, curve)},
        out / "learning_curve.png",
        xlabel="env steps per seed",
        ylabel="training episode return (10-update average)",
        title=f"PPO on {args.env}: mean and SE over {args.seeds} seeds",
    )
    summary = {
        "env": args.env,
        "level": args.level,
        "seeds": args.seeds,
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(config).items() if k != "hparams"},
        "hparams": {k: float(getattr(hp, k)) for k in ("lr", "ent_coef", "clip_eps", "vf_coef", "gamma", "gae_lambda", "max_grad_norm")},
        "final_return_mean": final.mean(axis=1).tolist(),
        "final_return_episodes": args.eval_episodes,
        "final_train_return": np.nanmean(np.asarray(metrics["episode_return"])[:, -10:], axis=1).tolist(),
        "env_steps": timing["env_steps_per_seed"],
        "env_steps_total": timing["env_steps_per_seed"] * args.seeds,
        "wall_time_s": wall,
        "compile_s": timing["compile_s"],
        "train_s": timing["train_s"],
        "steps_per_s": timing["env_steps_per_s"],
        **runtime.provenance("shed_jax"),
        "curve": {"env_steps": x[:: max(1, len(x) // 200)].tolist(),
                  "mean_return": np.nanmean(curve, axis=0)[:: max(1, len(x) // 200)].tolist()},
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    print(f"final return per seed: {np.round(final.mean(axis=1), 1).tolist()}  "
          f"({timing['env_steps_per_seed']:.3g} steps/seed, {timing['env_steps_per_s']:.3g} steps/s, wall {wall:.1f}s)")
    print(f"wrote {out / 'summary.json'}, {out / 'learning_curve.png'} and {out / 'policy.msgpack'}")
    return summary
