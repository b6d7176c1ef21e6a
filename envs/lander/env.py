"""Parametric Lunar Lander in pure JAX, statistically faithful to Gymnasium LunarLander-v3.

A level is ``LanderParams`` (gravity, wind on/off, wind and turbulence power, time limit). The rules
(terrain, engines, wind, observation, reward, termination) live here; rigid-body dynamics are
``envs.physics2d``. See docs/design.md §13.1 and docs/lander.md.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import physics2d
from envs.core import Box, Discrete, EnvParams, EnvState, Environment, ParamSpace
from envs.lander import model as M
from envs.lander.levels import UED


@struct.dataclass
class LanderParams(EnvParams):
    """One level. Every field is an array so a batch of levels is a params pytree with a leading axis."""

    gravity: jax.Array = struct.field(default_factory=lambda: jnp.asarray(-10.0, jnp.float32))
    enable_wind: jax.Array = struct.field(default_factory=lambda: jnp.asarray(False))
    wind_power: jax.Array = struct.field(default_factory=lambda: jnp.asarray(15.0, jnp.float32))
    turbulence_power: jax.Array = struct.field(default_factory=lambda: jnp.asarray(1.5, jnp.float32))


def make_params(max_steps=1000, gravity=-10.0, enable_wind=False, wind_power=15.0, turbulence_power=1.5) -> LanderParams:
    """LanderParams with every leaf cast to its canonical dtype (broadcastable values allowed)."""
    return LanderParams(
        max_steps=jnp.asarray(max_steps, jnp.int32),
        gravity=jnp.asarray(gravity, jnp.float32),
        enable_wind=jnp.asarray(enable_wind, bool),
        wind_power=jnp.asarray(wind_power, jnp.float32),
        turbulence_power=jnp.asarray(turbulence_power, jnp.float32),
    )


@struct.dataclass
class LanderState(EnvState):
    world: physics2d.WorldState
    terrain_y: jax.Array  # (CHUNKS,) smoothed ground heights at CHUNK_X
    leg_contact: jax.Array  # (2,) bool, Gymnasium's legs[i].ground_contact after the last step
    leg_pairs: jax.Array  # (2, CHUNKS - 1) bool, leg touching each ground edge after the last step
    prev_shaping: jax.Array  # ()
    wind_idx: jax.Array  # () int32
    torque_idx: jax.Array  # () int32
    main_power: jax.Array  # () last main-engine throttle (0 if off), for rendering
    side_power: jax.Array  # () last side-engine throttle, signed by direction, for rendering


def wave(idx):
    """Gymnasium's wind / turbulence profile tanh(sin(0.02 k) + sin(0.01 pi k))."""
    k = idx.astype(jnp.float32)
    return jnp.tanh(jnp.sin(0.02 * k) + jnp.sin(0.01 * jnp.pi * k))


def terrain(key):
    """Smoothed heights (CHUNKS,) of a fresh random terrain with the flat helipad (docs/lander.md "Model")."""
    h = jax.random.uniform(key, (M.CHUNKS + 1,), jnp.float32, 0.0, M.H / 2)
    pad = (jnp.arange(M.CHUNKS + 1) >= M.CHUNKS // 2 - 2) & (jnp.arange(M.CHUNKS + 1) <= M.CHUNKS // 2 + 2)
    h = jnp.where(pad, jnp.float32(M.HELIPAD_Y), h)
    # smooth_i = 0.33 (h_{i-1} + h_i + h_{i+1}), h_{-1} wrapping to h_{CHUNKS}
    return 0.33 * (jnp.roll(h, 1)[: M.CHUNKS] + h[: M.CHUNKS] + h[1: M.CHUNKS + 1])


def observation(model, world, leg_contact):
    hull_origin = physics2d.body_origin(model, world.bodies)[0]
    b = world.bodies
    return jnp.stack([
        (hull_origin[0] - M.W / 2) / (M.W / 2),
        (hull_origin[1] - (M.HELIPAD_Y + M.LEG_DOWN)) / (M.H / 2),
        b.vel[0, 0] * (M.W / 2) / M.FPS,
        b.vel[0, 1] * (M.H / 2) / M.FPS,
        b.angle[0],
        20.0 * b.omega[0] / M.FPS,
        leg_contact[0].astype(jnp.float32),
        leg_contact[1].astype(jnp.float32),
    ])


def shaping(obs):
    return (-100.0 * jnp.sqrt(obs[0] ** 2 + obs[1] ** 2) - 100.0 * jnp.sqrt(obs[2] ** 2 + obs[3] ** 2)
            - 100.0 * jnp.abs(obs[4]) + 10.0 * obs[6] + 10.0 * obs[7])


def assign_reward(shaped, crashed, asleep):
    """Gymnasium's terminal rules: -100 on a crash, then +100 if asleep (checked second, so it wins);
    terminal rewards replace the shaped reward. Returns (reward, terminated)."""
    reward = jnp.where(crashed, -100.0, shaped)
    reward = jnp.where(asleep, 100.0, reward)
    return reward, crashed | asleep


class LunarLander(Environment):
    """Gymnasium LunarLander-v3 as a pure-JAX, level-parametric environment (see module docstring)."""

    ued = UED  # teacher box Θ, 600-step training levels, official eval/test landers (envs/lander/levels.py)

    def __init__(self, continuous: bool = False, velocity_iterations: int = M.VELOCITY_ITERATIONS,
                 position_iterations: int = M.POSITION_ITERATIONS, unroll: int | None = None,
                 solver_kernel: str = "auto"):
        # unroll: solver-loop unroll factor, a speed knob with no effect on results. None picks 4 on
        # accelerators (2.4 vs 3.7 ms per sequential step at batch 40 on an H200; docs/log/benchmarks.md)
        # and 1 on CPU, where the larger program mostly costs compile time.
        if unroll is None:
            unroll = 1 if jax.default_backend() == "cpu" else 4
        self.continuous = bool(continuous)
        self.name = "lander-continuous" if self.continuous else "lander"
        # solver_kernel: how the solver's iteration loops run; "auto" fuses each into one Pallas
        # kernel on GPU (envs/physics2d/fused.py) and uses plain XLA loops elsewhere.
        self.model = M.lander_model(int(velocity_iterations), int(position_iterations), int(unroll), solver_kernel)
        pos, ang = M.initial_pose()
        self._start_bodies = (pos, ang)
        self._reset_projector = M.reset_projector(int(velocity_iterations), int(position_iterations), int(unroll))

    # --- spaces and levels ---
    @property
    def default_params(self) -> LanderParams:
        return make_params()

    @property
    def param_bounds(self) -> dict:
        return {
            "gravity": (-12.0, 0.0, False, False),
            "wind_power": (0.0, 20.0, True, True),
            "turbulence_power": (0.0, 2.0, True, True),
        }

    @property
    def param_space(self) -> ParamSpace:
        return ParamSpace(("gravity", "wind_power", "turbulence_power"), (-11.99, 0.0, 0.0), (-0.01, 20.0, 2.0),
                          self.default_params)

    def observation_space(self, params=None):
        hi = np.asarray([2.5, 2.5, 10.0, 10.0, 2 * np.pi, 10.0, 1.0, 1.0], np.float32)
        lo = -hi
        lo[6:] = 0.0
        return Box(lo, hi, (8,))

    def action_space(self, params=None):
        return Box(-1.0, 1.0, (2,)) if self.continuous else Discrete(4)

    # --- dynamics ---
    def _engines(self, action):
        """Throttles: (fire_main, p_main, fire_side, p_side, direction) from one action."""
        if self.continuous:
            a = jnp.clip(action, -1.0, 1.0)
            fire_m = a[0] > 0.0
            p_m = jnp.where(fire_m, (jnp.clip(a[0], 0.0, 1.0) + 1.0) * 0.5, 0.0)
            fire_s = jnp.abs(a[1]) > 0.5
            direction = jnp.sign(a[1])
            p_s = jnp.where(fire_s, jnp.clip(jnp.abs(a[1]), 0.5, 1.0), 0.0)
        else:
            fire_m = action == 2
            p_m = fire_m.astype(jnp.float32)
            fire_s = (action == 1) | (action == 3)
            direction = (action - 2).astype(jnp.float32)
            p_s = fire_s.astype(jnp.float32)
        return p_m, p_s, direction

    def _advance(self, key, state: LanderState, p_m, p_s, direction, params, extra_force, reset=False,
                 dispersion=None):
        """Wind, engine impulses, one physics step. Returns (obs, state, terminated, game_over, asleep)."""
        model = self.model
        world = state.world
        bodies = world.bodies
        # 1. wind and turbulence, suspended while a leg touched the ground on the previous step
        wind_on = params.enable_wind & ~jnp.any(state.leg_contact)
        wind = jnp.where(wind_on, wave(state.wind_idx) * params.wind_power, 0.0)
        turb = jnp.where(wind_on, wave(state.torque_idx) * params.turbulence_power, 0.0)
        wind_idx = state.wind_idx + wind_on.astype(jnp.int32)
        torque_idx = state.torque_idx + wind_on.astype(jnp.int32)
        # 2. engine frame and dispersion (drawn every step)
        angle = bodies.angle[0]
        tip = jnp.stack([jnp.sin(angle), jnp.cos(angle)])
        side = jnp.stack([-tip[1], tip[0]])
        if dispersion is None:
            dispersion = jax.random.uniform(key, (2,), jnp.float32, -1.0, 1.0)
        d = dispersion / M.SCALE
        origin = physics2d.body_origin(model, bodies)[0]
        # 3. main engine: impulse at an offset point below the body origin
        mo = M.MAIN_ENGINE_Y_LOCATION + 2.0 * d[0]
        ox = tip[0] * mo + side[0] * d[1]
        oy = -tip[1] * mo - side[1] * d[1]
        imp = -M.MAIN_ENGINE_POWER * p_m * jnp.stack([ox, oy])
        bodies = physics2d.apply_impulse(model, bodies, 0, imp, origin + jnp.stack([ox, oy]))
        # 4. side engine (Gymnasium's x offset uses 17 px, its y offset SIDE_ENGINE_HEIGHT = 14 px)
        so = 3.0 * d[1] + direction * M.SIDE_ENGINE_AWAY
        ox = tip[0] * d[0] + side[0] * so
        oy = -tip[1] * d[0] - side[1] * so
        imp = -M.SIDE_ENGINE_POWER * p_s * jnp.stack([ox, oy])
        point = origin + jnp.stack([ox - tip[0] * 17.0 / M.SCALE, oy + tip[1] * M.SIDE_ENGINE_HEIGHT])
        bodies = physics2d.apply_impulse(model, bodies, 0, imp, point)
        # 5. physics
        force = jnp.zeros((3, 2), jnp.float32).at[0].set(jnp.stack([wind, 0.0]) + extra_force)
        torque = jnp.zeros((3,), jnp.float32).at[0].set(turb)
        ground = jnp.stack([jnp.asarray(M.CHUNK_X), state.terrain_y], -1)
        if reset:
            # the no-op step after creation: exact locked-leg velocity solve (see model.py), in free
            # flight: the lander starts at y = H, more than H/2 above the highest terrain point
            # (0.99 H/2), so no contact is possible and collision is skipped (same result, less work;
            # tests/test_physics2d.py checks this on random and worst-case terrain)
            world, info = physics2d.step(model, world.replace(bodies=bodies), ground, params.gravity, force, torque,
                                         projector=self._reset_projector,
                                         position_iterations=M.RESET_POSITION_ITERATIONS, free_flight=True)
        else:
            world, info = physics2d.step(model, world.replace(bodies=bodies), ground, params.gravity, force, torque)
        # Gymnasium's ContactDetector: one Box2D contact per (leg, ground edge) pair; BeginContact
        # sets the leg's flag, EndContact clears it -- even while the leg still touches another edge
        pairs = info["pair_touching"][1:3]
        began = jnp.any(pairs & ~state.leg_pairs, axis=1)
        ended = jnp.any(~pairs & state.leg_pairs, axis=1)
        leg_contact = jnp.where(ended, False, jnp.where(began, True, state.leg_contact))
        game_over = info["polygon_touching"][0]
        obs = observation(model, world, leg_contact)
        state = state.replace(world=world, leg_contact=leg_contact, leg_pairs=pairs, wind_idx=wind_idx, torque_idx=torque_idx,
                              main_power=p_m, side_power=p_s * direction)
        return obs, state, game_over, info["asleep"]

    def reset_env(self, key, params):
        k_terrain, k_push, k_wind, _ = jax.random.split(key, 4)  # 4: the streams of earlier versions
        pos, ang = self._start_bodies
        bodies = physics2d.bodies_from_origin(self.model, pos, ang)
        idx = jax.random.randint(k_wind, (2,), -9999, 9999, dtype=jnp.int32)
        state = LanderState(
            time=jnp.zeros((), jnp.int32),
            episode_return=jnp.zeros((), jnp.float32),
            world=physics2d.init_world(self.model, bodies),
            terrain_y=terrain(k_terrain),
            leg_contact=jnp.zeros((2,), bool),
            leg_pairs=jnp.zeros((2, M.CHUNKS - 1), bool),
            prev_shaping=jnp.zeros((), jnp.float32),
            wind_idx=idx[0],
            torque_idx=idx[1],
            main_power=jnp.zeros((), jnp.float32),
            side_power=jnp.zeros((), jnp.float32),
        )
        push = jax.random.uniform(k_push, (2,), jnp.float32, -M.INITIAL_RANDOM, M.INITIAL_RANDOM)
        zero = jnp.zeros((), jnp.float32)
        # engines are off in the no-op step, so their dispersion draw would only be multiplied by zero
        obs, state, _, _ = self._advance(None, state, zero, zero, zero, params, push, reset=True,
                                         dispersion=jnp.zeros((2,), jnp.float32))
        return obs, state.replace(prev_shaping=shaping(obs))

    def step_env(self, key, state, action, params):
        p_m, p_s, direction = self._engines(action)
        obs, new_state, game_over, asleep = self._advance(key, state, p_m, p_s, direction, params, jnp.zeros((2,)))
        shape = shaping(obs)
        reward = shape - state.prev_shaping - 0.30 * p_m - 0.03 * p_s
        crashed = game_over | (jnp.abs(obs[0]) >= 1.0)
        reward, terminated = assign_reward(reward, crashed, asleep)
        new_state = new_state.replace(prev_shaping=shape)
        info = {"crashed": crashed, "landed": asleep}
        return obs, new_state, reward, terminated, info

    def render(self, state, params=None) -> np.ndarray:
        from envs.lander.render import render_state

        return render_state(self, state)
