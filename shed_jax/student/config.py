"""Static PPO configuration (`PPOConfig`) and dynamic hyperparameters (`PPOHyperparams`).

The split is what makes sweeps cheap: everything that fixes array shapes or program structure
(number of envs, rollout length, network sizes, on/off switches) is a frozen, hashable
`PPOConfig` that the student closes over at trace time; every float one may want to sweep
(learning rate, entropy coefficient, clip epsilon, discount, ...) is a leaf of the
`PPOHyperparams` pytree stored inside the student state, so ``jax.vmap`` over a batch of
hyperparameters is a single compile.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal, get_args

import jax.numpy as jnp
from flax import struct

from shed_jax.configs import check_modes

Activation = Literal["tanh", "relu", "elu", "gelu", "silu"]
ACTIVATIONS = get_args(Activation)
# Where a training rollout's auto-resets come from: "per_step", the env's own `step` (every env
# computes a fresh reset at every step under vmap and keeps it where its episode ended);
# "per_rollout", one reset per slot drawn at the start of each rollout (and one per pending level
# switch), which every episode of that slot ending in the rollout restarts from.
ResetDraw = Literal["per_step", "per_rollout"]

_HPARAM_RANGES = {
    # name: (low, high, low_inclusive, high_inclusive)
    "lr": (0.0, math.inf, False, False),
    "ent_coef": (0.0, math.inf, True, False),
    "clip_eps": (0.0, math.inf, False, False),
    "vf_coef": (0.0, math.inf, True, False),
    "gamma": (0.0, 1.0, True, True),
    "gae_lambda": (0.0, 1.0, True, True),
    "max_grad_norm": (0.0, math.inf, False, False),
}


@struct.dataclass
class PPOHyperparams:
    """Dynamic PPO hyperparameters: a pytree of float scalars (or batches of them, for vmap).

    Built with Python floats these are hashable and can sit inside a `PPOConfig` as defaults;
    `as_arrays()` turns them into float32 arrays for the student state.
    """

    lr: Any = 3e-4
    ent_coef: Any = 0.01
    clip_eps: Any = 0.2
    vf_coef: Any = 0.5
    gamma: Any = 0.99
    gae_lambda: Any = 0.95
    max_grad_norm: Any = 0.5

    def validate(self) -> "PPOHyperparams":
        """Raise ValueError naming the field for concrete values outside their valid range."""
        from envs.core import check_ranges

        check_ranges(self, _HPARAM_RANGES)
        return self

    def as_arrays(self) -> "PPOHyperparams":
        return self.validate().replace(**{f: jnp.asarray(getattr(self, f), jnp.float32) for f in _HPARAM_RANGES})

    @staticmethod
    def stack(items: list["PPOHyperparams"]) -> "PPOHyperparams":
        """A batch (leading axis) of hyperparameter sets, ready for ``jax.vmap``."""
        items = [h.validate() for h in items]
        return PPOHyperparams(**{f: jnp.asarray([getattr(h, f) for h in items], jnp.float32) for f in _HPARAM_RANGES})


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Static PPO settings (shapes and switches), validated on construction.

    num_envs x num_steps transitions per rollout, split into num_minibatches minibatches for
    update_epochs epochs. `hparams` holds the default dynamic hyperparameters used when
    ``student.init`` is called without any.
    """

    num_envs: int = 40
    num_steps: int = 128
    update_epochs: int = 4
    num_minibatches: int = 8
    actor_hidden: tuple[int, ...] = (64, 64)
    critic_hidden: tuple[int, ...] = (64, 64)
    activation: Activation = "tanh"
    normalize_advantages: bool = True
    clip_value_loss: bool = False
    normalize_observations: bool = False
    normalize_returns: bool = True
    reward_clip: float = 10.0  # clip of normalised rewards, as SB3 VecNormalize (ignored if not normalising)
    obs_clip: float = 10.0  # clip of normalised observations, as SB3 VecNormalize
    init_log_std: float = 0.0  # continuous actions: initial state-independent log-std
    # continuous actions: soft bounds on the log-std (networks.bounded_log_std; infinite: none)
    log_std_min: float = -math.inf
    log_std_max: float = math.inf
    anneal_lr: bool = False
    anneal_updates: int = 0  # updates over which lr decays linearly to 0 (required if anneal_lr)
    reset_draw: ResetDraw = "per_step"  # see ResetDraw; "per_rollout" for envs with a costly reset
    hparams: PPOHyperparams = PPOHyperparams()

    def __post_init__(self):
        for name in ("num_envs", "num_steps", "update_epochs", "num_minibatches"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"PPOConfig.{name} must be a positive int, got {v!r}")
        if (self.num_envs * self.num_steps) % self.num_minibatches:
            raise ValueError(
                f"PPOConfig: num_envs*num_steps = {self.num_envs * self.num_steps} is not divisible by "
                f"num_minibatches = {self.num_minibatches}"
            )
        for name in ("actor_hidden", "critic_hidden"):
            v = tuple(getattr(self, name))
            if not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in v):
                raise ValueError(f"PPOConfig.{name} must be a tuple of positive ints, got {getattr(self, name)!r}")
            object.__setattr__(self, name, v)
        check_modes(self)
        for name in ("reward_clip", "obs_clip"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0):
                raise ValueError(f"PPOConfig.{name} must be a positive number, got {v!r}")
        for name in ("init_log_std", "log_std_min", "log_std_max"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or math.isnan(v):
                raise ValueError(f"PPOConfig.{name} must be a number, got {v!r}")
        if not self.log_std_min < self.log_std_max:  # also refuses a lower bound of inf or an upper of -inf
            raise ValueError(f"PPOConfig.log_std_min must be below log_std_max, both finite or -inf/inf for no bound, "
                             f"got ({self.log_std_min:g}, {self.log_std_max:g})")
        if math.isinf(self.init_log_std) or not self.log_std_min < self.init_log_std < self.log_std_max:
            raise ValueError(f"PPOConfig.init_log_std must be finite and inside (log_std_min, log_std_max) = "
                             f"({self.log_std_min:g}, {self.log_std_max:g}), got {self.init_log_std!r}")
        if not isinstance(self.anneal_updates, int) or self.anneal_updates < 0:
            raise ValueError(f"PPOConfig.anneal_updates must be a non-negative int, got {self.anneal_updates!r}")
        if self.anneal_lr and self.anneal_updates < 1:
            raise ValueError("PPOConfig.anneal_lr=True needs anneal_updates >= 1 (the length of the decay)")
        if not isinstance(self.hparams, PPOHyperparams):
            raise ValueError(f"PPOConfig.hparams must be a PPOHyperparams, got {type(self.hparams).__name__}")
        hp = self.hparams.validate()
        # keep the defaults hashable (Python floats) so the config can be a static jit argument
        object.__setattr__(self, "hparams", hp.replace(**{f: float(getattr(hp, f)) for f in _HPARAM_RANGES}))

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches

    def replace(self, **changes) -> "PPOConfig":
        return dataclasses.replace(self, **changes)

    def with_overrides(self, overrides: dict | None) -> "PPOConfig":
        """This config with ``overrides`` applied: PPOConfig fields and PPOHyperparams fields by name
        (as :func:`parse_overrides` returns them); the result is validated like any PPOConfig."""
        from shed_jax import configs

        overrides = dict(overrides or {})
        if "hparams" in overrides:
            raise ValueError("PPO overrides: unknown field 'hparams' (give the hyperparameters by name, e.g. lr)")
        hp = {k: overrides.pop(k) for k in list(overrides) if k in _HPARAM_RANGES}
        if hp:
            overrides["hparams"] = hp
        return configs.with_overrides(self, overrides, "PPO overrides: ")

    @classmethod
    def for_env(cls, name: str, **overrides) -> "PPOConfig":
        """The preset for a registered environment (docs/design.md §10.1), with optional field overrides."""
        if name not in PRESETS:
            raise ValueError(f"no PPO preset for environment {name!r}; known: {', '.join(sorted(PRESETS))}")
        return dataclasses.replace(PRESETS[name], **overrides)


# docs/design.md §10.1, lander column (SB3 LunarLander practice). Meets the acceptance check (median of 8 seeds
# >= 200 within 3M env steps) on the discrete lander; change these values only with the evidence of
# a GPU run of experiments/bench_ppo.py (docs/benchmarks.md "Student PPO", dated runs in docs/log/benchmarks.md).
_LANDER = PPOConfig(
    num_envs=40,
    num_steps=128,
    update_epochs=4,
    num_minibatches=8,
    normalize_returns=True,
    hparams=PPOHyperparams(lr=3e-4, ent_coef=0.01, clip_eps=0.2, vf_coef=0.5, gamma=0.999, gae_lambda=0.98, max_grad_norm=0.5),
)

# The continuous lander: the discrete preset with a Gaussian policy that starts narrower (std
# e^-0.5 = 0.61 instead of 1), no entropy bonus, and 32 minibatches (160 samples each, 4x the
# gradient steps). With the discrete preset unchanged the stochastic policy's median was 144 at 3M
# steps; with this one it is 276, and the median training return passes 200 at 0.71M steps
# (8 seeds, H200, 2026-11-22; docs/log/benchmarks.md "The walker, the tuned continuous lander and Brax's PPO").
_LANDER_CONTINUOUS = dataclasses.replace(
    _LANDER, num_minibatches=32, init_log_std=-0.5, hparams=_LANDER.hparams.replace(ent_coef=0.0)
)

PRESETS: dict[str, PPOConfig] = {
    "lander": _LANDER,
    "lander-continuous": _LANDER_CONTINUOUS,
    # The walker student: observations normalised (running mean/std), 1,024 envs x 64 steps per
    # rollout, 10 epochs of 64 minibatches (1,024 samples each), gamma 0.999, lambda 0.95, no entropy
    # bonus (close to SB3's tuned BipedalWalker PPO). 8 seeds on the flat BipedalWalker level, 16
    # stochastic evaluation episodes each: median 259 at 3.1M env steps, every seed >= 230 from 4.2M
    # (H200, 2026-11-25; docs/walker.md). The earlier preset (256 x 32, 5 epochs
    # of 8, gamma 0.99, lambda 0.9, raw observations) needed 18.4M steps for a median of 230.
    # Resets drawn once per rollout: on the MJX walker (H100, 4 seeds, 5.2M steps) training ran 1.34x
    # faster than with a reset at every step (74 s vs 99 s) and the final stochastic median was 276 vs
    # 275; on the 2-D walker a per-step reset's rollout was still compiling after 7.5 minutes
    # (docs/walker.md, "Resets once per rollout"; docs/bipedal.md).
    "walker": PPOConfig(
        num_envs=1024,
        num_steps=64,
        update_epochs=10,
        num_minibatches=64,
        normalize_observations=True,
        normalize_returns=True,
        clip_value_loss=False,
        reset_draw="per_rollout",
        hparams=PPOHyperparams(lr=3e-4, ent_coef=0.0, clip_eps=0.2, vf_coef=0.5, gamma=0.999, gae_lambda=0.95, max_grad_norm=0.5),
    ),
    # PureJaxRL's CartPole settings scaled to more envs; fast to train on CPU, used by the tests.
    "cartpole": PPOConfig(
        num_envs=16,
        num_steps=64,
        update_epochs=4,
        num_minibatches=4,
        normalize_returns=True,
        hparams=PPOHyperparams(lr=1e-3, ent_coef=0.01, clip_eps=0.2, vf_coef=0.5, gamma=0.99, gae_lambda=0.95, max_grad_norm=0.5),
    ),
}


# The Box2D-faithful walker on physics2d (envs/bipedal): the MJX walker's task, observations and
# reward, so the same student; not yet tuned on it.
PRESETS["bipedal"] = PRESETS["walker"]


def parse_overrides(items) -> dict:
    """Command-line ``KEY=VALUE`` strings -> PPO overrides for :meth:`PPOConfig.with_overrides`.

    ``["num_envs=2048", "ent_coef=0", "actor_hidden=128,128"]`` -> ``{"num_envs": 2048,
    "ent_coef": 0.0, "actor_hidden": (128, 128)}``. Values take the type of the field's default
    (int, float, bool as true/false/1/0, int tuples); hyperparameters are floats. Unknown keys and
    malformed items raise ValueError naming the known fields.
    """
    cfg_fields = {f.name for f in dataclasses.fields(PPOConfig)} - {"hparams"}
    defaults = PPOConfig()
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--ppo takes KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        if key not in _HPARAM_RANGES and key not in cfg_fields:
            raise ValueError(f"--ppo: unknown field {key!r}; known: {', '.join(sorted(cfg_fields | set(_HPARAM_RANGES)))}")
        default = 0.0 if key in _HPARAM_RANGES else getattr(defaults, key)
        try:
            if isinstance(default, bool):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError(value)
                out[key] = value.lower() in ("true", "1")
            elif isinstance(default, tuple):
                out[key] = tuple(int(v) for v in value.split(","))
            elif isinstance(default, (int, float)):
                out[key] = type(default)(value)
            else:
                out[key] = value
        except ValueError:
            kind = ("true or false" if isinstance(default, bool) else "comma-separated ints" if isinstance(default, tuple)
                    else f"an {type(default).__name__}" if isinstance(default, int) else f"a {type(default).__name__}")
            raise ValueError(f"--ppo {key} takes {kind}, got {value!r}") from None
    return out
