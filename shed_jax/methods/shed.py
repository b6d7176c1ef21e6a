"""SHED (docs/design.md §3-§7): the hierarchical DDPG teacher plus a diffusion synthesiser.

``make_shed`` composes ``shed_jax.methods.hierarchical.HierarchicalTeacher`` (the DDPG teacher, as
h-MDP) with ``shed_jax.teacher.synthesiser.DiffusionSynthesiser`` (diffusion model, synthetic buffer,
mixed updates). :class:`SHEDConfig` is h-MDP's settings plus the synthesiser's; :class:`SHEDHyperparams`
adds the dynamic real-data ratio psi.
"""
from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

from flax import struct

from shed_jax.configs import coerce
from shed_jax.methods.hierarchical import (
    HierarchicalTeacher,
    TeacherConfig,
    TeacherHyperparams,
    teacher_dims,
)
from shed_jax.teacher.diffusion import DiffusionConfig, Sampler, SynAction, SynReward, make_diffusion
from shed_jax.teacher.synthesiser import DiffusionSynthesiser


@dataclasses.dataclass(frozen=True)
class SHEDConfig(TeacherConfig):
    """SHED's settings: the teacher's (``TeacherConfig``) with B_real of 2,048, and the synthesiser's [official code]."""

    real_capacity: int = 2048
    psi: float = 0.75  # default of SHEDHyperparams.psi
    syn_capacity: int = 900
    diffusion_threshold: int = 64  # train D once |B_real| > this
    diffusion_steps: int = 250
    num_syn: int = 10
    syn_threshold: int = 500  # mixed updates once |B_syn| > this
    syn_action: SynAction = "uniform"
    syn_reward: SynReward = "recompute"
    sampler: Sampler = "ancestral"
    diffusion_lr: float = 1e-3
    diffusion_ema: float = 0.0

    POSITIVE: ClassVar[tuple] = TeacherConfig.POSITIVE + ("syn_capacity", "diffusion_steps", "num_syn")

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.psi <= 1.0:
            raise ValueError(f"SHEDConfig.psi must lie in [0, 1], got {self.psi}")


@struct.dataclass
class SHEDHyperparams(TeacherHyperparams):
    """The teacher's hyperparameters plus psi, the real-data ratio of a mixed DDPG batch.

    psi is implemented as a *fixed split with a dynamic ratio*: each mixed update draws ``ddpg_batch``
    candidates from each buffer and keeps the first floor(psi * ddpg_batch) real ones and synthetic
    ones after them (a mask over a static batch, ``buffers.sample_mixed``), z-scoring the rewards of
    both parts separately. This is the official code's layout (24 real + 8 synthetic for psi = 0.75,
    batch 32) for every psi, with no extra noise in the part sizes; a per-sample Bernoulli(psi) mask
    would make the part sizes binomial (and occasionally empty) and so change what the per-part
    reward z-scoring does.
    """

    psi: Any = 0.75

    RANGES: ClassVar[dict] = {**TeacherHyperparams.RANGES, "psi": (0.0, 1.0, True, True)}

    @classmethod
    def from_config(cls, config: SHEDConfig) -> "SHEDHyperparams":
        return cls(**dataclasses.asdict(TeacherHyperparams.from_config(config)), psi=float(config.psi))


def diffusion_synthesiser(cfg: SHEDConfig, state_dim: int, action_dim: int) -> DiffusionSynthesiser:
    """SHED's synthesiser (conditional diffusion model + B_syn) for a teacher of these sizes, from ``cfg``."""
    model = make_diffusion(DiffusionConfig(state_dim, action_dim, lr=cfg.diffusion_lr, sampler=cfg.sampler,
                                           train_bc=cfg.syn_action == "bc", ema_decay=cfg.diffusion_ema))
    return DiffusionSynthesiser(model, capacity=cfg.syn_capacity, train_threshold=cfg.diffusion_threshold,
                                train_steps=cfg.diffusion_steps, num_syn=cfg.num_syn, mix_threshold=cfg.syn_threshold,
                                syn_action=cfg.syn_action, syn_reward=cfg.syn_reward)


def make_shed(env, student, config: Any = None, eval_levels=None, name: str = "shed") -> HierarchicalTeacher:
    """SHED: the hierarchical teacher with a diffusion synthesiser. ``config``: None, a dict or a :class:`SHEDConfig`."""
    cfg = coerce(SHEDConfig, config, f"method {name!r}")
    return HierarchicalTeacher(env, student, cfg, name=name, eval_levels=eval_levels,
                               synthesiser=diffusion_synthesiser(cfg, *teacher_dims(env, cfg)), hparams_class=SHEDHyperparams)
