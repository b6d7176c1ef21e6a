"""The teacher's reward R(s, a, s') on performance vectors, and per-batch reward normalisation.

Forms (docs/design.md §4), chosen by a frozen :class:`RewardConfig`:

* ``paper_l1`` (default, [paper]):  R = ||s' - s||_1 - eta * cv
* ``signed_sum`` ([our choice]):    R = sum_i (s'_i - s_i) - eta * cv   (does not reward drops)
* ``code_mean`` ([official code]):  R = mean(s') - mean(s) [+ 0.01 * (cv_c(s) - cv_c(s'))]

with omega = s' - s and cv = sample-std(omega) / |mean(omega)|.  The guard replaces mean^2 by
max(mean^2, 1e-6) in the denominator (an unguarded cv is infinite when the student's average change is
exactly zero, e.g. two identical evaluations, and would swamp the L1 term); the result is clipped at
100 so that one near-zero mean change cannot dominate a batch of rewards either.

All functions act on the last axis, so they broadcast over any leading batch axes and are jittable
and vmappable.
"""
from __future__ import annotations

import dataclasses
from typing import Literal, get_args

import jax
import jax.numpy as jnp

from shed_jax.configs import check_modes

RewardForm = Literal["paper_l1", "signed_sum", "code_mean"]
REWARD_FORMS = get_args(RewardForm)


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """Static choice of the teacher reward.

    form:        'paper_l1' | 'signed_sum' | 'code_mean'.
    eta:         fairness weight of cv in the paper forms (0.05 [paper v1]; ablation 10).
    code_cv:     add the official code's optional term c * (cv_c(s) - cv_c(s')) to 'code_mean'.
    code_cv_weight: its weight c (0.01 in the official code).
    cv_guard:    lower bound on mean(omega)^2 in the cv denominator.
    cv_clip:     upper bound on cv.
    """

    form: RewardForm = "paper_l1"
    eta: float = 0.05
    code_cv: bool = False
    code_cv_weight: float = 0.01
    cv_guard: float = 1e-6
    cv_clip: float = 100.0

    def __post_init__(self):
        check_modes(self)
        if not self.eta >= 0:
            raise ValueError(f"RewardConfig.eta must be >= 0, got {self.eta}")
        if not self.cv_guard > 0:
            raise ValueError(f"RewardConfig.cv_guard must be > 0, got {self.cv_guard}")
        if not self.cv_clip > 0:
            raise ValueError(f"RewardConfig.cv_clip must be > 0, got {self.cv_clip}")
        if self.code_cv and self.form != "code_mean":
            raise ValueError("RewardConfig.code_cv only applies to form='code_mean'")


def coefficient_of_variation(s, s_next, guard: float = 1e-6, clip: float = 100.0) -> jax.Array:
    """cv of the per-environment change omega = s' - s (docs/design.md §4.1), guarded and clipped.

    cv = sqrt( sum_i (omega_i - mean)^2 / (m - 1) / max(mean^2, guard) ), clipped to [0, clip].
    Needs m >= 2 evaluation environments (the sample std is undefined for m = 1).
    """
    omega = jnp.asarray(s_next, jnp.float32) - jnp.asarray(s, jnp.float32)
    m = omega.shape[-1]
    if m < 2:
        raise ValueError(f"cv needs at least 2 evaluation environments, got m={m}")
    mean = jnp.mean(omega, axis=-1, keepdims=True)
    var = jnp.sum((omega - mean) ** 2, axis=-1) / (m - 1)
    cv = jnp.sqrt(var / jnp.maximum(mean[..., 0] ** 2, guard))
    return jnp.minimum(cv, clip)


def code_cv(x) -> jax.Array:
    """The official code's cv_c(x) = 100 * population-std(x) / mean(x) of a performance vector.

    Unguarded and signed, as in the code: it flips sign when mean(x) < 0 (documented in docs/design.md §4.3).
    """
    x = jnp.asarray(x, jnp.float32)
    return 100.0 * jnp.std(x, axis=-1) / jnp.mean(x, axis=-1)


def teacher_reward(config: RewardConfig, s, a, s_next) -> jax.Array:
    """R(s, a, s') for performance vectors s, s' (last axis m); the action is unused by every form.

    ``a`` is accepted so that this has the signature synthetic-experience generation expects.
    """
    del a
    s = jnp.asarray(s, jnp.float32)
    s_next = jnp.asarray(s_next, jnp.float32)
    if config.form == "code_mean":
        r = jnp.mean(s_next, axis=-1) - jnp.mean(s, axis=-1)
        if config.code_cv:
            r = r + config.code_cv_weight * (code_cv(s) - code_cv(s_next))
        return r
    cv = coefficient_of_variation(s, s_next, config.cv_guard, config.cv_clip)
    if config.form == "paper_l1":
        gain = jnp.sum(jnp.abs(s_next - s), axis=-1)
    else:  # signed_sum
        gain = jnp.sum(s_next - s, axis=-1)
    return gain - config.eta * cv


def make_reward_fn(config: RewardConfig):
    """``(s, a, s') -> R`` closed over a config (what ``diffusion.synthesize`` takes)."""
    return lambda s, a, s_next: teacher_reward(config, s, a, s_next)


def zscore(r, eps: float = 1e-6) -> jax.Array:
    """(r - mean) / (std + eps) over the last axis (population std, as numpy's default).

    The DDPG teacher z-scores the rewards of every sampled batch [official code]: the raw scale of
    R (hundreds of return points) would otherwise set the critic's learning rate.
    """
    r = jnp.asarray(r, jnp.float32)
    mean = jnp.mean(r, axis=-1, keepdims=True)
    std = jnp.std(r, axis=-1, keepdims=True)
    return (r - mean) / (std + eps)


def _masked_zscore(r, mask, eps: float) -> jax.Array:
    """``zscore`` over the entries of ``r`` [B] where ``mask`` holds, written back there (others: 0)."""
    w = mask.astype(jnp.float32)
    n = jnp.maximum(jnp.sum(w), 1.0)
    mean = jnp.sum(w * r) / n
    std = jnp.sqrt(jnp.sum(w * (r - mean) ** 2) / n)
    return jnp.where(mask, (r - mean) / (std + eps), 0.0)


def zscore_mixed(r, real_mask, eps: float = 1e-6) -> jax.Array:
    """Z-score the real entries (``real_mask``) and the synthetic ones (the rest) of a mixed batch separately.

    ``r`` is one batch of rewards [B] (``vmap`` for more axes); ``real_mask`` a bool per entry, which
    may be traced (the real share psi is a dynamic hyperparameter, ``buffers.sample_mixed``). Either
    part may be empty. An all-true mask gives the per-batch ``zscore`` up to float32 rounding; the
    DDPG update uses it so for real batches. (The sums are over the whole batch: with ``axis=-1,
    keepdims=True`` XLA rounded them differently inside the lander SHED program.)
    """
    r = jnp.asarray(r, jnp.float32)
    real_mask = jnp.asarray(real_mask, bool)
    if r.ndim != 1 or real_mask.shape != r.shape:
        raise ValueError(f"zscore_mixed takes rewards [B] and real_mask [B] (one flag per reward), got shapes "
                         f"{r.shape} and {real_mask.shape}")
    return _masked_zscore(r, real_mask, eps) + _masked_zscore(r, ~real_mask, eps)
