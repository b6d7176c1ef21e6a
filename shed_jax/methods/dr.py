"""Domain randomisation (DR), plus the level plumbing every native-mode baseline shares.

DR (docs/design.md §8.2): each PPO rollout, every slot gets a fresh level drawn from a fixed distribution and
the student trains on all of them. Default distribution: U(Θ), the teacher's box (lander: the docs/design.md
1.6 box with wind on; walker: U(FULL)). Option ``distribution="code"``: the official lander code's
"hard" Gaussian DR (g ~ N(-10, 1), wind on with p 0.5, wind ~ N(15, 1), turb ~ N(1.5, 0.5), each
clipped), which lies mostly outside Θ. Option ``level_switch="episode"``: a slot moves to its fresh
level only when its current episode ends, so episodes longer than a rollout are played to the end
(docs/baselines.md, "Rollout length in native mode").

Shared plumbing (used by plr.py, accel.py, paired.py):

* :func:`teacher_space` -- the box Θ levels live in, per environment.
* :class:`LevelCodec` -- a level is a parameter vector in ``param_space`` order plus a terrain
  seed; the codec turns ``([n, d], [n])`` into an env params pytree. Environments whose params
  have a ``terrain_seed`` field (the walker) get the seed and ``fixed_terrain=True``, so a level
  is exactly reproducible (DCD level semantics, docs/walker.md "Level"); others ignore the seed.
* :func:`nan_like` -- NaN-filled metrics for ``lax.cond`` branches that skip a PPO update.
* :func:`warn_if_rollouts_cut_episodes` -- native mode resets every slot at each rollout, so it
  warns when a training episode can outlast a rollout.
"""
from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from envs.core import ParamSpace
from shed_jax.methods.base import StepInfo
from shed_jax.methods.mutations import new_seeds

# docs/design.md §5: the lander teacher box Θ, (gravity, wind_power, turbulence_power).
LANDER_THETA_LOW = (-9.0, 0.01, 0.01)
LANDER_THETA_HIGH = (-0.01, 12.0, 1.5)
LANDER_TRAIN_MAX_STEPS = 600  # docs/design.md §13.1: training envs 600 steps, eval/test 500 [official code]


def teacher_space(env, low=None, high=None) -> ParamSpace:
    """The box Θ the teacher samples from.

    Explicit ``low``/``high`` (validated to lie inside ``env.param_space``) win. Otherwise the
    lander uses the docs/design.md §5 box with ``enable_wind=True`` and the 600-step training time limit for
    every generated level, and any other environment its whole ``param_space`` (walker: FULL).
    """
    space = env.param_space
    base = space.base
    lander = getattr(env, "name", "").startswith("lander")
    if base is not None and hasattr(base, "enable_wind"):
        base = base.replace(enable_wind=jnp.asarray(True, jnp.asarray(base.enable_wind).dtype))
    if base is not None and lander:
        base = base.replace(max_steps=jnp.asarray(LANDER_TRAIN_MAX_STEPS, jnp.asarray(base.max_steps).dtype))
    if low is None and high is None and lander:
        if space.dim != 3:
            raise ValueError(f"lander teacher box expects 3 parameters (gravity, wind, turbulence), got {space.names}")
        low, high = LANDER_THETA_LOW, LANDER_THETA_HIGH
    return space.with_bounds(low, high, base)


class RolloutTruncationWarning(UserWarning):
    """A native-mode method whose rollouts are shorter than a training episode may last."""


def warn_if_rollouts_cut_episodes(name: str, student, space: ParamSpace, other_fix: str = "") -> None:
    """Warn when native-mode rollouts cannot hold a whole training episode.

    Native mode (docs/design.md §8.1) resets every slot onto its new level at the start of each rollout, so an
    episode longer than ``student.config.num_steps`` is cut off and its end (a landing, the walker's
    goal) is never seen in training. DCD's and JaxUED's rollouts are as long as an episode; the
    lander (128 < 600) and walker (32 < 2000) presets' are not (docs/baselines.md).
    """
    limit = getattr(space.base, "max_steps", None) if space.base is not None else None
    if limit is None or student is None:  # a method built without a student only samples levels
        return
    limit, steps = int(np.max(np.asarray(limit))), int(student.config.num_steps)
    if steps >= limit:
        return
    batch = steps * int(student.config.num_envs)
    longer = next((k * steps for k in range(-(-limit // steps), batch // steps + 1) if batch % (k * steps) == 0), None)
    hint = (f", e.g. --ppo num_envs={batch // longer} --ppo num_steps={longer} (the same {batch:,} steps per update)"
            if longer is not None else "")
    warnings.warn(
        f"{name}: native-mode rollouts of {steps} steps reset every slot, but a training episode may last "
        f"{limit} steps; longer episodes are cut off and their ends never reach the student (docs/baselines.md, "
        f"'Rollout length in native mode'). Rollouts of >= {limit} steps avoid it{hint}.{other_fix}",
        RolloutTruncationWarning, stacklevel=3)


@dataclasses.dataclass(frozen=True)
class LevelCodec:
    """Level vectors (+ terrain seeds) -> env params pytrees, for one box ``space``."""

    space: ParamSpace

    @property
    def dim(self) -> int:
        return self.space.dim

    @property
    def has_seed(self) -> bool:
        return self.space.base is not None and hasattr(self.space.base, "terrain_seed")

    def to_params(self, vecs: jax.Array, seeds: jax.Array | None = None):
        """``[n, d]`` vectors (clipped into the box) and ``[n]`` seeds -> params with leading n."""
        params = self.space.from_vector(vecs)
        if self.has_seed and seeds is not None:
            n = vecs.shape[0]
            params = params.replace(
                terrain_seed=jnp.asarray(seeds, jnp.asarray(self.space.base.terrain_seed).dtype),
                fixed_terrain=jnp.ones((n,), jnp.asarray(self.space.base.fixed_terrain).dtype),
            )
        return params

    def sample_uniform(self, key: jax.Array, n: int):
        """``n`` levels uniform over the box, each with a fresh seed -> (vecs [n, d], seeds [n])."""
        k_v, k_s = jax.random.split(key)
        return self.space.sample_vector(k_v, (n,)), new_seeds(k_s, n)


def nan_like(tree: Any) -> Any:
    """A pytree of NaNs (floats) / zeros (ints, bools) shaped like ``tree`` (or its ShapeDtypeStructs)."""

    def fill(x):
        dt = jnp.dtype(x.dtype)
        return jnp.full(x.shape, jnp.nan if jnp.issubdtype(dt, jnp.floating) else 0, dt)

    return jax.tree_util.tree_map(fill, tree)


def mean_metrics(metrics: Any) -> Any:
    """Mean over the leading (update) axis, ignoring NaN placeholders of skipped updates."""
    return jax.tree_util.tree_map(lambda x: jnp.nanmean(jnp.asarray(x, jnp.float32), axis=0), metrics)


def update_metrics_shape(student, sstate, key):
    """Shapes of ``student.update``'s metrics, without running it (for NaN placeholders)."""
    traj_shape = jax.eval_shape(student.rollout, sstate, key)[1]
    return jax.eval_shape(student.update, sstate, key, traj_shape)[1]


# --------------------------------------------------------------------------------------------
# DR
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class DRConfig:
    """DR settings. ``updates_per_step`` PPO updates (num_envs x num_steps steps each) per budget step."""

    updates_per_step: int = 10
    distribution: str = "uniform"  # "uniform": U(Θ); "code": official-code Gaussian DR (lander only)
    low: tuple[float, ...] | None = None  # Θ override (default: teacher_space)
    high: tuple[float, ...] | None = None
    # "rollout" (docs/design.md §8.1, DCD): every rollout resets every slot onto a new level. "episode": a slot
    # moves to a new level only when its episode ends (student.rollout's next_levels), so episodes
    # longer than a rollout run to their end.
    level_switch: str = "rollout"

    def __post_init__(self):
        if not isinstance(self.updates_per_step, int) or self.updates_per_step < 1:
            raise ValueError(f"DRConfig.updates_per_step must be a positive int, got {self.updates_per_step!r}")
        if self.distribution not in ("uniform", "code"):
            raise ValueError(f"DRConfig.distribution must be 'uniform' or 'code', got {self.distribution!r}")
        if self.level_switch not in ("rollout", "episode"):
            raise ValueError(f"DRConfig.level_switch must be 'rollout' or 'episode', got {self.level_switch!r}")


# docs/design.md §8.2 `dr=code` [official code]: (mean, std, clip low, clip high) per lander parameter.
_CODE_DR = ((-10.0, 1.0, -11.99, -0.01), (15.0, 1.0, 0.01, 19.99), (1.5, 0.5, 0.01, 1.99))


@dataclasses.dataclass(frozen=True)
class DR:
    """Domain randomisation behind the UED method interface (native mode)."""

    env: Any
    student: Any
    config: DRConfig = DRConfig()
    name: str = "dr"

    def __post_init__(self):
        space = teacher_space(self.env, self.config.low, self.config.high)
        if self.config.distribution == "code":
            if not getattr(self.env, "name", "").startswith("lander"):
                raise ValueError(f"DRConfig.distribution='code' is the lander's official-code DR; env is {self.env.name!r}")
            # the code distribution leaves Θ; build params in the wider physically valid box
            lo = np.array([c[2] for c in _CODE_DR], np.float32)
            hi = np.array([c[3] for c in _CODE_DR], np.float32)
            space = ParamSpace(space.names, lo, hi, space.base)
        object.__setattr__(self, "codec", LevelCodec(space))
        if self.config.level_switch == "rollout":  # "episode" runs every episode to its end
            warn_if_rollouts_cut_episodes(self.name, self.student, space,
                                          " For DR, so does --set level_switch=episode.")

    def sample_levels(self, key: jax.Array, n: int):
        """``n`` DR levels -> (vectors [n, d], params pytree with leading n)."""
        if self.config.distribution == "uniform":
            vecs, seeds = self.codec.sample_uniform(key, n)
            return vecs, self.codec.to_params(vecs, seeds)
        k_v, k_w = jax.random.split(key)
        mean = jnp.asarray([c[0] for c in _CODE_DR])
        std = jnp.asarray([c[1] for c in _CODE_DR])
        vecs = mean + std * jax.random.normal(k_v, (n, 3))
        vecs = jnp.clip(vecs, self.codec.space.low, self.codec.space.high)
        params = self.codec.to_params(vecs)
        wind_on = jax.random.bernoulli(k_w, 0.5, (n,))
        params = params.replace(enable_wind=wind_on.astype(jnp.asarray(params.enable_wind).dtype))
        return vecs, params

    def init(self, key: jax.Array):
        return {}

    def begin_episode(self, key: jax.Array, mstate, sstate):
        if self.config.level_switch == "episode":  # the fresh student's slots start on DR levels
            k_lvl, k_assign = jax.random.split(key)
            sstate = self.student.assign_levels(sstate, k_assign, self.sample_levels(k_lvl, self.student.config.num_envs)[1])
        return mstate, sstate

    def step(self, key: jax.Array, mstate, sstate):
        student = self.student
        n = student.config.num_envs
        per_episode = self.config.level_switch == "episode"

        def one_update(s, k):
            k_lvl, k_assign, k_roll, k_upd = jax.random.split(k, 4)
            vecs, params = self.sample_levels(k_lvl, n)
            if per_episode:  # slot j takes level j when its episode ends (at most once per rollout)
                s, traj = student.rollout(s, k_roll, next_levels=params)
                used = traj.dones.any(axis=0)
            else:
                s = student.assign_levels(s, k_assign, params)
                s, traj = student.rollout(s, k_roll)
                used = jnp.ones((n,), bool)
            s, metrics = student.update(s, k_upd, traj)
            return s, (vecs, used, metrics)

        u = self.config.updates_per_step
        sstate, (vecs, used, metrics) = jax.lax.scan(one_update, sstate, jax.random.split(key, u))
        info = StepInfo(
            levels=vecs.reshape(u * n, -1),
            env_steps_train=jnp.int32(u * student.env_steps_per_update),
            env_steps_eval=jnp.int32(0),
            teacher_reward=jnp.float32(jnp.nan),
            num_new_levels=used.sum().astype(jnp.int32),
            # "episode": levels drawn but not reached (no episode end in that slot) were never played
            extras={"ppo": mean_metrics(metrics), "levels_trained_mask": used.reshape(u * n)},
        )
        return mstate, sstate, info
