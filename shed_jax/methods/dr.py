"""Domain randomisation (DR), docs/design.md §8.2.

Each PPO rollout, every slot gets a fresh level drawn from a fixed distribution and the student
trains on all of them. Default distribution: U(Θ), the teacher's box (``shed_jax.levels.teacher_space``;
lander: the docs/design.md §5 box with wind on; walker: U(FULL)). Option ``distribution="code"``: the
environment's reference-code Gaussian DR (``env.ued.code_dr``; the lander's official "hard" DR:
g ~ N(-10, 1), wind on with p 0.5, wind ~ N(15, 1), turb ~ N(1.5, 0.5), each clipped), which lies
mostly outside Θ. Option ``level_switch="episode"``: a slot moves to its fresh level only when its
current episode ends, so episodes longer than a rollout are played to the end (docs/baselines.md,
"Rollout length in native mode").
"""
from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Literal

import jax
import jax.numpy as jnp
import numpy as np

from envs.core import ParamSpace
from shed_jax.configs import check_modes
from shed_jax.levels import LevelCodec, teacher_space, ued
from shed_jax.methods.base import StepInfo, mean_metrics, warn_if_rollouts_cut_episodes


@dataclasses.dataclass(frozen=True)
class DRConfig:
    """DR settings. ``updates_per_step`` PPO updates (num_envs x num_steps steps each) per budget step."""

    updates_per_step: int = 10
    distribution: Literal["uniform", "code"] = "uniform"  # "uniform": U(Θ); "code": the env's reference-code Gaussian DR (env.ued.code_dr)
    low: tuple[float, ...] | None = None  # Θ override (default: levels.teacher_space)
    high: tuple[float, ...] | None = None
    # "rollout" (docs/design.md §8.1, DCD): every rollout resets every slot onto a new level. "episode": a slot
    # moves to a new level only when its episode ends (student.rollout's next_levels), so episodes
    # longer than a rollout run to their end.
    level_switch: Literal["rollout", "episode"] = "episode"
    # what a run saved before a field existed ran with (experiment_from_dict fills it in)
    SAVED_BEFORE: ClassVar[dict] = {"level_switch": "rollout"}

    def __post_init__(self):
        if not isinstance(self.updates_per_step, int) or self.updates_per_step < 1:
            raise ValueError(f"DRConfig.updates_per_step must be a positive int, got {self.updates_per_step!r}")
        check_modes(self)


@dataclasses.dataclass(frozen=True)
class DR:
    """Domain randomisation behind the UED method interface (native mode)."""

    env: Any
    student: Any
    config: DRConfig = DRConfig()
    name: str = "dr"

    def __post_init__(self):
        space = teacher_space(self.env, self.config.low, self.config.high)
        code_dr = ued(self.env).code_dr
        if self.config.distribution == "code":
            if code_dr is None:
                raise ValueError(f"DRConfig.distribution='code' is an environment's reference-code DR (the lander's "
                                 f"official one); {self.env.name!r} has none (env.ued.code_dr)")
            # the code distribution leaves Θ; build params in the wider physically valid box
            lo = np.array([c[2] for c in code_dr], np.float32)
            hi = np.array([c[3] for c in code_dr], np.float32)
            space = ParamSpace(space.names, lo, hi, space.base)
        object.__setattr__(self, "codec", LevelCodec(space))
        object.__setattr__(self, "code_dr", code_dr)
        if self.config.level_switch == "rollout":  # "episode" runs every episode to its end
            warn_if_rollouts_cut_episodes(self.name, self.student, space,
                                          " So does level_switch=episode, the default.")

    def sample_levels(self, key: jax.Array, n: int):
        """``n`` DR levels -> (vectors [n, d], params pytree with leading n)."""
        if self.config.distribution == "uniform":
            vecs, seeds = self.codec.sample_uniform(key, n)
            return vecs, self.codec.to_params(vecs, seeds)
        k_v, k_w = jax.random.split(key)
        mean = jnp.asarray([c[0] for c in self.code_dr])
        std = jnp.asarray([c[1] for c in self.code_dr])
        vecs = mean + std * jax.random.normal(k_v, (n, len(self.code_dr)))
        vecs = jnp.clip(vecs, self.codec.space.low, self.codec.space.high)
        params = self.codec.to_params(vecs)
        wind_on = jax.random.bernoulli(k_w, 0.5, (n,))
        params = params.replace(enable_wind=wind_on.astype(jnp.asarray(params.enable_wind).dtype))
        return vecs, params

    def init(self, key: jax.Array):
        return {}

    def begin_episode(self, key: jax.Array, mstate, sstate):
        if self.config.level_switch == "episode":  # the fresh student's slots start on DR levels
            k_lvl, k_assign = jax.random.split(key)
            sstate = self.student.assign_levels(sstate, k_assign, self.sample_levels(k_lvl, self.student.config.num_envs)[1])
        return mstate, sstate

    def step(self, key: jax.Array, mstate, sstate):
        student = self.student
        n = student.config.num_envs
        per_episode = self.config.level_switch == "episode"

        def one_update(s, k):
            k_lvl, k_assign, k_roll, k_upd = jax.random.split(k, 4)
            vecs, params = self.sample_levels(k_lvl, n)
            if per_episode:  # slot j takes level j when its episode ends (at most once per rollout)
                s, traj = student.rollout(s, k_roll, next_levels=params)
                used = traj.dones.any(axis=0)
            else:
                s = student.assign_levels(s, k_assign, params)
                s, traj = student.rollout(s, k_roll)
                used = jnp.ones((n,), bool)
            s, metrics = student.update(s, k_upd, traj)
            return s, (vecs, used, metrics)

        u = self.config.updates_per_step
        sstate, (vecs, used, metrics) = jax.lax.scan(one_update, sstate, jax.random.split(key, u))
        info = StepInfo(
            levels=vecs.reshape(u * n, -1),
            env_steps_train=jnp.int32(u * student.env_steps_per_update),
            env_steps_eval=jnp.int32(0),
            teacher_reward=jnp.float32(jnp.nan),
            num_new_levels=used.sum().astype(jnp.int32),
            # "episode": levels drawn but not reached (no episode end in that slot) were never played
            extras={"ppo": mean_metrics(metrics), "levels_trained_mask": used.reshape(u * n)},
        )
        return mstate, sstate, info
