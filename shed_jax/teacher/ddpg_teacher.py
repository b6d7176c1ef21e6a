"""The DDPG teacher of a hierarchical UED method (docs/design.md §3, §5): the part h-MDP and SHED share.

It acts on the teacher state (the student's performance vector s), keeps the real replay buffer
B_real and runs DDPG updates on real batches. The buffer holds raw performance vectors; the DDPG
networks see them multiplied by 1 / ``state_scale`` (the teacher sees s/100, docs/design.md §2).

Its own update rule (h-MDP's): ``num_updates`` real updates per budget step once |B_real| >
``threshold``. A synthesiser (``shed_jax.teacher.synthesiser``) replaces the rule with its own and
calls ``real_updates``/``update`` for the DDPG steps.

Dynamic hyperparameters (exploration std, learning rates) are arguments or live in the DDPG state
(``ddpg.with_learning_rates``); everything here is a pure function of frozen settings.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from shed_jax.teacher.buffers import RingBuffer, Transition, buffer_add, buffer_add_many, buffer_init, buffer_sample, make_transition
from shed_jax.teacher.ddpg import DDPG, DDPGState


@dataclasses.dataclass(frozen=True)
class DDPGTeacher:
    """DDPG over performance vectors with a real replay buffer (build with the method's config)."""

    ddpg: DDPG
    capacity: int  # |B_real|, FIFO
    batch_size: int = 32  # DDPG batch
    threshold: int = 32  # updates once |B_real| > threshold
    num_updates: int = 2  # real updates per budget step (h-MDP) [official code]
    state_scale: float = 100.0  # the networks see s / state_scale

    def __post_init__(self):
        if self.capacity < self.batch_size:
            raise ValueError(f"DDPGTeacher: the real buffer's capacity ({self.capacity}) must be >= the DDPG batch ({self.batch_size})")

    @property
    def state_dim(self) -> int:
        return self.ddpg.config.state_dim

    @property
    def action_dim(self) -> int:
        return self.ddpg.config.action_dim

    def init(self, key: jax.Array) -> tuple[DDPGState, RingBuffer]:
        """Fresh DDPG state and an empty B_real."""
        return self.ddpg.init(key), buffer_init(make_transition(self.state_dim, self.action_dim), self.capacity)

    def act(self, st: DDPGState, s, key: jax.Array, sigma) -> jax.Array:
        """u = clip(mu(s / scale) + N(0, sigma^2), -1, 1) in [-1, 1]^{d_a}; ``sigma`` may be traced."""
        return self.ddpg.act(st, s / self.state_scale, key, sigma)

    def store(self, real: RingBuffer, transition: Transition) -> RingBuffer:
        """B_real with ``transition`` added: one (a scalar ``r``), or a batch with a leading axis, in order."""
        return buffer_add(real, transition) if jnp.ndim(transition.r) == 0 else buffer_add_many(real, transition)

    def ready(self, real: RingBuffer) -> jax.Array:
        """Whether B_real holds enough transitions for DDPG updates."""
        return real.count > self.threshold

    def update(self, st: DDPGState, batch: Transition, real_mask=None) -> DDPGState:
        """One DDPG update on a raw batch (scaled here); ``real_mask`` marks a mixed batch's real items."""
        k = 1.0 / self.state_scale
        return self.ddpg.update(st, batch.replace(s=batch.s * k, s_next=batch.s_next * k), real_mask)[0]

    def td_error(self, st: DDPGState, transition: Transition, r) -> jax.Array:
        """The critic's |TD error| on one raw transition (scaled here), with reward ``r`` as the critic sees it;
        on a batch of them (a leading axis on every field and on ``r``), one per transition."""
        k = 1.0 / self.state_scale
        item = transition.replace(s=transition.s * k, s_next=transition.s_next * k, r=jnp.asarray(r, jnp.float32))
        if jnp.ndim(transition.r) == 1:
            return self.ddpg.td_errors(st, item)
        return self.ddpg.td_errors(st, jax.tree_util.tree_map(lambda x: x[None], item))[0]

    def real_updates(self, key: jax.Array, st: DDPGState, real: RingBuffer, count: int) -> DDPGState:
        """``count`` (static) updates on uniform batches from B_real, keys split from ``key``."""
        def one(st, k):
            return self.update(st, buffer_sample(real, k, self.batch_size)), None

        return jax.lax.scan(one, st, jax.random.split(key, count))[0]

    def updates(self, key: jax.Array, st: DDPGState, real: RingBuffer) -> tuple[DDPGState, jax.Array]:
        """This teacher's own rule: ``num_updates`` real updates once ready. Returns (state, branch 0 none / 1 real)."""
        branch = jnp.where(self.ready(real), 1, 0)
        return jax.lax.switch(branch, [lambda st: st, lambda st: self.real_updates(key, st, real, self.num_updates)], st), branch
