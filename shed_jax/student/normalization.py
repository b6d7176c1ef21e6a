"""Running observation and return normalisation, kept as pytree state (SB3 VecNormalize semantics).

`RunningMeanStd` merges batch moments with the parallel algorithm of Chan et al. (exact for any
split of the data into batches, up to float error). The return normaliser follows SB3/DCD
VecNormalize: per env it accumulates the discounted return ``G <- gamma*G + r``, updates a running
variance of G every step, scales the reward by ``1/sqrt(var + eps)`` (no mean shift), clips, and
zeroes G where the episode ended.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

EPS = 1e-8


@struct.dataclass
class RunningMeanStd:
    mean: jax.Array
    var: jax.Array
    count: jax.Array  # float32 scalar; starts at a tiny epsilon as in SB3

    @classmethod
    def create(cls, shape=(), epsilon: float = 1e-4) -> "RunningMeanStd":
        return cls(jnp.zeros(shape, jnp.float32), jnp.ones(shape, jnp.float32), jnp.asarray(epsilon, jnp.float32))

    def update(self, batch: jax.Array, mask=None) -> "RunningMeanStd":
        """Merge a batch whose leading axis indexes samples (trailing axes match `mean`); with ``mask``
        (bool, leading axis) only its True samples (none: the statistics are unchanged)."""
        batch = jnp.asarray(batch, jnp.float32)
        if mask is None:
            b_mean = jnp.mean(batch, axis=0)
            b_var = jnp.var(batch, axis=0)
            b_count = jnp.asarray(batch.shape[0], jnp.float32)
        else:
            w = jnp.asarray(mask, jnp.float32).reshape(mask.shape + (1,) * (batch.ndim - 1))
            b_count = jnp.sum(w[(slice(None),) + (0,) * (batch.ndim - 1)])
            b_mean = jnp.sum(w * batch, axis=0) / jnp.maximum(b_count, 1.0)
            b_var = jnp.sum(w * (batch - b_mean) ** 2, axis=0) / jnp.maximum(b_count, 1.0)
        delta = b_mean - self.mean
        total = self.count + b_count
        mean = self.mean + delta * b_count / total
        m2 = self.var * self.count + b_var * b_count + delta**2 * self.count * b_count / total
        return RunningMeanStd(mean, m2 / total, total)

    def normalize(self, x, clip: float | None = None):
        y = (x - self.mean) / jnp.sqrt(self.var + EPS)
        return y if clip is None else jnp.clip(y, -clip, clip)


@struct.dataclass
class ReturnNormalizer:
    rms: RunningMeanStd  # scalar statistics of the discounted return
    ret: jax.Array  # [num_envs] running discounted return per env

    @classmethod
    def create(cls, num_envs: int) -> "ReturnNormalizer":
        return cls(RunningMeanStd.create(()), jnp.zeros((num_envs,), jnp.float32))

    def step(self, reward, done, gamma, clip: float):
        """One env step for all envs: returns (new normaliser, scaled and clipped reward)."""
        ret = self.ret * gamma + reward
        rms = self.rms.update(ret)
        scaled = jnp.clip(reward / jnp.sqrt(rms.var + EPS), -clip, clip)
        return ReturnNormalizer(rms, jnp.where(done, 0.0, ret)), scaled

    def reset(self) -> "ReturnNormalizer":
        return self.replace(ret=jnp.zeros_like(self.ret))
