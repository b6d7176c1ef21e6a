"""GPU learning benchmark of the PPO student (run by the lead on one H200).

    OUT=runs/bench_ppo python -m experiments.bench_ppo            # everything, defaults below
    python -m experiments.bench_ppo --sections lander --total-steps 3000000 --seeds 8 --out DIR

Sections (each is independent; a failure is recorded in results.json and the next one runs):
  lander / lander-continuous  8 vmapped seeds to 3M env steps (SPEC 6.1 preset). Records the
                              learning curve (training episode returns), the first env step at
                              which the median over seeds reaches 200 (SPEC 6.1 acceptance), the
                              final evaluation return per seed (stochastic and deterministic
                              policy), compile time, env steps/s and wall time.
  walker                      4 vmapped seeds on a flat level (`--walker-level`, default
                              "BipedalWalker") up to `--walker-steps`.
  brax                        Brax's own PPO (brax.training.agents.ppo.train) on the continuous
                              lander through a thin adapter to brax's Env interface, with the
                              same network sizes and PPO settings, `--brax-seeds` runs one after
                              another; reports env steps/s and the final evaluation return, and
                              their ratios to ours at equal env steps. Brax's PPO has only
                              continuous (tanh-Gaussian) policies, hence lander-continuous.
Any registered env works for the first kind of section (e.g. --sections cartpole). One device
command may run at most 10 minutes, so run the sections as separate commands, e.g.
    python -m experiments.bench_ppo --sections lander --out $OUT/lander
Writes OUT/results.json and OUT/<section>_curve.png.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import pathlib
import time
import traceback

import jax
import jax.numpy as jnp
import numpy as np

TARGET = 200.0


def first_crossing(x, y, target):
    """First x at which y >= target (None if never)."""
    idx = np.flatnonzero(np.asarray(y) >= target)
    return None if idx.size == 0 else int(x[idx[0]])


def bench_student(env_name, total_steps, seeds, out, level_name=None, chunks=20, eval_episodes=16, seed=0):
    import envs
    from shed_jax import reporting
    from shed_jax.cli.ppo import resolve_level, smoothed, train_seeds
    from shed_jax.student import PPOConfig, PPOHyperparams, make_student

    env = envs.make(env_name)
    config = PPOConfig.for_env(env_name) if env_name in ("lander", "lander-continuous", "walker", "cartpole") else PPOConfig()
    student = make_student(env, config)
    level = resolve_level(env, level_name)
    keys = jax.random.split(jax.random.PRNGKey(seed), seeds)
    hps = PPOHyperparams.stack([config.hparams] * seeds)
    num_updates = -(-total_steps // student.env_steps_per_update)
    t0 = time.perf_counter()
    states, metrics, timing = train_seeds(student, keys, hps, level, num_updates, chunks, progress=True)
    train_wall = time.perf_counter() - t0

    levels = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], level)
    final = {}
    for det in (False, True):
        ev = jax.jit(jax.vmap(lambda s, k: student.evaluate(s, k, levels, eval_episodes, None, det)))
        final["deterministic" if det else "stochastic"] = np.asarray(ev(states, jax.vmap(lambda k: jax.random.fold_in(k, 7))(keys)))[:, 0]
    x = (np.arange(timing["updates"]) + 1) * student.env_steps_per_update
    curve = smoothed(metrics["episode_return"], 10)  # [seeds, updates]
    median = np.nanmedian(curve, axis=0)
    reporting.plot_curves({env_name: (x, curve)}, out / f"{env_name}_curve.png", xlabel="env steps per seed",
                          ylabel="training episode return (10-update avg)",
                          title=f"PPO student on {env_name}{' / ' + level_name if level_name else ''}: {seeds} seeds",
                          references={str(TARGET): TARGET})
    stride = max(1, len(x) // 300)
    return {
        "env": env_name, "level": level_name, "seeds": seeds,
        "env_steps_per_seed": timing["env_steps_per_seed"],
        "compile_s": timing["compile_s"], "train_s": timing["train_s"], "wall_s": train_wall,
        "env_steps_per_s": timing["env_steps_per_s"],
        "median_reaches_200_at": first_crossing(x, median, TARGET),
        "seeds_reaching_200_within_1e6": int(sum(first_crossing(x, c, TARGET) is not None and first_crossing(x, c, TARGET) <= 1_000_000 for c in curve)),
        "final_eval_stochastic": final["stochastic"].mean(1).tolist(),
        "final_eval_deterministic": final["deterministic"].mean(1).tolist(),
        "final_eval_median_stochastic": float(np.median(final["stochastic"].mean(1))),
        "final_train_return": np.nanmean(curve[:, -10:], axis=1).tolist(),
        "curve_env_steps": x[::stride].tolist(),
        "curve_median": median[::stride].tolist(),
        "curve_mean": np.nanmean(curve, axis=0)[::stride].tolist(),
    }


# --------------------------------------------------------------------------------------------
# Brax PPO through an adapter
# --------------------------------------------------------------------------------------------


def _brax_compat():
    """brax 0.14.2's PPO calls jax.device_put_replicated, which jax 0.11 removed (SPEC 7)."""
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


def bench_brax(env_name, total_steps, seeds, ours):
    import envs
    from brax.envs.wrappers.training import VmapWrapper
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as ppo
    from shed_jax.student import PPOConfig

    _brax_compat()
    env = envs.make(env_name)
    cfg = PPOConfig.for_env(env_name)
    hp = cfg.hparams
    adapter = make_brax_adapter(env, env.default_params)
    max_steps = int(env.default_params.max_steps)
    results = []
    for seed in range(seeds):
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
            progress_fn=lambda step, m: evals.append((int(step), float(m.get("eval/episode_reward", np.nan)), time.perf_counter())),
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
    p.add_argument("--brax-seeds", type=int, default=3)
    p.add_argument("--brax-env", default="lander-continuous", help="a registered env with a Box action space")
    p.add_argument("--chunks", type=int, default=20)
    p.add_argument("--out", default=os.environ.get("OUT", "runs/bench_ppo"))
    args = p.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"device": str(jax.devices()[0]), "jax": jax.__version__, "sections": {}}

    def save():
        (out / "results.json").write_text(json.dumps(results, indent=2, default=float))

    for section in args.sections:
        t0 = time.perf_counter()
        try:
            if section == "walker":
                r = bench_student("walker", args.walker_steps, args.walker_seeds, out, args.walker_level, args.chunks)
            elif section == "brax":
                r = bench_brax(args.brax_env, args.total_steps, args.brax_seeds, results["sections"].get(args.brax_env))
            else:
                r = bench_student(section, args.total_steps, args.seeds, out, None, args.chunks)
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
