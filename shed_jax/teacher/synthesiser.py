"""SHED's synthesiser (docs/design.md §6, §7): synthetic teacher experience for a DDPG teacher.

A conditional diffusion model D of s' given (s, u), trained on the real buffer B_real, and the
synthetic buffer B_syn it fills. Per budget step, after the real transition is stored:

* ``grow``: once |B_real| > ``train_threshold``, measure D's loss on the step's new real
  transitions (held out: D has not trained on them yet), train D ``train_steps`` steps and add
  ``num_syn`` synthetic transitions to B_syn (``DiffusionModel.synthesize``; with
  ``syn_action='policy'`` their actions come from the teacher's current policy plus N(0,
  ``syn_sigma``²) noise).
* ``updates`` (the mixed-update rule, replacing the teacher's own): once |B_syn| > ``mix_threshold``
  and both buffers hold more than the teacher's threshold, ``num_mixed_updates`` updates on mixed
  batches (floor(psi B) real items, the rest synthetic; ``buffers.sample_mixed``); else
  ``num_real_updates`` real updates once the teacher is ready [official code]. With a finite
  ``loss_bar``, mixing also needs this step's held-out loss below it (the paper's rule: inf).

psi is an argument (a dynamic hyperparameter of the method).
"""
from __future__ import annotations

import dataclasses
import math
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
    syn_action: str = "uniform"  # 'uniform' | 'bc' | 'policy' (DiffusionModel.synthesize)
    syn_sigma: float = 0.1  # 'policy': the noise SD added to the policy's synthetic actions
    syn_reward: str = "recompute"  # 'recompute' | 'copy'
    num_real_updates: int = 3  # per budget step before mixing starts
    num_mixed_updates: int = 2
    loss_bar: float = math.inf  # mixed updates only while the held-out loss is below this
    heldout_draws: int = 16  # noise draws averaged in the held-out loss

    def init(self, key: jax.Array) -> SynthState:
        c = self.model.config
        return SynthState(diffusion=self.model.init(key), syn=buffer_init(make_transition(c.state_dim, c.action_dim), self.capacity))

    def grow(self, key: jax.Array, sst: SynthState, real: RingBuffer, reward_fn: Callable, new: Transition,
             policy: Callable | None = None) -> tuple[SynthState, jax.Array, jax.Array]:
        """Train D and add synthetic transitions once B_real is large enough. ``new``: the step's real
        transitions (one, or a batch with a leading axis), already in ``real``; ``policy(key, s,
        sigma)``: the teacher's actions, for ``syn_action='policy'``. Returns (state, mean D loss,
        D's loss on ``new`` before this training), both NaN while D does not train."""
        k_train, k_syn = jax.random.split(key)
        k_held = jax.random.fold_in(key, 1)  # its own stream: the paper's keys above are unchanged
        batch = jax.tree_util.tree_map(lambda x: x[None], new) if jnp.ndim(new.r) == 0 else new
        action_fn = None if policy is None else (lambda k, s: policy(k, s, self.syn_sigma))

        def run(sst):
            held = self.model.heldout_loss(sst.diffusion, k_held, batch.s, batch.u, batch.s_next, self.heldout_draws)
            d, losses = self.model.train_steps(sst.diffusion, k_train, real, self.train_steps)
            syn = self.model.synthesize(d, k_syn, real, self.num_syn, reward_fn, self.syn_action, self.syn_reward,
                                        action_fn)
            return SynthState(diffusion=d, syn=buffer_add_many(sst.syn, syn)), jnp.mean(losses), held

        def skip(sst):
            return sst, jnp.float32(jnp.nan), jnp.float32(jnp.nan)

        return jax.lax.cond(real.count > self.train_threshold, run, skip, sst)

    def updates(self, key: jax.Array, teacher: DDPGTeacher, st: DDPGState, real: RingBuffer, sst: SynthState,
                psi, heldout=jnp.nan) -> tuple[DDPGState, jax.Array]:
        """The mixed-update rule; ``heldout``: this step's held-out D loss (``grow``), read only with a
        finite ``loss_bar``. Returns (state, branch 0 none / 1 real-only / 2 mixed)."""
        syn = sst.syn

        def mixed(st):
            def one(st, k):
                batch, mask = sample_mixed(real, syn, k, teacher.batch_size, psi)
                return teacher.update(st, batch, mask), None

            return jax.lax.scan(one, st, jax.random.split(key, self.num_mixed_updates))[0]

        ready = teacher.ready(real)
        mix = (syn.count > self.mix_threshold) & ready & (syn.count > teacher.threshold)
        if math.isfinite(self.loss_bar):
            mix = mix & (heldout < self.loss_bar)  # NaN (D not trained yet) never passes
        branch = jnp.where(mix, 2, jnp.where(ready, 1, 0))
        branches = [lambda st: st, lambda st: teacher.real_updates(key, st, real, self.num_real_updates), mixed]
        return jax.lax.switch(branch, branches, st), branch
