"""Train the walker's PPO student in Gymnasium's Box2D BipedalWalker, for the reverse parity check of
docs/bipedal.md: a policy trained in Box2D, then played in both engines by
``python -m envs.bipedal.parity --policy ... --tag box2d_policy``.

    python -m experiments.bipedal_box2d_ppo --total-steps 5000000 --workers 2 --out runs/box2d_ppo

The student is the project's own ``PPOStudent`` with the bipedal preset (``PPOConfig.for_env("bipedal")``,
``--ppo KEY=VALUE`` to change it): the same networks, normalisers and ``PPOStudent.update``. Only the
rollout differs. ``--workers`` processes each step a slice of the ``num_envs`` Gymnasium envs
(``SyncVectorEnv`` with same-step autoreset, so a finished episode's last observation is
``info["final_obs"]``), and each step's acting and trajectory row are ``PPOStudent.act_step`` and
``record_step``, the two halves of the JAX rollout's step. Writes OUT/policy.msgpack (the format of
``python -m shed_jax ppo``'s) and OUT/summary.json (training curve, device, command, date).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import pathlib
import sys
import time

import numpy as np

GYM_ID = "BipedalWalker-v3"


def _worker(conn, n: int, seed: int) -> None:
    """n Box2D envs in one process. Messages: None -> reset (answers obs); actions [n, 4] -> one step
    (answers obs, reward, terminated, truncated, final_obs, episode_return, episode_length); 'close'."""
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode

    envs = gym.vector.SyncVectorEnv([lambda: gym.make(GYM_ID) for _ in range(n)], autoreset_mode=AutoresetMode.SAME_STEP)
    ret, length = np.zeros(n), np.zeros(n, np.int64)
    while True:
        msg = conn.recv()
        if isinstance(msg, str):
            envs.close()
            return
        if msg is None:
            obs, _ = envs.reset(seed=seed)
            conn.send(obs.astype(np.float32))
            continue
        obs, reward, term, trunc, info = envs.step(msg)
        done = term | trunc
        ret, length = ret + reward, length + 1
        final_obs = obs.copy()
        if done.any():
            final_obs[done] = np.stack([info["final_obs"][i] for i in np.flatnonzero(done)])
        conn.send((obs.astype(np.float32), reward.astype(np.float32), term, trunc, final_obs.astype(np.float32),
                   np.where(done, ret, 0.0).astype(np.float32), np.where(done, length, 0).astype(np.int32)))
        ret, length = np.where(done, 0.0, ret), np.where(done, 0, length)


class HostEnvs:
    """``num_envs`` Gymnasium envs split over ``workers`` processes (started before any JAX work)."""

    def __init__(self, num_envs: int, workers: int, seed: int):
        if num_envs % workers:
            raise SystemExit(f"--workers {workers} must divide num_envs ({num_envs})")
        ctx = mp.get_context("spawn")
        self.conns, self.procs = [], []
        for w in range(workers):
            a, b = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(b, num_envs // workers, seed + 100_003 * w), daemon=True)
            proc.start()
            self.conns.append(a)
            self.procs.append(proc)

    def reset(self) -> np.ndarray:
        for c in self.conns:
            c.send(None)
        return np.concatenate([c.recv() for c in self.conns])

    def step(self, actions: np.ndarray):
        for c, a in zip(self.conns, np.split(actions, len(self.conns))):
            c.send(a)
        parts = [c.recv() for c in self.conns]
        return tuple(np.concatenate(x) for x in zip(*parts))

    def close(self) -> None:
        for c in self.conns:
            c.send("close")
        for p in self.procs:
            p.join(timeout=10)


def train_one(student, envs: HostEnvs, key, num_updates: int, progress=print):
    """PPO in the host envs: ``num_updates`` rollouts of ``num_steps`` x ``num_envs`` and their updates.
    Returns (final StudentState, curve: [(env steps, mean return of the episodes ended in the rollout)])."""
    import jax
    import jax.numpy as jnp

    cfg = student.config

    @jax.jit
    def act(params, obs_norm, k, obs):
        """act_step plus the action the env receives (clipped to the action box)."""
        obs_norm, acted = student.act_step(params, obs_norm, k, obs)
        return obs_norm, acted, student._env_action(acted[1])

    record = jax.jit(student.record_step)
    update = jax.jit(student.update)
    k_init, key = jax.random.split(key)
    state = student.init(k_init)
    obs = jnp.asarray(envs.reset())
    curve, t0, steps = [], time.time(), 0
    for u in range(num_updates):
        obs_norm, ret_norm, rows = state.obs_norm, state.ret_norm, []
        for k in jax.random.split(jax.random.fold_in(key, 2 * u), cfg.num_steps):
            obs_norm, acted, env_action = act(state.params, obs_norm, k, obs)
            obs2, reward, term, trunc, final_obs, ep_ret, ep_len = envs.step(np.asarray(env_action))
            info = {"final_obs": final_obs, "terminated": term, "truncated": trunc, "episode_return": ep_ret,
                    "episode_length": ep_len}
            ret_norm, row = record(state.params, state.hparams, obs_norm, ret_norm, acted, reward, term | trunc, info)
            rows.append(row)
            obs = jnp.asarray(obs2)
        traj = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *rows)
        state = state.replace(obs_norm=obs_norm, ret_norm=ret_norm)
        state, metrics = update(state, jax.random.fold_in(key, 2 * u + 1), traj)
        steps += cfg.num_envs * cfg.num_steps
        r = float(metrics["episode_return"])
        curve.append((steps, r))
        progress(f"update {u + 1}/{num_updates}  env steps {steps:,}  episode return {r:8.1f}  "
                 f"{steps / (time.time() - t0):,.0f} steps/s")
    return state, curve


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--total-steps", type=int, default=5_000_000, help="env steps per seed")
    p.add_argument("--seeds", type=int, default=1, help="seeds, trained one after the other")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2, help="processes stepping the Box2D envs")
    p.add_argument("--ppo", action="append", default=[], metavar="KEY=VALUE", help="a PPOConfig field, as for ppo")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    for name in ("total_steps", "seeds", "workers"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    from shed_jax import configs
    from shed_jax.student.config import PPOConfig, parse_overrides

    try:
        cfg = PPOConfig.for_env("bipedal").with_overrides(parse_overrides(a.ppo))
    except ValueError as e:
        p.error(str(e))
    envs = HostEnvs(cfg.num_envs, a.workers, a.seed)  # processes first, then JAX
    try:
        import jax

        from envs.bipedal import BipedalWalker
        from shed_jax.runtime import provenance
        from shed_jax.student import make_student
        from shed_jax.training import save_policy

        student = make_student(BipedalWalker(), cfg)
        num_updates = max(1, a.total_steps // (cfg.num_envs * cfg.num_steps))
        states, curves = [], []
        for i in range(a.seeds):
            state, curve = train_one(student, envs, jax.random.fold_in(jax.random.PRNGKey(a.seed), i), num_updates,
                                     progress=lambda s, i=i: print(f"[box2d ppo] seed {i}: {s}", flush=True))
            states.append(state)
            curves.append(curve)
    finally:
        envs.close()
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    save_policy(out / "policy.msgpack", jax.tree_util.tree_map(lambda *x: np.stack(x), *states))
    summary = {**provenance("experiments.bipedal_box2d_ppo", sys.argv[1:] if argv is None else argv),
               "env": GYM_ID, "seeds": a.seeds, "env_steps_per_seed": curves[0][-1][0], "workers": a.workers,
               "ppo": configs.to_dict(cfg),
               "final_episode_return_per_seed": [c[-1][1] for c in curves],
               "curve": [[int(s), r] for s, r in curves[0]]}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(f"[box2d ppo] policy in {out / 'policy.msgpack'}; final training returns "
          f"{', '.join(f'{c[-1][1]:.1f}' for c in curves)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
