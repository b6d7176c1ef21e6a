"""Prioritised level replay buffer (the PLR / ACCEL level sampler) as a pure pytree.

A fixed-capacity buffer of levels, each stored as a parameter vector (``env.param_space`` order)
plus optional per-level extra data (e.g. a walker terrain seed), with a score and the time it was
last sampled. Everything is a pure function of a :class:`LevelBuffer` pytree, so it is jittable,
usable inside ``lax.scan`` and vmappable over seeds.

Replay distribution (Jiang et al., "Prioritized Level Replay"; docs/design.md §8.4):

    P = (1 - rho) * P_S + rho * P_C
    P_S(i) ∝ (1 / rank_i) ** (1 / beta)      rank 1 = highest score among the held levels
    P_C(i) ∝ c - C_i                         staleness: clock now minus clock when last sampled

Buffer rules [ext: JaxUED, DCD]: insert while not full, otherwise replace the minimum-score level
if the new score is strictly higher; a replayed level's score is overwritten with its new score.

The clock ``c`` counts level *samples*: every level handed to a slot (a replay draw or a new level
inserted) advances it by one [our choice; DCD counts per-seed sampling events the same way].

Written by hand rather than taken from JaxUED because that sampler keeps its state in a dict and
stores whole level pytrees; here a level is a float vector plus an optional extra pytree, which the
parameter-space mutations and the dedup check work on directly.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Literal

import jax
import jax.numpy as jnp
from flax import struct

from shed_jax.configs import check_modes


@struct.dataclass
class LevelBuffer:
    """The sampler state.

    levels:        [capacity, d] float32 parameter vectors (rows >= size are unused).
    extra:         pytree of [capacity, ...] arrays (per-level data other than the vector), or {}.
    scores:        [capacity] float32 scores (PVL / MaxMC; larger = more useful to replay).
    timestamps:    [capacity] int32 clock value when the level was last sampled or inserted.
    size:          int32 number of filled rows (rows 0..size-1 are valid).
    episode_count: int32 clock c: number of level samples so far.
    """

    levels: jax.Array
    extra: Any
    scores: jax.Array
    timestamps: jax.Array
    size: jax.Array
    episode_count: jax.Array


@dataclasses.dataclass(frozen=True)
class LevelSamplerConfig:
    """Static level-sampler settings (defaults: docs/design.md §8.4, DCD bipedal)."""

    capacity: int = 1000
    replay_prob: float = 0.5  # p_replay: PLR⊥ 0.5, ACCEL 0.9 [DCD]
    staleness_coef: float = 0.5  # rho
    temperature: float = 0.1  # beta of the rank prioritisation
    min_fill: float = 0.5  # replay only once size >= min_fill * capacity
    schedule: Literal["fixed", "proportionate"] = "fixed"  # "fixed": p_replay; "proportionate": min(fill, p_replay) [DCD]
    duplicate_check: bool = False  # refuse to store a second copy of a held level

    def __post_init__(self):
        if not isinstance(self.capacity, int) or self.capacity < 1:
            raise ValueError(f"LevelSamplerConfig.capacity must be a positive int, got {self.capacity!r}")
        for name in ("replay_prob", "staleness_coef", "min_fill"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"LevelSamplerConfig.{name} must lie in [0, 1], got {v!r}")
        if not self.temperature > 0.0:
            raise ValueError(f"LevelSamplerConfig.temperature must be > 0, got {self.temperature!r}")
        check_modes(self)


@dataclasses.dataclass(frozen=True)
class LevelSampler:
    """Pure functions over a :class:`LevelBuffer` for one static configuration."""

    config: LevelSamplerConfig = LevelSamplerConfig()

    # ---------------------------------------------------------------- construction
    def init(self, level_dim: int, extra_template: Any = None) -> LevelBuffer:
        """An empty buffer for levels of ``level_dim`` parameters.

        ``extra_template`` is one level's extra data (a pytree of arrays, e.g. ``jnp.uint32(0)``
        for a terrain seed); it is tiled to ``capacity`` rows. ``None`` means no extra data.
        """
        cap = self.config.capacity
        extra = {} if extra_template is None else jax.tree_util.tree_map(
            lambda x: jnp.zeros((cap,) + jnp.shape(x), jnp.asarray(x).dtype), extra_template
        )
        return LevelBuffer(
            levels=jnp.zeros((cap, level_dim), jnp.float32),
            extra=extra,
            scores=jnp.zeros((cap,), jnp.float32),
            timestamps=jnp.zeros((cap,), jnp.int32),
            size=jnp.int32(0),
            episode_count=jnp.int32(0),
        )

    # ---------------------------------------------------------------- probabilities
    def filled_mask(self, buf: LevelBuffer) -> jax.Array:
        return jnp.arange(self.config.capacity) < buf.size

    def score_weights(self, buf: LevelBuffer) -> jax.Array:
        """P_S: rank prioritisation over the held levels, (1/rank)^(1/beta), normalised.

        Ties are broken by buffer index (lower index ranks higher). Computed in log space so that
        small temperatures (beta = 0.1 gives rank^-10) do not underflow before normalising.
        """
        filled = self.filled_mask(buf)
        masked = jnp.where(filled, buf.scores, -jnp.inf)
        order = jnp.argsort(-masked, stable=True)  # descending; unfilled (-inf) go last
        ranks = jnp.zeros_like(order).at[order].set(jnp.arange(1, order.shape[0] + 1))
        logits = -jnp.log(ranks.astype(jnp.float32)) / self.config.temperature
        logits = jnp.where(filled, logits, -jnp.inf)
        w = jax.nn.softmax(logits)
        return jnp.where(buf.size > 0, w, 0.0)

    def staleness_weights(self, buf: LevelBuffer) -> jax.Array:
        """P_C ∝ c - C_i over the held levels; uniform over them when every staleness is 0."""
        filled = self.filled_mask(buf)
        stale = jnp.where(filled, (buf.episode_count - buf.timestamps).astype(jnp.float32), 0.0)
        total = stale.sum()
        uniform = filled.astype(jnp.float32) / jnp.maximum(buf.size, 1).astype(jnp.float32)
        return jnp.where(total > 0, stale / jnp.where(total > 0, total, 1.0), uniform)

    def replay_weights(self, buf: LevelBuffer) -> jax.Array:
        """The replay distribution P = (1 - rho) P_S + rho P_C ([capacity], zero on empty rows)."""
        rho = self.config.staleness_coef
        return (1.0 - rho) * self.score_weights(buf) + rho * self.staleness_weights(buf)

    # ---------------------------------------------------------------- sampling
    def replay_probability(self, buf: LevelBuffer) -> jax.Array:
        """Probability of replaying now: 0 below the minimum fill, else the schedule's p."""
        fill = buf.size.astype(jnp.float32) / self.config.capacity
        p = jnp.float32(self.config.replay_prob)
        if self.config.schedule == "proportionate":
            p = jnp.minimum(fill, p)
        enough = buf.size >= jnp.ceil(self.config.min_fill * self.config.capacity).astype(jnp.int32)
        return jnp.where(enough & (buf.size > 0), p, 0.0)

    def sample_replay_decision(self, buf: LevelBuffer, key: jax.Array) -> jax.Array:
        """Bernoulli(replay_probability): True = replay from the buffer, False = new levels."""
        return jax.random.uniform(key) < self.replay_probability(buf)

    def sample(self, buf: LevelBuffer, key: jax.Array, num: int):
        """Draw ``num`` buffer indices i.i.d. from the replay distribution (with replacement).

        Returns ``(buf, idx, levels, extra)``; the clock advances by ``num`` and the sampled levels'
        timestamps are set to the new clock (they become the least stale).
        """
        idx, levels, extra = self.draw(buf, key, num)
        count = buf.episode_count + num
        buf = buf.replace(episode_count=count, timestamps=buf.timestamps.at[idx].set(count))
        return buf, idx, levels, extra

    def draw(self, buf: LevelBuffer, key: jax.Array, num: int):
        """``num`` indices from the replay distribution, as ``sample`` draws them, without counting
        them as sampled: ``(idx, levels, extra)``. ``mark_sampled`` counts the ones used."""
        w = self.replay_weights(buf)
        idx = jax.random.choice(key, self.config.capacity, (num,), replace=True, p=w)
        return idx, buf.levels[idx], jax.tree_util.tree_map(lambda x: x[idx], buf.extra)

    def mark_sampled(self, buf: LevelBuffer, idx: jax.Array, replayed: jax.Array, handed: jax.Array) -> LevelBuffer:
        """Count the levels handed to slots: the clock advances by ``handed.sum()`` (replays and new
        levels alike) and the replayed rows ``idx[replayed]`` take the new clock as their timestamp."""
        count = buf.episode_count + jnp.sum(handed).astype(jnp.int32)
        hit = jnp.zeros((self.config.capacity,), bool).at[idx].max(replayed & handed)
        return buf.replace(episode_count=count, timestamps=jnp.where(hit, count, buf.timestamps))

    # ---------------------------------------------------------------- scores
    def update_scores(self, buf: LevelBuffer, idx: jax.Array, scores: jax.Array, mask=None) -> LevelBuffer:
        """Overwrite the scores of replayed levels ``idx`` [n] with ``scores`` [n] [DCD] (only where
        ``mask`` [n] is True, if given).

        When one level was replayed in several slots, its new score is the mean of their scores
        (a well-defined answer instead of an arbitrary winner of a scatter).
        """
        idx = jnp.asarray(idx, jnp.int32)
        cap = self.config.capacity
        scores = jnp.asarray(scores, jnp.float32)
        ones = jnp.ones_like(scores)
        if mask is not None:
            scores, ones = jnp.where(mask, scores, 0.0), jnp.where(mask, ones, 0.0)
        total = jnp.zeros((cap,), jnp.float32).at[idx].add(scores)
        count = jnp.zeros((cap,), jnp.float32).at[idx].add(ones)
        new = jnp.where(count > 0, total / jnp.maximum(count, 1.0), buf.scores)
        return buf.replace(scores=new)

    # ---------------------------------------------------------------- insertion
    def find(self, buf: LevelBuffer, level: jax.Array, extra: Any = None) -> jax.Array:
        """Index of a held level equal to ``level`` (vector and extra data), or -1."""
        same = jnp.all(buf.levels == level[None, :], axis=-1)
        if extra is not None:
            for held, x in zip(jax.tree_util.tree_leaves(buf.extra), jax.tree_util.tree_leaves(extra)):
                eq = held == jnp.asarray(x)[None]
                same &= jnp.all(eq.reshape(eq.shape[0], -1), axis=-1)
        same &= self.filled_mask(buf)
        return jnp.where(jnp.any(same), jnp.argmax(same), -1).astype(jnp.int32)

    def insert(self, buf: LevelBuffer, level: jax.Array, score: jax.Array, extra: Any = None):
        """Insert one level; returns ``(buf, index)`` with index -1 when it was not stored.

        Not full: append. Full: replace the minimum-score level if ``score`` is strictly higher.
        With ``duplicate_check`` a level already held is not stored again; the held copy's score
        is refreshed with the new one instead (its index is returned) [ext: JaxUED].
        """
        cap = self.config.capacity
        level = jnp.asarray(level, jnp.float32)
        score = jnp.asarray(score, jnp.float32)
        masked = jnp.where(self.filled_mask(buf), buf.scores, jnp.inf)
        min_idx = jnp.argmin(masked).astype(jnp.int32)
        full = buf.size >= cap
        target = jnp.where(full, min_idx, jnp.minimum(buf.size, cap - 1)).astype(jnp.int32)
        accept = jnp.logical_or(~full, score > buf.scores[min_idx])
        if self.config.duplicate_check:
            dup = self.find(buf, level, extra)
            is_dup = dup >= 0
        else:
            dup, is_dup = jnp.int32(-1), jnp.bool_(False)
        store = accept & ~is_dup

        def put(arr, value):
            return jnp.where(store, arr.at[target].set(value), arr)

        new_extra = buf.extra
        if extra is not None:
            new_extra = jax.tree_util.tree_map(lambda a, v: put(a, jnp.asarray(v, a.dtype)), buf.extra, extra)
        scores = put(buf.scores, score)
        scores = jnp.where(is_dup, scores.at[dup].set(score), scores)
        buf = buf.replace(
            levels=put(buf.levels, level),
            extra=new_extra,
            scores=scores,
            timestamps=put(buf.timestamps, buf.episode_count),
            size=jnp.where(store & ~full, buf.size + 1, buf.size).astype(jnp.int32),
        )
        index = jnp.where(store, target, jnp.where(is_dup, dup, -1)).astype(jnp.int32)
        return buf, index

    def insert_batch(self, buf: LevelBuffer, levels: jax.Array, scores: jax.Array, extra: Any = None, mask=None):
        """Insert ``levels`` [n, d] one after another (a ``lax.scan``); returns ``(buf, indices)``.
        With ``mask`` [n], only the rows where it is True are offered (the others get index -1)."""
        n = len(levels)
        take = jnp.ones((n,), bool) if mask is None else jnp.asarray(mask, bool)

        def body(b, x):
            lv, sc, ex, m = x
            b2, i = self.insert(b, lv, sc, ex if extra is not None else None)
            if mask is None:
                return b2, i
            return jax.tree_util.tree_map(lambda new, old: jnp.where(m, new, old), b2, b), jnp.where(m, i, -1)

        xs = (jnp.asarray(levels, jnp.float32), jnp.asarray(scores, jnp.float32),
              extra if extra is not None else jnp.zeros(n), take)
        return jax.lax.scan(body, buf, xs)

    def advance_clock(self, buf: LevelBuffer, num: int) -> LevelBuffer:
        """Count ``num`` level samples that were not replays (new levels handed to slots)."""
        return buf.replace(episode_count=buf.episode_count + num)
