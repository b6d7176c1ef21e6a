"""Classic CartPole (Barto, Sutton & Anderson 1983; Gymnasium CartPole-v1 dynamics, Euler
integration) behind `envs.core.Environment`: a tiny, fast env for unit tests of learners and of
the level machinery. Its physical constants are level parameters, and gravity, pole half-length
and push force form the teacher-controllable `ParamSpace`.

Observation: [x, x_dot, theta, theta_dot]. Actions: 0 push left, 1 push right. Reward 1 per step
(including the terminating one, as Gymnasium). Terminates when |x| > 2.4 or |theta| > 12 degrees;
truncated at `max_steps` (500) by the base class.
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from flax import struct

from envs.core import Box, Discrete, EnvParams, EnvState, Environment, ParamSpace, UEDSpec


@struct.dataclass
class CartPoleParams(EnvParams):
    gravity: jax.Array = 9.8
    masscart: jax.Array = 1.0
    masspole: jax.Array = 0.1
    length: jax.Array = 0.5  # half the pole length (Gymnasium convention)
    force_mag: jax.Array = 10.0
    tau: jax.Array = 0.02  # seconds per step
    x_threshold: jax.Array = 2.4
    theta_threshold: jax.Array = 12 * 2 * math.pi / 360


@struct.dataclass
class CartPoleState(EnvState):
    x: jax.Array
    x_dot: jax.Array
    theta: jax.Array
    theta_dot: jax.Array


def _default_params(**kw) -> CartPoleParams:
    p = CartPoleParams(max_steps=500)
    p = p.replace(**kw)
    return CartPoleParams(
        max_steps=jnp.asarray(p.max_steps, jnp.int32),
        **{f: jnp.asarray(getattr(p, f), jnp.float32) for f in (
            "gravity", "masscart", "masspole", "length", "force_mag", "tau", "x_threshold", "theta_threshold")},
    )


# Named levels: field overrides of the default level.
LEVEL_FIELDS = {
    "default": dict(),
    "moon": dict(gravity=1.62),
    "heavy": dict(gravity=20.0, masspole=0.3),
    "long_pole": dict(length=1.0),
    "short": dict(max_steps=200),
}

#: name -> builder(**overrides) -> CartPoleParams (used by `python -m shed_jax ppo --level NAME`).
LEVELS = {name: functools.partial(_default_params, **fields) for name, fields in LEVEL_FIELDS.items()}


def named_levels(base):
    """Every level of ``LEVELS``, stacked (leading level axis), with their names."""
    built = [build() for build in LEVELS.values()]
    return jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *built), list(LEVELS)


# No teacher box or evaluation set of its own: Θ is the whole param_space (tests pass their own levels).
UED = UEDSpec(named_levels=named_levels, solved_threshold=475.0)  # Gymnasium's CartPole-v1 threshold


class CartPole(Environment):
    name = "cartpole"
    ued = UED

    @property
    def default_params(self) -> CartPoleParams:
        return _default_params()

    @staticmethod
    def level(name: str) -> CartPoleParams:
        if name not in LEVELS:
            raise ValueError(f"cartpole: unknown level {name!r}; known: {', '.join(LEVELS)}")
        return LEVELS[name]()

    @property
    def param_space(self) -> ParamSpace:
        return ParamSpace(("gravity", "length", "force_mag"), [1.0, 0.25, 5.0], [20.0, 1.0, 20.0], self.default_params)

    @property
    def param_bounds(self) -> dict:
        pos = (0.0, math.inf, False, False)
        return {
            "max_steps": (1, 2**31 - 1, True, True),
            "gravity": (0.0, math.inf, True, False),
            "masscart": pos,
            "masspole": pos,
            "length": pos,
            "force_mag": pos,
            "tau": pos,
            "x_threshold": pos,
            "theta_threshold": pos,
        }

    def observation_space(self, params=None) -> Box:
        return Box(-jnp.inf, jnp.inf, (4,), jnp.float32)

    def action_space(self, params=None) -> Discrete:
        return Discrete(2)

    @staticmethod
    def _obs(s: CartPoleState):
        return jnp.stack([s.x, s.x_dot, s.theta, s.theta_dot]).astype(jnp.float32)

    def reset_env(self, key, params):
        x, x_dot, theta, theta_dot = jax.random.uniform(key, (4,), jnp.float32, -0.05, 0.05)
        s = CartPoleState(
            time=jnp.asarray(0, jnp.int32), episode_return=jnp.asarray(0.0, jnp.float32),
            x=x, x_dot=x_dot, theta=theta, theta_dot=theta_dot,
        )
        return self._obs(s), s

    def step_env(self, key, state, action, params):
        p = params
        force = jnp.where(action == 1, p.force_mag, -p.force_mag)
        total_mass = p.masspole + p.masscart
        polemass_length = p.masspole * p.length
        cos, sin = jnp.cos(state.theta), jnp.sin(state.theta)
        temp = (force + polemass_length * state.theta_dot**2 * sin) / total_mass
        theta_acc = (p.gravity * sin - cos * temp) / (p.length * (4.0 / 3.0 - p.masspole * cos**2 / total_mass))
        x_acc = temp - polemass_length * theta_acc * cos / total_mass
        # explicit Euler, as Gymnasium's default "euler" kinematics integrator
        s = state.replace(
            x=state.x + p.tau * state.x_dot,
            x_dot=state.x_dot + p.tau * x_acc,
            theta=state.theta + p.tau * state.theta_dot,
            theta_dot=state.theta_dot + p.tau * theta_acc,
        )
        terminated = (jnp.abs(s.x) > p.x_threshold) | (jnp.abs(s.theta) > p.theta_threshold)
        return self._obs(s), s, jnp.asarray(1.0, jnp.float32), terminated, {}
