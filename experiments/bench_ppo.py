"""GPU learning benchmark of the PPO student (run by the lead on one H200).

    OUT=runs/bench_ppo python -m experiments.bench_ppo            # everything, defaults below
    python -m experiments.bench_ppo --sections lander --total-steps 3000000 --seeds 8 --out DIR

Sections (each is independent; a failure is recorded in results.json and the next one runs):
  lander / lander-continuous  8 vmapped seeds to 3M env steps (docs/design.md §10.1 preset). Records the
                              learning curve (training episode returns), the first env step at
                              which the median over seeds reaches 200 (docs/design.md §10.1 acceptance), the
                              final evaluation return per seed (stochastic and deterministic
                              policy), compile time, env steps/s and wall time.
  walker                      4 vmapped seeds on a flat level (`--walker-level`, default
                              "BipedalWalker") up to `--walker-steps`; target 230.
  brax                        Brax's own PPO (brax.training.agents.ppo.train) on `--brax-env`
                              (lander-continuous or walker; Brax's PPO has only tanh-Gaussian
                              policies) through a thin adapter to brax's Env interface, with the
                              same network sizes and PPO settings, `--brax-seeds` runs one after
                              another; reports env steps/s and the final evaluation return, and
                              their ratios to ours at equal env steps.
Options for long runs: `--ppo KEY=VALUE ...` overrides the preset (e.g. num_envs=2048);
`--stop-at R` ends a student section once the median training return reaches R; `--log FILE`
appends one JSON line per chunk; `--ckpt DIR` saves the learning state after every chunk (orbax,
`shed_jax.checkpoint.RunCheckpointer`, in DIR/checkpoints) and continues from it when run again
(`--time-limit S` stops in time for the next device call, and `--eval-only` only evaluates the
checkpoint). One device command may run at most 10 minutes:
    python -m experiments.bench_ppo --sections walker --ppo num_envs=2048 --stop-at 230 \
        --walker-steps 100000000 --chunks 100 --ckpt /tmp/wck --time-limit 500 --out $OUT/walker
Writes OUT/results.json and OUT/<section>_curve.png.
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import pathlib
import sys
import time
import traceback
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from shed_jax.checkpoint import CheckpointNotFoundError, ConfigMismatchError, RunCheckpointer, check_config
from shed_jax.student.config import parse_overrides

TARGETS = {"walker": 230.0}  # issue 4: walker >= 230, the landers >= 200


def target_of(env_name):
    return TARGETS.get(env_name, 200.0)


def first_crossing(x, y, target):
    """First x at which y >= target (None if never)."""
    idx = np.flatnonzero(np.asarray(y) >= target)
    return None if idx.size == 0 else int(x[idx[0]])


def make_config(env_name, overrides=None):
    """The env's PPO preset with ``overrides`` (from ``parse_overrides``) applied."""
    from shed_jax.student import PPOConfig

    config = PPOConfig.for_env(env_name) if env_name in ("lander", "lander-continuous", "walker", "cartpole") else PPOConfig()
    return config.with_overrides(overrides)


def _concat(history):
    """Per-chunk metrics dicts ([seeds, updates_of_chunk] leaves) -> one dict over all updates."""
    return {k: np.concatenate([h[k] for h in history], axis=1) for k in history[0]}


def _learning_state(states):
    """What a resumed run keeps: everything but the env slots (those are reset on resume)."""
    return states.replace(env_state=None, obs=None, levels=None)


def save_checkpoint(ckpt, states, history, meta, chunks_done):
    """Save the learning state and the per-update metrics after chunk ``chunks_done``, with ``meta``
    as the run configuration: the project's orbax ``RunCheckpointer`` (atomic, digest-checked; only
    the latest is kept)."""
    with RunCheckpointer(ckpt, keep=1, async_save=False) as ck:
        ck.save(chunks_done, _learning_state(states), _concat(history), config=meta)


def load_checkpoint(ckpt, meta_expected):
    """(chunks_done, restore_fn, history) from `ckpt`, or (0, None, []) if it holds none.
    A checkpoint of another configuration is an error, never silently restarted."""
    try:
        with RunCheckpointer(ckpt, keep=1, create=False, async_save=False) as ck:
            step = ck.latest_step()
            if step is None:
                return 0, None, []
            try:
                check_config(ck.read_config(step), meta_expected, keys=list(meta_expected))
            except ConfigMismatchError as err:
                raise ValueError(f"checkpoint {ckpt} is from another run configuration: {err}") from err
            history = [ck.read_history(step)]
    except CheckpointNotFoundError:
        return 0, None, []

    def restore(states):
        # restore only after the fresh states are ready (the XLA:CPU hangs once seen here were the
        # batched-LAPACK deadlock of the vmapped init, now avoided, shed_jax/xla_cpu.py)
        states = jax.block_until_ready(states)
        with RunCheckpointer(ckpt, keep=1, create=False, async_save=False) as ck:
            saved = ck.restore(_learning_state(states), step=step, with_history=False).state
        # the running returns restart at zero with the freshly reset envs: keep the fresh ones
        return states.replace(params=saved.params, opt_state=saved.opt_state, hparams=saved.hparams,
                              obs_norm=saved.obs_norm, ret_norm=saved.ret_norm.replace(ret=states.ret_norm.ret),
                              update_step=saved.update_step)

    return step, restore, history


def bench_student(env_name, total_steps, seeds, out, level_name=None, chunks=20, eval_episodes=16, seed=0,
                  overrides=None, stop_at=None, log_path=None, ckpt=None, time_limit=None, eval_only=False,
                  eval_every=None):
    """Train `seeds` vmapped students; ``stop_at``: stop after the first chunk at whose end the
    median over seeds of the training return (whole chunk) is >= stop_at.
    ``log_path``: one JSON line per chunk (env steps, per-seed return, elapsed seconds).
    ``ckpt``: a directory; the learning state is saved there after every chunk, and a run that
    finds a checkpoint there continues from it (with freshly reset env slots: episodes running at
    the save are cut, which is the only difference from an uninterrupted run).
    ``time_limit``: seconds; stop after the chunk after which another chunk would not fit.
    ``eval_only``: restore the checkpoint and only evaluate it (curve from the saved metrics).
    ``eval_every``: env steps per seed; after each chunk that crosses a multiple of it, the
    stochastic policy plays ``eval_episodes`` episodes per seed on the level (``evals`` in the
    result, with the first env step at which the median over seeds, and each seed, reaches the
    target)."""
    import envs
    from shed_jax import reporting
    from shed_jax.training import resolve_level, smoothed, train_seeds
    from shed_jax.student import PPOHyperparams, make_student

    env = envs.make(env_name)
    config = make_config(env_name, overrides)
    student = make_student(env, config)
    level = resolve_level(env, level_name)
    keys = jax.random.split(jax.random.PRNGKey(seed), seeds)
    hps = PPOHyperparams.stack([config.hparams] * seeds)
    num_updates = -(-total_steps // student.env_steps_per_update)
    chunks = max(1, min(chunks, num_updates))
    per_chunk = -(-num_updates // chunks)
    t_start = time.perf_counter()
    ckpt = None if ckpt is None else pathlib.Path(ckpt)
    meta = {"env": env_name, "level": level_name, "seeds": seeds, "seed": seed, "chunks": chunks,
            "per_chunk": per_chunk, "config": repr(config)}
    start_chunk, restore, history = (0, None, []) if ckpt is None else load_checkpoint(ckpt, meta)
    if eval_only:
        if not start_chunk:
            raise ValueError(f"--eval-only needs a checkpoint in --ckpt; none in {ckpt}")
        chunks = start_chunk  # train nothing more: restore, then evaluate
    if start_chunk:
        print(f"resuming from {ckpt} after chunk {start_chunk} of {chunks}", flush=True)

    stop = {}
    evals = []
    levels = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], level)
    evaluate = jax.jit(jax.vmap(lambda s, k: student.evaluate(s, k, levels, eval_episodes, None, False)))

    def on_chunk(c, states, m):
        steps = (c + 1) * per_chunk * student.env_steps_per_update
        if eval_every and steps // eval_every > c * per_chunk * student.env_steps_per_update // eval_every:
            r = np.asarray(evaluate(states, jax.vmap(lambda k: jax.random.fold_in(k, 1000 + c))(keys)))[:, 0]
            evals.append({"env_steps_per_seed": steps, "per_seed": r.mean(1).tolist()})
            print(f"eval at {steps:,} steps: median {np.median(r.mean(1)):.1f}, per seed "
                  f"{np.round(r.mean(1), 1).tolist()}", flush=True)
        # mean over the whole chunk of the training episodes that ended in it (NaN: none ended;
        # long episodes on a synchronised batch, e.g. the walker's 2000 steps, can skip a chunk)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ret = np.nanmean(m["episode_return"], axis=1)
            med = float(np.nanmedian(ret))
        if log_path is not None:
            with open(log_path, "a") as f:
                f.write(json.dumps({"chunk": c, "env_steps_per_seed": (c + 1) * per_chunk * student.env_steps_per_update,
                                    "train_return": ret.tolist(), "median": med,
                                    "elapsed_s": time.perf_counter() - t_start}) + "\n")
        history.append(m)
        if ckpt is not None:
            save_checkpoint(ckpt, states, history, meta, c + 1)
        if stop_at is not None and med >= stop_at:
            stop["reason"] = f"median training return {med:.1f} >= {stop_at}"
        elapsed = time.perf_counter() - t_start
        stop["chunk_s"] = elapsed - stop.get("elapsed", 0.0)
        stop["elapsed"] = elapsed
        if time_limit is not None and elapsed + 1.2 * stop["chunk_s"] > time_limit:
            stop.setdefault("reason", f"time limit {time_limit:.0f} s")
        return "reason" in stop

    t0 = time.perf_counter()
    states, _, timing = train_seeds(student, keys, hps, level, chunks * per_chunk, chunks, progress=True,
                                    on_chunk=on_chunk, start_chunk=start_chunk, restore=restore)
    train_wall = time.perf_counter() - t0
    metrics = _concat(history)
    if stop.get("reason", "").startswith("time limit"):  # to be continued from the checkpoint
        return {"env": env_name, "seeds": seeds, "stop_reason": stop["reason"], "resumed_from_chunk": start_chunk,
                "env_steps_per_seed": timing["env_steps_per_seed"], "compile_s": timing["compile_s"],
                "train_s": timing["train_s"], "env_steps_per_s": timing["env_steps_per_s"]}

    final = {}
    for det in (False, True):
        ev = jax.jit(jax.vmap(lambda s, k: student.evaluate(s, k, levels, eval_episodes, None, det)))
        final["deterministic" if det else "stochastic"] = np.asarray(ev(states, jax.vmap(lambda k: jax.random.fold_in(k, 7))(keys)))[:, 0]
    target = target_of(env_name)
    x = (np.arange(timing["updates"]) + 1) * student.env_steps_per_update
    curve = smoothed(metrics["episode_return"], 10)  # [seeds, updates]
    median = np.nanmedian(curve, axis=0)
    reporting.plot_curves({env_name: (x, curve)}, out / f"{env_name}_curve.png", xlabel="env steps per seed",
                          ylabel="training episode return (10-update avg)",
                          title=f"PPO student on {env_name}{' / ' + level_name if level_name else ''}: {seeds} seeds",
                          references={str(target): target})
    crossings = [first_crossing(x, c, target) for c in curve]
    stride = max(1, len(x) // 300)
    eval_steps = np.array([e["env_steps_per_seed"] for e in evals])
    eval_returns = np.array([e["per_seed"] for e in evals]).reshape(len(evals), seeds)  # [evals, seeds]
    return {
        "env": env_name, "level": level_name, "seeds": seeds,
        "config": {k: v for k, v in dataclasses.asdict(config).items() if k != "hparams"},
        "hparams": {f: float(getattr(config.hparams, f)) for f in PPOHyperparams.__dataclass_fields__},
        "stop_reason": stop.get("reason"),
        "resumed_from_chunk": start_chunk,
        "env_steps_per_seed": timing["env_steps_per_seed"],
        "compile_s": timing["compile_s"], "train_s": timing["train_s"], "wall_s": train_wall,
        "env_steps_per_s": timing["env_steps_per_s"],
        "target": target,
        "median_reaches_target_at": first_crossing(x, median, target),
        "seeds_reaching_target_within_1e6": sum(c is not None and c <= 1_000_000 for c in crossings),
        "final_eval_stochastic": final["stochastic"].mean(1).tolist(),
        "final_eval_deterministic": final["deterministic"].mean(1).tolist(),
        "final_eval_median_stochastic": float(np.median(final["stochastic"].mean(1))),
        "final_train_return": np.nanmean(curve[:, -10:], axis=1).tolist(),
        "evals": evals,
        "eval_median_reaches_target_at": first_crossing(eval_steps, np.median(eval_returns, 1), target) if evals else None,
        "eval_seed_reaches_target_at": [first_crossing(eval_steps, eval_returns[:, i], target) for i in range(seeds)] if evals else None,
        "curve_env_steps": x[::stride].tolist(),
        "curve_median": median[::stride].tolist(),
        "curve_mean": np.nanmean(curve, axis=0)[::stride].tolist(),
    }


# --------------------------------------------------------------------------------------------
# Brax PPO through an adapter
# --------------------------------------------------------------------------------------------


def _brax_compat():
    """brax 0.14.2's PPO calls jax.device_put_replicated, which jax 0.11 removed (docs/design.md §12.3)."""
    if not hasattr(jax, "device_put_replicated"):
        def device_put_replicated(x, devices):
            stacked = jax.tree_util.tree_map(lambda a: jnp.stack([jnp.asarray(a)] * len(devices)), x)
            if len(devices) == 1:
                return jax.device_put(stacked, devices[0])
            mesh = jax.sharding.Mesh(np.array(devices), ("d",))
            return jax.device_put(stacked, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("d")))
        jax.device_put_replicated = device_put_replicated


def make_brax_adapter(env, level):
    """Our env (auto-reset, time limit, truncation flag) behind brax's Env interface, one level.

    Brax steps carry no key, so the PRNG key lives in state.info. The episode bookkeeping brax's
    PPO reads (truncation, episode_metrics, episode_done) is filled from our env's info.
    """
    from brax.envs.base import Env, State

    class Adapter(Env):
        def reset(self, rng):
            k_reset, k_next = jax.random.split(rng)
            obs, s = env.reset(k_reset, level)
            zero = jnp.zeros((), jnp.float32)
            info = {"rng": k_next, "truncation": zero, "episode_done": zero, "steps": zero,
                    "episode_metrics": {"sum_reward": zero, "length": zero}}
            return State(pipeline_state=s, obs=obs, reward=zero, done=zero, metrics={}, info=info)

        def step(self, state, action):
            k_step, k_next = jax.random.split(state.info["rng"])
            obs, s, r, done, info = env.step(k_step, state.pipeline_state, action, level)
            ep_ret = jnp.where(done, info["episode_return"], s.episode_return)
            ep_len = jnp.where(done, info["episode_length"], s.time).astype(jnp.float32)
            new_info = {"rng": k_next, "truncation": info["truncated"].astype(jnp.float32),
                        "episode_done": done.astype(jnp.float32), "steps": ep_len,
                        "episode_metrics": {"sum_reward": ep_ret, "length": ep_len}}
            return state.replace(pipeline_state=s, obs=obs, reward=r, done=done.astype(jnp.float32), info=new_info)

        @property
        def observation_size(self):
            return int(np.prod(env.observation_space(None).shape))

        @property
        def action_size(self):
            return int(env.action_space(None).shape[0])

        @property
        def backend(self):
            return "jax"

    return Adapter()


def bench_brax(env_name, total_steps, seeds, ours, level_name=None, overrides=None, seed0=0):
    cfg = make_config(env_name, overrides)
    # Brax's minibatches are whole rollouts (batch_size envs x unroll_length steps); ours are
    # num_envs * num_steps / num_minibatches samples. They match only when envs split evenly.
    if cfg.num_envs % cfg.num_minibatches:
        raise ValueError(
            f"Brax PPO needs num_envs ({cfg.num_envs}) divisible by num_minibatches ({cfg.num_minibatches}) "
            f"to use the same minibatches as ours; pass e.g. --ppo num_minibatches=8"
        )
    import envs
    from brax.envs.wrappers.training import VmapWrapper
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as ppo

    from shed_jax.training import resolve_level

    _brax_compat()
    env = envs.make(env_name)
    hp = cfg.hparams
    level = resolve_level(env, level_name)
    adapter = make_brax_adapter(env, level)
    max_steps = int(level.max_steps)
    results = []
    for seed in range(seed0, seed0 + seeds):
        evals = []
        t0 = time.perf_counter()
        ppo.train(
            environment=adapter,
            num_timesteps=total_steps,
            wrap_env_fn=lambda e, **kw: VmapWrapper(e),  # our env already auto-resets and truncates
            num_envs=cfg.num_envs,
            episode_length=max_steps,
            unroll_length=cfg.num_steps,
            batch_size=cfg.num_envs // cfg.num_minibatches,
            num_minibatches=cfg.num_minibatches,
            num_updates_per_batch=cfg.update_epochs,
            learning_rate=hp.lr,
            entropy_cost=hp.ent_coef,
            discounting=hp.gamma,
            gae_lambda=hp.gae_lambda,
            clipping_epsilon=hp.clip_eps,
            vf_loss_coefficient=hp.vf_coef,
            max_grad_norm=hp.max_grad_norm,
            normalize_advantage=True,
            network_factory=functools.partial(ppo_networks.make_ppo_networks, policy_hidden_layer_sizes=cfg.actor_hidden,
                                              value_hidden_layer_sizes=cfg.critic_hidden),
            num_evals=5,
            num_eval_envs=16,
            seed=seed,
            progress_fn=lambda step, m: (evals.append((int(step), float(m.get("eval/episode_reward", np.nan)), time.perf_counter())),
                                         print(f"brax {env_name} seed {seed}: step {int(step)} eval return "
                                               f"{evals[-1][1]:.1f} at {evals[-1][2] - t0:.0f} s", flush=True)),
        )
        wall = time.perf_counter() - t0
        # steady-state rate between the first and last progress callbacks: excludes the initial
        # compile, includes brax's periodic evaluations (its own end-to-end training loop)
        steady = (evals[-1][0] - evals[0][0]) / (evals[-1][2] - evals[0][2]) if len(evals) > 1 else float("nan")
        results.append({"seed": seed, "wall_s": wall, "env_steps_per_s_incl_compile": total_steps / wall,
                        "env_steps_per_s": steady, "evals": [e[:2] for e in evals],
                        "final_eval": evals[-1][1] if evals else None})
    final = [r["final_eval"] for r in results]
    out = {"env": env_name, "seeds": seeds, "env_steps": total_steps, "runs": results,
           "final_eval_median": float(np.median(final)),
           "env_steps_per_s_per_seed": float(np.median([r["env_steps_per_s"] for r in results]))}
    if ours is not None:
        ours_per_seed_rate = ours["env_steps_per_s"] / ours["seeds"]
        out["throughput_ratio_ours_over_brax_per_seed"] = ours_per_seed_rate / out["env_steps_per_s_per_seed"]
        out["throughput_ratio_ours_vmapped_over_brax"] = ours["env_steps_per_s"] / out["env_steps_per_s_per_seed"]
        out["final_return_ratio_ours_over_brax"] = ours["final_eval_median_stochastic"] / out["final_eval_median"] if out["final_eval_median"] else None
        out["note"] = "ours: median over vmapped seeds of the stochastic-policy evaluation; brax: its own final eval (16 envs)"
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sections", nargs="+", default=["lander", "lander-continuous", "walker", "brax"])
    p.add_argument("--total-steps", type=int, default=3_000_000)
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--walker-steps", type=int, default=1_000_000, help="per seed; keep a run under the 10-minute device limit")
    p.add_argument("--walker-seeds", type=int, default=4)
    p.add_argument("--walker-level", default="BipedalWalker")
    p.add_argument("--eval-every", type=int, default=None,
                   help="env steps per seed between evaluations of the stochastic policy (16 episodes per seed)")
    p.add_argument("--brax-seeds", type=int, default=3)
    p.add_argument("--brax-env", default="lander-continuous", help="a registered env with a Box action space")
    p.add_argument("--brax-level", default=None, help="a named level of --brax-env (default: its default level)")
    p.add_argument("--chunks", type=int, default=20)
    p.add_argument("--ppo", nargs="*", default=[], metavar="KEY=VALUE",
                   help="PPOConfig / PPOHyperparams overrides for every section, e.g. num_envs=2048 ent_coef=0")
    p.add_argument("--stop-at", type=float, default=None,
                   help="stop a student section once the median training return over seeds reaches this")
    p.add_argument("--log", default=None, help="append one JSON line per chunk to this file (progress of long runs)")
    p.add_argument("--ckpt", default=None, help="save the learning state here after every chunk; continue from it if present")
    p.add_argument("--time-limit", type=float, default=None,
                   help="seconds: stop (checkpoint kept) before a chunk would end after this; needs --ckpt")
    p.add_argument("--eval-only", action="store_true", help="evaluate the checkpoint in --ckpt without training further")
    p.add_argument("--brax-seed0", type=int, default=0, help="first Brax seed (runs seeds seed0 .. seed0+brax_seeds-1)")
    p.add_argument("--out", default=os.environ.get("OUT", "runs/bench_ppo"))
    args = p.parse_args(argv)
    if args.time_limit is not None and args.ckpt is None:
        p.error("--time-limit needs --ckpt (the run continues from the checkpoint later)")
    overrides = parse_overrides(args.ppo)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
               "date": time.strftime("%Y-%m-%d", time.gmtime()),
               "command": "python -m experiments.bench_ppo " + " ".join(argv if argv is not None else sys.argv[1:]),
               "sections": {}}

    def save():
        (out / "results.json").write_text(json.dumps(results, indent=2, default=float))

    for section in args.sections:
        t0 = time.perf_counter()
        try:
            if section == "walker":
                r = bench_student("walker", args.walker_steps, args.walker_seeds, out, args.walker_level, args.chunks,
                                  overrides=overrides, stop_at=args.stop_at, log_path=args.log, ckpt=args.ckpt,
                                  time_limit=args.time_limit, eval_only=args.eval_only, eval_every=args.eval_every)
            elif section == "brax":
                r = bench_brax(args.brax_env, args.total_steps, args.brax_seeds, results["sections"].get(args.brax_env),
                               args.brax_level, overrides, args.brax_seed0)
            else:
                r = bench_student(section, args.total_steps, args.seeds, out, None, args.chunks,
                                  overrides=overrides, stop_at=args.stop_at, log_path=args.log, ckpt=args.ckpt,
                                  time_limit=args.time_limit, eval_only=args.eval_only, eval_every=args.eval_every)
        except Exception as err:  # record and go on with the other sections
            r = {"error": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc()[-4000:]}
        r["section_wall_s"] = time.perf_counter() - t0
        results["sections"][section] = r
        save()
        summary = {k: v for k, v in r.items() if not k.startswith("curve") and k not in ("runs", "traceback")}
        print(section, json.dumps(summary, default=float)[:1500], flush=True)
    print(f"wrote {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
