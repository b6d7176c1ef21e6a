"""SHED's synthesiser (docs/design.md §6, §7): synthetic teacher experience for a DDPG teacher.

A conditional diffusion model D of s' given (s, u), trained on the real buffer B_real, and the
synthetic buffer B_syn it fills. Per budget step, after the real transition is stored:

* ``grow``: once |B_real| > ``train_threshold``, train D ``train_steps`` steps and add ``num_syn``
  synthetic transitions to B_syn (``DiffusionModel.synthesize``).
* ``updates`` (the mixed-update rule, replacing the teacher's own): once |B_syn| > ``mix_threshold``
  and both buffers hold more than the teacher's threshold, ``num_mixed_updates`` updates on mixed
  batches (floor(psi B) real items, the rest synthetic; ``buffers.sample_mixed``); else
  ``num_real_updates`` real updates once the teacher is ready [official code].

psi is an argument (a dynamic hyperparameter of the method).
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

from shed_jax.teacher.buffers import RingBuffer, buffer_add_many, buffer_init, make_transition, sample_mixed
from shed_jax.teacher.ddpg import DDPGState
from shed_jax.teacher.ddpg_teacher import DDPGTeacher
from shed_jax.teacher.diffusion import DiffusionModel, DiffusionState


@struct.dataclass
class SynthState:
    diffusion: DiffusionState
    syn: RingBuffer  # B_syn


@dataclasses.dataclass(frozen=True)
class DiffusionSynthesiser:
    """Diffusion model + synthetic buffer + the mixed-update rule (defaults: docs/design.md §10.2)."""

    model: DiffusionModel
    capacity: int = 900  # |B_syn|, FIFO
    train_threshold: int = 64  # train D once |B_real| > this
    train_steps: int = 250
    num_syn: int = 10  # synthetic transitions per budget step
    mix_threshold: int = 500  # mixed updates once |B_syn| > this
    syn_action: str = "uniform"  # 'uniform' | 'bc' (DiffusionModel.synthesize)
    syn_reward: str = "recompute"  # 'recompute' | 'copy'
    num_real_updates: int = 3  # per budget step before mixing starts
    num_mixed_updates: int = 2

    def init(self, key: jax.Array) -> SynthState:
        c = self.model.config
        return SynthState(diffusion=self.model.init(key), syn=buffer_init(make_transition(c.state_dim, c.action_dim), self.capacity))

    def grow(self, key: jax.Array, sst: SynthState, real: RingBuffer, reward_fn: Callable) -> tuple[SynthState, jax.Array]:
        """Train D and add synthetic transitions once B_real is large enough. Returns (state, mean D loss or NaN)."""
        k_train, k_syn = jax.random.split(key)

        def run(sst):
            d, losses = self.model.train_steps(sst.diffusion, k_train, real, self.train_steps)
            new = self.model.synthesize(d, k_syn, real, self.num_syn, reward_fn, self.syn_action, self.syn_reward)
            return SynthState(diffusion=d, syn=buffer_add_many(sst.syn, new)), jnp.mean(losses)

        def skip(sst):
            return sst, jnp.float32(jnp.nan)

        return jax.lax.cond(real.count > self.train_threshold, run, skip, sst)

    def updates(self, key: jax.Array, teacher: DDPGTeacher, st: DDPGState, real: RingBuffer, sst: SynthState,
                psi) -> tuple[DDPGState, jax.Array]:
        """The mixed-update rule. Returns (state, branch 0 none / 1 real-only / 2 mixed)."""
        syn = sst.syn

        def mixed(st):
            def one(st, k):
                batch, mask = sample_mixed(real, syn, k, teacher.batch_size, psi)
                return teacher.update(st, batch, mask), None

            return jax.lax.scan(one, st, jax.random.split(key, self.num_mixed_updates))[0]

        ready = teacher.ready(real)
        mix = (syn.count > self.mix_threshold) & ready & (syn.count > teacher.threshold)
        branch = jnp.where(mix, 2, jnp.where(ready, 1, 0))
        branches = [lambda st: st, lambda st: teacher.real_updates(key, st, real, self.num_real_updates), mixed]
        return jax.lax.switch(branch, branches, st), branch
