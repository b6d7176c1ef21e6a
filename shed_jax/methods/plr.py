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

**Whole episodes** (``level_switch="episode"``): a slot keeps its level until its episode ends,
then takes the level drawn for it before the rollout (``student.rollout``'s ``next_levels``): with
the replay probability a buffer level (rank + staleness), else a new one. A level's score
accumulates over every step it is played in a slot, across rollouts, and is written when the slot
leaves it: a replayed level's score is overwritten, a new level is offered to the buffer (if the
buffer replaced a replayed level meanwhile, its score is offered as a new level). The robust rule
holds per transition: the PPO update sees only the steps played on replayed levels (a mask), and
no update runs in a rollout without one. The per-step scores come from each rollout's GAE, which
bootstraps at the rollout's end, so an episode cut by rollouts scores as its pieces' advantages say
(as in JaxUED's and DCD's per-rollout scoring); the sum over its steps is what carries over.
"""
from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Literal

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
    # "rollout" (DCD, JaxUED): every rollout puts every slot on a new level. "episode": a slot moves to
    # its next level only when its episode ends, and scores accumulate until then (module docstring).
    level_switch: Literal["rollout", "episode"] = "episode"
    # what a run saved before a field existed ran with (experiment_from_dict fills it in)
    SAVED_BEFORE: ClassVar[dict] = {"level_switch": "rollout"}

    def __post_init__(self):
        cls = type(self).__name__
        if not isinstance(self.updates_per_step, int) or self.updates_per_step < 1:
            raise ValueError(f"{cls}.updates_per_step must be a positive int, got {self.updates_per_step!r}")
        check_modes(self)
        if not isinstance(self.sampler, LevelSamplerConfig):
            raise ValueError(f"{cls}.sampler must be a LevelSamplerConfig, got {type(self.sampler).__name__}")


@struct.dataclass
class Slots:
    """Whole-episode mode: the level each slot plays and its score so far ([num_envs] each)."""

    vecs: jax.Array  # [n, d] level vectors
    seeds: jax.Array  # [n] terrain seeds
    idx: jax.Array  # [n] int32 buffer row of a replayed level, -1 for a new one
    total: jax.Array  # [n] sum of per-step scores (PVL: max(A, 0); MaxMC: V(s_t)) while on the level
    count: jax.Array  # [n] steps played on the level
    max_return: jax.Array  # [n] largest value target seen on the level (MaxMC)


def accumulate(slots: Slots, terms, targets, dones):
    """One rollout's per-step score terms [T, n] and value targets [T, n] added to the slots' running sums.

    A slot whose episode ends in the rollout (``moved``) leaves its level at its first done: the
    steps up to it (``old`` [T, n]) complete that level's sums (``ended``: total, count, max target),
    and the steps after it start the next level's (``after``). A slot with no episode end keeps its
    level, and ``after`` holds its sums so far. Returns ``(moved, old, ended, after)``.
    """
    T = dones.shape[0]
    moved = dones.any(axis=0)
    first = jnp.argmax(dones, axis=0)
    old = (jnp.arange(T)[:, None] <= first[None]) | ~moved[None]
    sum_where = lambda x, m: jnp.sum(jnp.where(m, x, 0.0), axis=0)  # noqa: E731
    max_where = lambda x, m: jnp.max(jnp.where(m, x, -jnp.inf), axis=0)  # noqa: E731
    ended = (slots.total + sum_where(terms, old), slots.count + old.sum(axis=0),
             jnp.maximum(slots.max_return, max_where(targets, old)))
    after = (jnp.where(moved, sum_where(terms, ~old), ended[0]),
             jnp.where(moved, (~old).sum(axis=0), ended[1]).astype(jnp.float32),
             jnp.where(moved, max_where(targets, ~old), ended[2]))
    return moved, old, ended, after


@struct.dataclass
class PLRState:
    buffer: LevelBuffer  # level vectors [capacity, d], extra = terrain seeds [capacity] int32
    slots: Any = None  # Slots in whole-episode mode, else None


@dataclasses.dataclass(frozen=True)
class PLR:
    """Robust PLR (PLR⊥): gradient updates only on replayed levels."""

    env: Any
    student: Any
    config: PLRConfig = PLRConfig()
    name: str = "plr"

    def __post_init__(self):
        object.__setattr__(self, "codec", LevelCodec(teacher_space(self.env, self.config.low, self.config.high)))
        if self.config.level_switch == "rollout":
            warn_if_rollouts_cut_episodes(self.name, self.student, self.codec.space,
                                          " So does level_switch=episode, the default.")
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
        buffer = self.sampler.init(self.codec.dim, extra_template=jnp.int32(0))
        if self.config.level_switch == "rollout":
            return PLRState(buffer=buffer)
        n = self.student.config.num_envs
        zeros = jnp.zeros((n,), jnp.float32)
        slots = Slots(vecs=jnp.zeros((n, self.codec.dim), jnp.float32), seeds=jnp.zeros((n,), jnp.int32),
                      idx=jnp.full((n,), -1, jnp.int32), total=zeros, count=zeros, max_return=jnp.full((n,), -jnp.inf, jnp.float32))
        return PLRState(buffer=buffer, slots=slots)  # begin_episode puts the slots on their first levels

    def begin_episode(self, key: jax.Array, mstate: PLRState, sstate):
        k_init, k_lvl, k_assign = jax.random.split(key, 3)
        if self.config.reset_on_episode:
            mstate = self.init(k_init)
        if self.config.level_switch == "episode":  # the fresh student's slots start on drawn levels
            idx, vecs, seeds = self._next_levels(k_lvl, mstate.buffer)
            buf = self.sampler.mark_sampled(mstate.buffer, idx, idx >= 0, jnp.ones_like(idx, bool))
            sstate = self.student.assign_levels(sstate, k_assign, self.codec.to_params(vecs, seeds))
            fresh = self.init(k_init).slots
            mstate = mstate.replace(buffer=buf, slots=fresh.replace(vecs=vecs, seeds=seeds, idx=idx))
        return mstate, sstate

    def _next_levels(self, key, buf: LevelBuffer, slots: Slots | None = None):
        """One candidate level per slot: a buffer level with the replay probability, else a new one.
        Returns ``(idx, vecs, seeds)`` with idx -1 for new levels; nothing is counted yet.
        ``slots`` (the levels the slots play now; None at the start) is for subclasses (ACCEL)."""
        n = self.student.config.num_envs
        k_dec, k_draw, k_new = jax.random.split(key, 3)
        replay = jax.random.uniform(k_dec, (n,)) < self.sampler.replay_probability(buf)
        ridx, rvecs, rseeds = self.sampler.draw(buf, k_draw, n)
        nvecs, nseeds = self.new_levels(k_new, n)
        vecs = jnp.where(replay[:, None], rvecs, nvecs)
        seeds = jnp.where(replay, rseeds, nseeds)
        return jnp.where(replay, ridx, -1).astype(jnp.int32), vecs, seeds

    def _score_terms(self, sstate, traj):
        """Per-step score terms [T, n] and value targets [T, n] of one rollout."""
        adv, targets = self.student.advantages(sstate, traj)
        terms = jnp.maximum(adv, 0.0) if self.config.score == "pvl" else traj.values
        return terms, targets

    def _finish(self, total, count, max_return):
        mean = total / jnp.maximum(count, 1.0)
        return mean if self.config.score == "pvl" else max_return - mean

    def step(self, key: jax.Array, mstate: PLRState, sstate):
        if self.config.level_switch == "episode":
            return self._step_episodes(key, mstate, sstate)
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
        info = self._info(rec, buf, trained=jnp.repeat(rec["trained"], n), replay_fraction=rec["trained"].mean(),
                          mean_score=rec["score"].mean())
        return mstate.replace(buffer=buf), sstate, info

    def _info(self, rec, buf: LevelBuffer, trained, replay_fraction, mean_score) -> StepInfo:
        """The step's StepInfo from the scanned per-rollout records ``rec`` and the final buffer."""
        return StepInfo(
            levels=rec["levels"].reshape(-1, rec["levels"].shape[-1]),
            env_steps_train=rec["env_steps_train"].sum(),
            env_steps_eval=rec["env_steps_eval"].sum(),
            teacher_reward=jnp.float32(jnp.nan),
            num_new_levels=rec["num_new"].sum(),
            extras={
                "ppo": mean_metrics(rec["ppo"]),
                "levels_trained_mask": trained,
                "replay_fraction": replay_fraction,
                "mean_score": mean_score,
                "buffer_size": buf.size,
                "buffer_mean_score": jnp.sum(jnp.where(self.sampler.filled_mask(buf), buf.scores, 0.0))
                / jnp.maximum(buf.size, 1),
            },
        )

    def _step_episodes(self, key: jax.Array, mstate: PLRState, sstate):
        """Whole-episode mode (module docstring): ``updates_per_step`` rollouts with per-slot switching."""
        student, n = self.student, self.student.config.num_envs
        T = student.config.num_steps
        k_shape, k_scan = jax.random.split(key)
        placeholder = nan_like(update_metrics_shape(student, sstate, k_shape))

        def one_rollout(carry, k):
            buf, slots, s = carry
            k_lvl, k_roll, k_upd = jax.random.split(k, 3)
            cidx, cvecs, cseeds = self._next_levels(k_lvl, buf, slots)
            s, traj = student.rollout(s, k_roll, next_levels=self.codec.to_params(cvecs, cseeds))
            terms, targets = self._score_terms(s, traj)
            moved, old, ended, after = accumulate(slots, terms, targets, traj.dones)
            score = self._finish(*ended)
            # the slots that left a level: a replayed level still held at its row gets its new score,
            # any other is offered to the buffer as a new level
            held = (slots.idx >= 0) & jnp.all(buf.levels[jnp.maximum(slots.idx, 0)] == slots.vecs, axis=-1) \
                & (buf.extra[jnp.maximum(slots.idx, 0)] == slots.seeds)
            buf = self.sampler.update_scores(buf, jnp.maximum(slots.idx, 0), score, mask=moved & held)
            buf, _ = self.sampler.insert_batch(buf, slots.vecs, score, slots.seeds, mask=moved & ~held)
            buf = self.sampler.mark_sampled(buf, cidx, cidx >= 0, moved)
            # robust rule: gradients only from steps on replayed levels
            trainable = jnp.where(old, (slots.idx >= 0)[None], (moved & (cidx >= 0))[None])
            s, metrics = jax.lax.cond(trainable.any(), lambda: student.update(s, k_upd, traj, mask=trainable),
                                      lambda: (s, placeholder))
            new = lambda a, b: jnp.where(moved if a.ndim == 1 else moved[:, None], a, b)  # noqa: E731
            slots = Slots(vecs=new(cvecs, slots.vecs), seeds=new(cseeds, slots.seeds), idx=new(cidx, slots.idx),
                          total=after[0], count=after[1], max_return=after[2])
            n_train = trainable.sum().astype(jnp.int32)
            rec = dict(
                levels=cvecs, handed=moved, replayed=moved & (cidx >= 0), ppo=metrics,
                score=jnp.where(moved.any(), jnp.sum(jnp.where(moved, score, 0.0)) / jnp.maximum(moved.sum(), 1), jnp.nan),
                env_steps_train=n_train, env_steps_eval=jnp.int32(T * n) - n_train,
                num_new=(moved & (cidx < 0)).sum().astype(jnp.int32),
            )
            return (buf, slots, s), rec

        u = self.config.updates_per_step
        (buf, slots, sstate), rec = jax.lax.scan(one_rollout, (mstate.buffer, mstate.slots, sstate),
                                                 jax.random.split(k_scan, u))
        # a drawn level enters the records only if a slot took it; trained = a replayed one
        info = self._info(rec, buf, trained=rec["replayed"].reshape(u * n),
                          replay_fraction=rec["replayed"].sum() / jnp.maximum(rec["handed"].sum(), 1),
                          mean_score=jnp.nanmean(rec["score"]))
        return mstate.replace(buffer=buf, slots=slots), sstate, info
