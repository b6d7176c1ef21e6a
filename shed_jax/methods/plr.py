"""Robust Prioritized Level Replay (PLR⊥) behind the UED method interface (native mode).

Each PPO iteration of a budget step (a ``lax.scan`` over ``updates_per_step`` iterations) either

* **replays** (probability ``replay_prob`` once the buffer holds ``min_fill`` of its capacity):
  draws one buffer level per slot from the rank+staleness distribution, rolls out, takes a PPO
  update on that rollout and overwrites the replayed levels' scores; or
* **explores**: draws one new level per slot (U(Θ)), rolls out *without* a gradient update
  (the "robust" ⊥ variant [DCD]), scores the levels and offers them to the buffer.

Scores are PVL, mean over the rollout of max(GAE advantage, 0) [DCD], or MaxMC (switch; the max
return is this rollout's largest value target, not a per-level running max) [ext: JaxUED].

The choice is a ``lax.cond``; under ``vmap`` over seeds both branches run (as in JaxUED), which
costs time but keeps the whole step one compiled program.

Budget accounting (``StepInfo``): ``env_steps_train`` counts only replay rollouts (gradient
updates); exploration rollouts are ``env_steps_eval``; ``num_new_levels`` counts new levels;
``levels`` holds every level rolled out this step and ``extras["levels_trained_mask"]`` marks those
trained on.

:class:`PLR` is the base of ACCEL (accel.py), which changes the new-level generator and adds edits
after each replay through the ``new_levels`` and ``after_replay`` hooks.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Literal

import jax
import jax.numpy as jnp
from flax import struct

from shed_jax.configs import check_modes
from shed_jax.levels import LevelCodec, teacher_space
from shed_jax.methods.base import StepInfo, mean_metrics, nan_like, update_metrics_shape, warn_if_rollouts_cut_episodes
from shed_jax.methods.level_sampler import LevelBuffer, LevelSampler, LevelSamplerConfig


@dataclasses.dataclass(frozen=True)
class PLRConfig:
    """PLR⊥ settings; sampler defaults are docs/design.md §8.4 (DCD bipedal, p_replay 0.5)."""

    updates_per_step: int = 10
    sampler: LevelSamplerConfig = LevelSamplerConfig()
    score: Literal["pvl", "maxmc"] = "pvl"
    reset_on_episode: bool = True  # empty the buffer when a fresh student starts a teacher episode
    low: tuple[float, ...] | None = None  # Θ override (default: levels.teacher_space)
    high: tuple[float, ...] | None = None

    def __post_init__(self):
        cls = type(self).__name__
        if not isinstance(self.updates_per_step, int) or self.updates_per_step < 1:
            raise ValueError(f"{cls}.updates_per_step must be a positive int, got {self.updates_per_step!r}")
        check_modes(self)
        if not isinstance(self.sampler, LevelSamplerConfig):
            raise ValueError(f"{cls}.sampler must be a LevelSamplerConfig, got {type(self.sampler).__name__}")


@struct.dataclass
class PLRState:
    buffer: LevelBuffer  # level vectors [capacity, d], extra = terrain seeds [capacity] int32


@dataclasses.dataclass(frozen=True)
class PLR:
    """Robust PLR (PLR⊥): gradient updates only on replayed levels."""

    env: Any
    student: Any
    config: PLRConfig = PLRConfig()
    name: str = "plr"

    def __post_init__(self):
        object.__setattr__(self, "codec", LevelCodec(teacher_space(self.env, self.config.low, self.config.high)))
        warn_if_rollouts_cut_episodes(self.name, self.student, self.codec.space)
        object.__setattr__(self, "sampler", LevelSampler(self.config.sampler))

    # ---------------------------------------------------------------- hooks (ACCEL overrides)
    def new_levels(self, key: jax.Array, n: int):
        """New levels for exploration: U(Θ) -> (vecs [n, d], seeds [n])."""
        return self.codec.sample_uniform(key, n)

    def after_replay(self, key, buf: LevelBuffer, sstate, traj):
        """Called after each replay update with the replay rollout ``traj``; returns
        (buf, sstate, eval_env_steps, num_new_levels)."""
        return buf, sstate, jnp.int32(0), jnp.int32(0)

    # ---------------------------------------------------------------- pieces
    def scores(self, sstate, traj) -> jax.Array:
        """Per-slot replay scores [num_envs] of one rollout (one level per slot)."""
        return self.student.level_scores(sstate, traj)[self.config.score]

    def score_rollout(self, key, sstate, vecs, seeds):
        """Assign the levels, roll out without updating, return (sstate, scores, traj)."""
        k_a, k_r = jax.random.split(key)
        sstate = self.student.assign_levels(sstate, k_a, self.codec.to_params(vecs, seeds))
        sstate, traj = self.student.rollout(sstate, k_r)
        return sstate, self.scores(sstate, traj), traj

    # ---------------------------------------------------------------- interface
    def init(self, key: jax.Array) -> PLRState:
        return PLRState(buffer=self.sampler.init(self.codec.dim, extra_template=jnp.int32(0)))

    def begin_episode(self, key: jax.Array, mstate: PLRState, sstate):
        if self.config.reset_on_episode:
            mstate = self.init(key)
        return mstate, sstate

    def step(self, key: jax.Array, mstate: PLRState, sstate):
        student, n = self.student, self.student.config.num_envs
        per_rollout = student.env_steps_per_update
        k_shape, k_scan = jax.random.split(key)
        placeholder = nan_like(update_metrics_shape(student, sstate, k_shape))

        def replay(buf, s, k):
            k_s, k_roll, k_u, k_after = jax.random.split(k, 4)
            buf, idx, vecs, seeds = self.sampler.sample(buf, k_s, n)
            s, scores, traj = self.score_rollout(k_roll, s, vecs, seeds)
            s, metrics = student.update(s, k_u, traj)
            buf = self.sampler.update_scores(buf, idx, scores)
            buf, s, eval_steps, num_new = self.after_replay(k_after, buf, s, traj)
            rec = dict(
                levels=vecs, trained=jnp.bool_(True), ppo=metrics, score=scores.mean(),
                env_steps_train=jnp.int32(per_rollout), env_steps_eval=eval_steps, num_new=num_new,
            )
            return buf, s, rec

        def explore(buf, s, k):
            k_l, k_roll = jax.random.split(k)
            vecs, seeds = self.new_levels(k_l, n)
            s, scores, _ = self.score_rollout(k_roll, s, vecs, seeds)
            buf = self.sampler.advance_clock(buf, n)
            buf, _ = self.sampler.insert_batch(buf, vecs, scores, seeds)
            rec = dict(
                levels=vecs, trained=jnp.bool_(False), ppo=placeholder, score=scores.mean(),
                env_steps_train=jnp.int32(0), env_steps_eval=jnp.int32(per_rollout), num_new=jnp.int32(n),
            )
            return buf, s, rec

        def one_iteration(carry, k):
            buf, s = carry
            k_dec, k_branch = jax.random.split(k)
            do_replay = self.sampler.sample_replay_decision(buf, k_dec)
            buf, s, rec = jax.lax.cond(do_replay, replay, explore, buf, s, k_branch)
            return (buf, s), rec

        u = self.config.updates_per_step
        (buf, sstate), rec = jax.lax.scan(one_iteration, (mstate.buffer, sstate), jax.random.split(k_scan, u))
        info = StepInfo(
            levels=rec["levels"].reshape(u * n, -1),
            env_steps_train=rec["env_steps_train"].sum(),
            env_steps_eval=rec["env_steps_eval"].sum(),
            teacher_reward=jnp.float32(jnp.nan),
            num_new_levels=rec["num_new"].sum(),
            extras={
                "ppo": mean_metrics(rec["ppo"]),
                "levels_trained_mask": jnp.repeat(rec["trained"], n),
                "replay_fraction": rec["trained"].mean(),
                "mean_score": rec["score"].mean(),
                "buffer_size": buf.size,
                "buffer_mean_score": jnp.sum(jnp.where(self.sampler.filled_mask(buf), buf.scores, 0.0))
                / jnp.maximum(buf.size, 1),
            },
        )
        return mstate.replace(buffer=buf), sstate, info
