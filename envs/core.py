"""One environment interface for every environment, following gymnax conventions.

An environment is a stateless Python object holding only static configuration. Everything that
changes lives in two pytrees that the caller threads explicitly:

* ``params`` -- the *level*: an ``EnvParams`` dataclass (gravity, terrain parameters, time limit...).
  Every leaf is an array, so a batch of different levels is just a params pytree with a leading axis
  and ``jax.vmap`` runs one level per env.
* ``state`` -- the simulator state of one episode, an ``EnvState`` subclass.

``reset(key, params) -> (obs, state)`` and ``step(key, state, action, params) -> (obs, state, reward,
done, info)``. ``step`` auto-resets on ``done``: the returned ``obs``/``state`` belong to a fresh
episode *of the same level*, drawn from the step's key (new terrain, new random draws -- never a
cached first state). ``info`` carries ``terminated``, ``truncated``, ``final_obs`` (the observation
before the reset, for bootstrapping on time limits) and, on the done step, ``episode_return`` and
``episode_length`` (zero on other steps).

Subclasses implement ``reset_env`` and ``step_env`` (no auto-reset, no time-limit bookkeeping),
``default_params``, ``observation_space``, ``action_space`` and ``param_space``; an environment for
unsupervised environment design also sets ``ued`` (:class:`UEDSpec`: teacher box, training time
limit, evaluation/test/named level sets, solved threshold).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


@struct.dataclass
class EnvState:
    """Fields every environment state carries; subclasses add their own after these."""

    time: jax.Array  # steps taken in the current episode (int32)
    episode_return: jax.Array  # undiscounted return accumulated in the current episode (float32)


@struct.dataclass
class EnvParams:
    """Fields every level carries; subclasses add their own after these."""

    max_steps: jax.Array  # time limit: the episode is truncated after this many steps (int32)


# --------------------------------------------------------------------------------------------
# Spaces
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Discrete:
    """Actions {0, ..., n-1}, given as an integer scalar per env."""

    n: int
    shape: tuple = ()
    dtype: Any = jnp.int32

    def sample(self, key: jax.Array) -> jax.Array:
        return jax.random.randint(key, self.shape, 0, self.n, dtype=self.dtype)

    def contains(self, x) -> jax.Array:
        x = jnp.asarray(x)
        return jnp.logical_and(x >= 0, x < self.n)


@dataclasses.dataclass(frozen=True)
class Box:
    """A box of real vectors ``low <= x <= high`` (bounds may be infinite)."""

    low: Any
    high: Any
    shape: tuple
    dtype: Any = jnp.float32

    def sample(self, key: jax.Array) -> jax.Array:
        low = jnp.broadcast_to(jnp.asarray(self.low, self.dtype), self.shape)
        high = jnp.broadcast_to(jnp.asarray(self.high, self.dtype), self.shape)
        low = jnp.where(jnp.isfinite(low), low, -1.0)
        high = jnp.where(jnp.isfinite(high), high, 1.0)
        return jax.random.uniform(key, self.shape, self.dtype, low, high)

    def contains(self, x) -> jax.Array:
        x = jnp.asarray(x)
        return jnp.all((x >= self.low) & (x <= self.high))


# --------------------------------------------------------------------------------------------
# Range checks (environment parameters here; the student's and the teacher's hyperparameters too)
# --------------------------------------------------------------------------------------------


def check_ranges(obj, ranges: dict, label: Callable[[str], str] | None = None) -> None:
    """ValueError naming the field for a concrete value outside ``ranges[field]``.

    ``ranges``: field -> (low, high, low_inclusive, high_inclusive); values may be scalars or arrays
    (every entry is checked, and the message shows the ones outside). ``label(field)`` names the
    field in the message (default ``<Class>.<field>``). Traced values are skipped (nothing to check
    at trace time).
    """
    for name, (lo, hi, lo_inc, hi_inc) in ranges.items():
        value = getattr(obj, name)
        try:
            v = np.asarray(value, dtype=np.float64)
        except Exception:  # a tracer
            continue
        with np.errstate(invalid="ignore"):
            ok = (v >= lo if lo_inc else v > lo) & (v <= hi if hi_inc else v < hi) & np.isfinite(v)
        if not np.all(ok):
            interval = f"{'[' if lo_inc else '('}{lo}, {hi}{']' if hi_inc else ')'}"
            what = label(name) if label is not None else f"{type(obj).__name__}.{name}"
            raise ValueError(f"{what} must be a finite value in {interval}, got {v[~ok] if v.ndim else v}")


# --------------------------------------------------------------------------------------------
# Level parameter space
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ParamSpace:
    """The teacher-controllable parameters of a level, as a box of named scalars.

    ``to_vector``/``from_vector`` convert between an ``EnvParams`` pytree and a float vector of
    shape ``[..., dim]`` (batched levels have leading axes). ``from_vector`` clips into the box and
    fills the fields that are not controllable from ``base``. ``to_unit``/``from_unit`` are the
    affine maps between the box and ``[-1, 1]^dim`` that teachers act in.
    """

    names: tuple[str, ...]
    low: np.ndarray
    high: np.ndarray
    base: Any  # EnvParams used for the non-controllable fields

    def __post_init__(self):
        low = np.asarray(self.low, np.float32)
        high = np.asarray(self.high, np.float32)
        if low.shape != (len(self.names),) or high.shape != low.shape:
            raise ValueError(f"ParamSpace bounds must have shape ({len(self.names)},), got {low.shape} and {high.shape}")
        if np.any(low > high):
            bad = [n for n, lo, hi in zip(self.names, low, high) if lo > hi]
            raise ValueError(f"ParamSpace low > high for {bad}")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)
        object.__setattr__(self, "names", tuple(self.names))

    @property
    def dim(self) -> int:
        return len(self.names)

    def with_bounds(self, low: Sequence[float] | None = None, high: Sequence[float] | None = None, base=None) -> "ParamSpace":
        """A sub-box of this space (e.g. a teacher's Theta), validated to lie inside it."""
        low = self.low if low is None else np.asarray(low, np.float32)
        high = self.high if high is None else np.asarray(high, np.float32)
        if np.any(low < self.low - 1e-6) or np.any(high > self.high + 1e-6):
            raise ValueError(
                f"bounds [{low}, {high}] leave the parameter space [{self.low}, {self.high}] of {self.names}"
            )
        return ParamSpace(self.names, low, high, self.base if base is None else base)

    def to_vector(self, params) -> jax.Array:
        return jnp.stack([jnp.asarray(getattr(params, n), jnp.float32) for n in self.names], axis=-1)

    def from_vector(self, vec, base=None):
        """Params from a ``[..., dim]`` vector, clipped into the box; other fields from ``base``."""
        vec = jnp.asarray(vec, jnp.float32)
        if vec.shape[-1] != self.dim:
            raise ValueError(f"expected a parameter vector with last axis {self.dim} ({self.names}), got shape {vec.shape}")
        vec = jnp.clip(vec, self.low, self.high)
        base = self.base if base is None else base
        batch = vec.shape[:-1]
        def _broadcast(x):
            # a base that is already batched like ``vec`` keeps its per-level values
            x = jnp.asarray(x)
            if batch and x.shape[: len(batch)] == batch:
                return x
            return jnp.broadcast_to(x, batch + x.shape)

        base = jax.tree_util.tree_map(_broadcast, base)
        fields = {}
        for i, n in enumerate(self.names):
            ref = getattr(base, n)
            fields[n] = vec[..., i].astype(jnp.asarray(ref).dtype)
        return base.replace(**fields)

    def to_unit(self, vec) -> jax.Array:
        """Box -> [-1, 1]^dim (affine)."""
        span = np.where(self.high > self.low, self.high - self.low, 1.0)
        return 2.0 * (jnp.asarray(vec, jnp.float32) - self.low) / span - 1.0

    def from_unit(self, u) -> jax.Array:
        """[-1, 1]^dim -> box (affine, clipped)."""
        u = jnp.clip(jnp.asarray(u, jnp.float32), -1.0, 1.0)
        return self.low + (u + 1.0) * 0.5 * (self.high - self.low)

    def sample_vector(self, key: jax.Array, shape: tuple = ()) -> jax.Array:
        return jax.random.uniform(key, shape + (self.dim,), jnp.float32, self.low, self.high)

    def sample(self, key: jax.Array, shape: tuple = (), base=None):
        """Levels drawn uniformly over the box (``shape`` leading batch axes)."""
        return self.from_vector(self.sample_vector(key, shape), base)


# --------------------------------------------------------------------------------------------
# What UED methods need to know about an environment
# --------------------------------------------------------------------------------------------

FIXED, UNIFORM = "fixed", "uniform"


@dataclasses.dataclass(frozen=True)
class EditTable:
    """ACCEL's per-parameter edit steps and EASY box for one environment (``param_space`` order)."""

    steps: tuple[float, ...]
    kinds: tuple[str, ...]  # FIXED: dir * step; UNIFORM: dir * U(0, step)
    easy_low: tuple[float, ...]
    easy_high: tuple[float, ...]

    def __post_init__(self):
        d = len(self.steps)
        for name in ("kinds", "easy_low", "easy_high"):
            if len(getattr(self, name)) != d:
                raise ValueError(f"EditTable.{name} has {len(getattr(self, name))} entries, expected {d} (one per parameter)")
        bad = [k for k in self.kinds if k not in (FIXED, UNIFORM)]
        if bad:
            raise ValueError(f"EditTable.kinds must be {FIXED!r} or {UNIFORM!r}, got {bad}")
        if any(s < 0 for s in self.steps):
            raise ValueError(f"EditTable.steps must be >= 0, got {self.steps}")
        if any(lo > hi for lo, hi in zip(self.easy_low, self.easy_high)):
            raise ValueError(f"EditTable EASY box has low > high: {self.easy_low} vs {self.easy_high}")

    @property
    def dim(self) -> int:
        return len(self.steps)


@dataclasses.dataclass(frozen=True)
class UEDSpec:
    """An environment's unsupervised-environment-design data; methods, presets and CLIs ask this
    (``env.ued``) instead of testing the environment's name. Every field is optional.

    * ``theta_low``/``theta_high``: the teacher box Θ in ``param_space`` order (None: the whole space).
    * ``train_max_steps``, ``train_fields``: the time limit and the other ``(field, value)`` settings
      every generated training level gets (the lander: 600 steps, wind on).
    * ``edit_table``: ACCEL's edit steps and EASY box (None: a generic table of the box).
    * ``editor``: the environment's own level editor ``(key, params, num_edits) -> params`` over the
      whole ``param_space``, or None.
    * ``code_dr``: ``(mean, std, clip low, clip high)`` per parameter of the environment's reference
      code's Gaussian domain randomisation (the lander's "hard" DR), or None.
    * ``eval_set(kind, m) -> LevelSet``: the teacher's m evaluation levels (``kind``: the SHED
      config's ``eval_set``; an environment with one construction ignores it), or None.
    * ``test_sets``: ``((name, build), ...)``; ``named_levels``: one ``build``; a ``build(base_params)``
      returns (params with a leading level axis, one label per level).
    * ``solved_threshold``: the return above which an episode counts as solved, or None.
    * ``final_eval``: the level sets ``run``/``sweep`` evaluate the final students on when
      ``--final-eval`` is not given (comma-separated ``eval --levels`` values, or ``"none"``).
    """

    theta_low: tuple[float, ...] | None = None
    theta_high: tuple[float, ...] | None = None
    train_max_steps: int | None = None
    train_fields: tuple[tuple[str, Any], ...] = ()
    edit_table: EditTable | None = None
    editor: Callable | None = None
    code_dr: tuple[tuple[float, float, float, float], ...] | None = None
    eval_set: Callable | None = None
    test_sets: tuple[tuple[str, Callable], ...] = ()
    named_levels: Callable | None = None
    solved_threshold: float | None = None
    final_eval: str = "none"

    def __post_init__(self):
        if (self.theta_low is None) != (self.theta_high is None):
            raise ValueError("UEDSpec: give both theta_low and theta_high, or neither")
        if self.theta_low is not None and len(self.theta_low) != len(self.theta_high):
            raise ValueError(f"UEDSpec: theta_low has {len(self.theta_low)} entries, theta_high {len(self.theta_high)}")

    def training_params(self, base):
        """``base`` with the training-level settings (``train_fields``, then ``train_max_steps``),
        each cast to the field's dtype."""
        fields = dict(self.train_fields)
        if self.train_max_steps is not None:
            fields["max_steps"] = self.train_max_steps
        return base.replace(**{k: jnp.asarray(v, jnp.asarray(getattr(base, k)).dtype) for k, v in fields.items()})

    def test_set(self, name: str) -> Callable:
        """The ``build`` of the test set ``name`` (ValueError naming the known ones)."""
        sets = dict(self.test_sets)
        if name not in sets:
            raise ValueError(f"unknown test set {name!r}; known: {', '.join(sets) or 'none'}")
        return sets[name]


def restart_where(done, reset, stepped):
    """The auto-reset's select for one env: the ``(obs, state)`` pair ``reset`` where ``done``, else
    ``stepped``. `Environment.step` passes a reset computed at the same step; a rollout may pass one
    drawn before it (a reset per step under ``vmap`` costs a whole ``reset_env`` for every env)."""
    return jax.tree_util.tree_map(lambda r, s: jnp.where(done, r, s), reset, stepped)


# --------------------------------------------------------------------------------------------
# Environment base class
# --------------------------------------------------------------------------------------------


class Environment:
    """Base class: auto-reset, time limits, episode statistics and input validation.

    Subclasses define:
      * ``default_params`` (property) -> EnvParams
      * ``param_space`` (property) -> ParamSpace
      * ``param_bounds`` (property) -> {field: (low, high, low_inclusive, high_inclusive)}, the
        physically valid range checked eagerly (may be wider than ``param_space``)
      * ``reset_env(key, params) -> (obs, state)``
      * ``step_env(key, state, action, params) -> (obs, state, reward, terminated, info)``; must
        not touch ``time``/``episode_return`` (the base class does) and must not auto-reset.
      * ``observation_space(params)``, ``action_space(params)``
      * optionally ``ued`` (a :class:`UEDSpec`): the teacher box, training time limit and level sets
    """

    name: str = "env"
    ued: UEDSpec = UEDSpec()  # what UED methods need to know (subclasses set their own)

    # --- to be provided by subclasses ---
    @property
    def default_params(self):
        raise NotImplementedError

    @property
    def param_space(self) -> ParamSpace:
        raise NotImplementedError

    @property
    def param_bounds(self) -> dict:
        return {}

    def reset_env(self, key, params):
        raise NotImplementedError

    def step_env(self, key, state, action, params):
        raise NotImplementedError

    def observation_space(self, params=None):
        raise NotImplementedError

    def action_space(self, params=None):
        raise NotImplementedError

    # --- public API ---
    def reset(self, key: jax.Array, params=None):
        params = self.default_params if params is None else params
        self.check_params(params)
        return self.reset_env(key, params)

    def step(self, key: jax.Array, state, action, params=None):
        """One step with auto-reset: where the episode ends, the returned obs/state are a fresh
        ``reset_env`` of the same params (``info["final_obs"]`` holds the last observation)."""
        params = self.default_params if params is None else params
        key_step, key_reset = jax.random.split(key)
        obs_st, state_st, reward, done, info = self._step(key_step, state, action, params)
        obs_out, state_out = restart_where(done, self.reset_env(key_reset, params), (obs_st, state_st))
        return obs_out, state_out, reward, done, info

    def step_without_reset(self, key: jax.Array, state, action, params=None):
        """`step` without the auto-reset: the same outputs wherever the episode goes on, and at an
        episode end the final obs/state instead of a reset's. For rollouts that keep only each env's
        first episode (evaluation): a reset computed at every step for every env and then discarded
        costs a whole terrain generation per step on the walker."""
        params = self.default_params if params is None else params
        key_step, _ = jax.random.split(key)  # the same key stream as `step`
        return self._step(key_step, state, action, params)

    def _step(self, key_step, state, action, params):
        self.check_params(params)
        action = self.check_action(action)
        obs_st, state_st, reward, terminated, info = self.step_env(key_step, state, action, params)
        reward = jnp.asarray(reward, jnp.float32)
        terminated = jnp.asarray(terminated, bool)
        time = state.time + 1
        ep_return = state.episode_return + reward
        state_st = state_st.replace(time=time, episode_return=ep_return)
        truncated = jnp.logical_and(time >= params.max_steps, jnp.logical_not(terminated))
        done = jnp.logical_or(terminated, truncated)
        info = dict(info)
        info.update(
            terminated=terminated,
            truncated=truncated,
            final_obs=obs_st,
            episode_return=jnp.where(done, ep_return, 0.0),
            episode_length=jnp.where(done, time, 0),
        )
        return obs_st, state_st, reward, done, info

    # --- validation ---
    def check_params(self, params) -> None:
        """Raise ValueError for concrete (eager) parameters outside their valid range."""
        check_ranges(params, self.param_bounds, label=lambda name: f"{self.name}: parameter '{name}'")

    def check_action(self, action):
        """Static (trace-time) check of the action's shape and dtype for one env."""
        space = self.action_space(None)
        action = jnp.asarray(action)
        if isinstance(space, Discrete):
            if not jnp.issubdtype(action.dtype, jnp.integer):
                raise TypeError(f"{self.name}: discrete action must be an integer, got dtype {action.dtype}")
            if action.shape != ():
                raise ValueError(f"{self.name}: discrete action must be a scalar per env, got shape {action.shape}")
            return action.astype(jnp.int32)
        if action.shape != tuple(space.shape):
            raise ValueError(f"{self.name}: action must have shape {tuple(space.shape)}, got {action.shape}")
        if not jnp.issubdtype(action.dtype, jnp.floating):
            raise TypeError(f"{self.name}: continuous action must be floating point, got dtype {action.dtype}")
        return action.astype(jnp.float32)

    # --- rendering (host side) ---
    def render(self, state, params=None) -> np.ndarray:
        """One unbatched state -> RGB frame (H, W, 3) uint8. Optional per environment."""
        raise NotImplementedError(f"{self.name} has no renderer")

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"
