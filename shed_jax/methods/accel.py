"""ACCEL (PLR⊥ + edits) and ACCEL-NR (the paper's ACCEL without revisiting), docs/design.md §8.5 / §8.6.

**ACCEL** (native mode) [DCD, ext: JaxUED]: PLR⊥ whose new levels come from the EASY generator,
with replay probability 0.9, and after every replay update the replayed levels are edited
(``num_edits`` = 3 edits each, new terrain seed), the children rolled out with the updated policy
*without* a gradient update, scored and offered to the buffer. Parents: all replayed levels
[our choice]; switch ``parents="dcd_easy"`` [DCD]: the 4 replayed levels with the *lowest*
(mean return - value loss), each replicated to fill the slots (DCD: 4 x 4 = 16 slots).
Children's rollouts are gradient-free steps (``env_steps_eval``).

**ACCEL-NR** (block mode) [our choice; the paper leaves it undefined]: no buffer. Start from n EASY
levels; each budget step trains the student C = ``updates_per_step`` PPO updates on the current n
levels (slot j runs level j % n), scores each level by PVL (mean over its slots, from the block's
last rollout), samples n parents with P ∝ 1/rank (``rank_temperature`` 1) and makes the next
batch their children (3 edits each, new seeds). ``p_fresh`` of the slots are redrawn from EASY.
No level is ever trained on twice, and every child is a new level.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from shed_jax.levels import LevelCodec, new_seeds, slot_returns, teacher_space
from shed_jax.methods.base import StepInfo, mean_metrics
from shed_jax.methods.level_sampler import LevelBuffer, LevelSamplerConfig
from shed_jax.methods.mutations import Mutator
from shed_jax.methods.plr import PLR, PLRConfig


@dataclasses.dataclass(frozen=True)
class ACCELConfig(PLRConfig):
    """ACCEL settings: PLR⊥'s plus edits; replay probability 0.9 [DCD]."""

    sampler: LevelSamplerConfig = LevelSamplerConfig(replay_prob=0.9)
    num_edits: int = 3
    new_levels: Literal["easy", "uniform"] = "easy"  # "easy": EASY base levels [DCD]; "uniform": U(Θ)
    parents: Literal["all", "dcd_easy"] = "all"  # "all": every replayed level; "dcd_easy": DCD's 4 lowest (return - value loss)

    def __post_init__(self):
        super().__post_init__()
        if not isinstance(self.num_edits, int) or self.num_edits < 1:
            raise ValueError(f"ACCELConfig.num_edits must be a positive int, got {self.num_edits!r}")
        if self.level_switch == "episode" and self.parents == "dcd_easy":
            raise ValueError("ACCELConfig.parents='dcd_easy' picks parents from one rollout's returns; "
                             "with level_switch='episode' (the default) use parents='all', or set level_switch='rollout'")


@dataclasses.dataclass(frozen=True)
class ACCEL(PLR):
    config: ACCELConfig = ACCELConfig()
    name: str = "accel"

    def __post_init__(self):
        super().__post_init__()
        e = self.student.config.num_envs
        if self.config.parents == "dcd_easy" and e % DCD_NUM_PARENTS:
            raise ValueError(f"ACCEL parents='dcd_easy' needs num_envs ({e}) divisible by {DCD_NUM_PARENTS}")
        object.__setattr__(self, "mutator", Mutator.for_env(self.env, self.codec.space, self.config.num_edits))

    def new_levels(self, key: jax.Array, n: int):
        if self.config.new_levels == "uniform":
            return self.codec.sample_uniform(key, n)
        k_v, k_s = jax.random.split(key)
        return self.mutator.sample_easy(k_v, n), new_seeds(k_s, n)

    def _next_levels(self, key, buf: LevelBuffer, slots=None):
        """Whole episodes: a slot that leaves a replayed level plays that level's child next (an edit
        with a new terrain seed: a new level, no gradient, scored and offered to the buffer); the
        other slots draw as PLR⊥ does (replay, else an EASY level)."""
        k_plr, k_m, k_s = jax.random.split(key, 3)
        idx, vecs, seeds = super()._next_levels(k_plr, buf, slots)
        if slots is None:
            return idx, vecs, seeds
        edit = slots.idx >= 0
        children = self.mutator.mutate_batch(k_m, slots.vecs)
        child_seeds = new_seeds(k_s, idx.shape[0])
        return (jnp.where(edit, -1, idx).astype(jnp.int32), jnp.where(edit[:, None], children, vecs),
                jnp.where(edit, child_seeds, seeds))

    def after_replay(self, key, buf: LevelBuffer, sstate, traj):
        """Edit the levels the student just replayed, score the children without gradients, insert."""
        n = self.student.config.num_envs
        k_m, k_s, k_roll = jax.random.split(key, 3)
        parents = self.codec.space.to_vector(sstate.levels)  # [num_envs, d]: one replayed level per slot
        if self.config.parents == "dcd_easy":
            mean_return, _ = slot_returns(traj, sstate.env_state.episode_return)
            _, targets = self.student.advantages(sstate, traj)
            value_loss = jnp.mean((targets - traj.values) ** 2, axis=0)
            parents = dcd_easy_parents(parents, mean_return, value_loss)
        children = self.mutator.mutate_batch(k_m, parents)
        seeds = new_seeds(k_s, n)
        sstate, scores, _ = self.score_rollout(k_roll, sstate, children, seeds)
        buf = self.sampler.advance_clock(buf, n)
        buf, _ = self.sampler.insert_batch(buf, children, scores, seeds)
        return buf, sstate, jnp.int32(self.student.env_steps_per_update), jnp.int32(n)


DCD_NUM_PARENTS = 4


def dcd_easy_parents(levels: jax.Array, mean_return: jax.Array, value_loss: jax.Array) -> jax.Array:
    """DCD's parent choice: the 4 levels with the lowest (mean return - value loss), in ascending
    order, each repeated to fill ``len(levels)`` rows (``[l0, l0, ..., l1, l1, ...]``)."""
    n = levels.shape[0]
    order = jnp.argsort(mean_return - value_loss, stable=True)[:DCD_NUM_PARENTS]
    return jnp.repeat(levels[order], n // DCD_NUM_PARENTS, axis=0)


# --------------------------------------------------------------------------------------------
# ACCEL-NR
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ACCELNRConfig:
    """ACCEL-NR settings (docs/design.md §8.6): block mode with SHED's n and C."""

    updates_per_step: int = 10  # C in PPO updates
    num_levels: int = 5  # n levels per budget step (lander 5, walker 4)
    num_edits: int = 3
    rank_temperature: float = 1.0  # parents P ∝ (1/rank)^(1/temperature)
    p_fresh: float = 0.0  # fraction of the n slots redrawn from EASY each block
    low: tuple[float, ...] | None = None
    high: tuple[float, ...] | None = None

    def __post_init__(self):
        for name in ("updates_per_step", "num_levels", "num_edits"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"ACCELNRConfig.{name} must be a positive int, got {v!r}")
        if not self.rank_temperature > 0:
            raise ValueError(f"ACCELNRConfig.rank_temperature must be > 0, got {self.rank_temperature!r}")
        if not 0.0 <= self.p_fresh <= 1.0:
            raise ValueError(f"ACCELNRConfig.p_fresh must lie in [0, 1], got {self.p_fresh!r}")


@struct.dataclass
class ACCELNRState:
    levels: jax.Array  # [n, d] the levels of the next block
    seeds: jax.Array  # [n] their terrain seeds


def rank_probabilities(scores: jax.Array, temperature: float = 1.0) -> jax.Array:
    """P_i ∝ (1/rank_i)^(1/temperature), rank 1 = highest score (ties by index)."""
    order = jnp.argsort(-scores, stable=True)
    ranks = jnp.zeros_like(order).at[order].set(jnp.arange(1, scores.shape[0] + 1))
    return jax.nn.softmax(-jnp.log(ranks.astype(jnp.float32)) / temperature)


@dataclasses.dataclass(frozen=True)
class ACCELNR:
    """ACCEL without revisiting: n levels per block, children of the best-scored replace them."""

    env: Any
    student: Any
    config: ACCELNRConfig = ACCELNRConfig()
    name: str = "accel-norevisit"

    def __post_init__(self):
        n, e = self.config.num_levels, self.student.config.num_envs
        if e % n:
            raise ValueError(f"ACCEL-NR: the student's num_envs ({e}) must be a multiple of num_levels ({n})")
        codec = LevelCodec(teacher_space(self.env, self.config.low, self.config.high))
        object.__setattr__(self, "codec", codec)
        object.__setattr__(self, "mutator", Mutator.for_env(self.env, codec.space, self.config.num_edits))
        object.__setattr__(self, "num_fresh", int(round(self.config.p_fresh * n)))

    def _easy(self, key, n):
        k_v, k_s = jax.random.split(key)
        return self.mutator.sample_easy(k_v, n), new_seeds(k_s, n)

    def init(self, key: jax.Array) -> ACCELNRState:
        vecs, seeds = self._easy(key, self.config.num_levels)
        return ACCELNRState(levels=vecs, seeds=seeds)

    def begin_episode(self, key: jax.Array, mstate, sstate):
        return self.init(key), sstate

    def level_scores(self, slot_scores: jax.Array) -> jax.Array:
        """Per-level score: mean of its slots' scores (slot j runs level j % n)."""
        n = self.config.num_levels
        return slot_scores.reshape(-1, n).mean(axis=0)

    def step(self, key: jax.Array, mstate: ACCELNRState, sstate):
        student, cfg = self.student, self.config
        n, u = cfg.num_levels, cfg.updates_per_step
        k_assign, k_train, k_parent, k_mut, k_seed, k_fresh = jax.random.split(key, 6)
        sstate = student.assign_levels(sstate, k_assign, self.codec.to_params(mstate.levels, mstate.seeds))

        def one_update(s, k):
            k_r, k_u = jax.random.split(k)
            s, traj = student.rollout(s, k_r)
            pvl = student.level_scores(s, traj)["pvl"]
            s, metrics = student.update(s, k_u, traj)
            return s, (metrics, pvl)

        sstate, (metrics, pvl) = jax.lax.scan(one_update, sstate, jax.random.split(k_train, u))
        scores = self.level_scores(pvl[-1])
        probs = rank_probabilities(scores, cfg.rank_temperature)
        parents = jax.random.choice(k_parent, n, (n,), replace=True, p=probs)
        children = self.mutator.mutate_batch(k_mut, mstate.levels[parents])
        seeds = new_seeds(k_seed, n)
        if self.num_fresh:
            fresh, fresh_seeds = self._easy(k_fresh, self.num_fresh)
            children = children.at[n - self.num_fresh :].set(fresh)
            seeds = seeds.at[n - self.num_fresh :].set(fresh_seeds)
        info = StepInfo(
            levels=mstate.levels,
            env_steps_train=jnp.int32(u * student.env_steps_per_update),
            env_steps_eval=jnp.int32(0),
            teacher_reward=jnp.float32(jnp.nan),
            num_new_levels=jnp.int32(n),
            extras={"ppo": mean_metrics(metrics), "level_scores": scores, "parents": parents},
        )
        return ACCELNRState(levels=children, seeds=seeds), sstate, info
