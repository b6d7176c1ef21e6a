"""The lander's rigid bodies as a physics2d model: hull + two legs on motorised, limited pins.

Every number is Gymnasium LunarLander-v3's (docs/design.md §13.1, docs/lander.md "Model"), converted from pixels (/ SCALE).
Body 0 is the hull (a sensor: any touch of the ground ends the episode, so its contacts never need
solving), bodies 1 and 2 are the legs (Gymnasium's i = -1 and i = +1).
"""
from __future__ import annotations

import functools

import numpy as np

from envs import physics2d

FPS = 50
SCALE = 30.0
W = 600 / SCALE  # 20.0
H = 400 / SCALE  # 13.333
MAIN_ENGINE_POWER = 13.0
SIDE_ENGINE_POWER = 0.6
INITIAL_RANDOM = 1000.0
LANDER_POLY = ((-14, 17), (-17, 0), (-17, -10), (17, -10), (17, 0), (14, 17))
LEG_AWAY = 20 / SCALE
LEG_DOWN = 18 / SCALE
LEG_W, LEG_H = 2 / SCALE, 8 / SCALE
LEG_SPRING_TORQUE = 40.0
SIDE_ENGINE_HEIGHT = 14 / SCALE
SIDE_ENGINE_AWAY = 12 / SCALE
MAIN_ENGINE_Y_LOCATION = 4 / SCALE
CHUNKS = 11
HELIPAD_Y = H / 4
HELIPAD_X1 = W / (CHUNKS - 1) * (CHUNKS // 2 - 1)
HELIPAD_X2 = W / (CHUNKS - 1) * (CHUNKS // 2 + 1)
CHUNK_X = np.asarray([W / (CHUNKS - 1) * i for i in range(CHUNKS)], np.float32)
START = (W / 2, H)
LEG_SIDES = (-1, +1)
# Legs start where Gymnasium creates them: level with the hull, 0.05 rad tilted, off their anchors
# and outside their limits; the reset's no-op step snaps them (see RESET_POSITION_ITERATIONS).
LEG_START_TILT = 0.05
RESET_POSITION_ITERATIONS = 10

# Solver iterations. Box2D is called with 180 / 60 in Gymnasium; with warm starting and the 3x3
# joint block these counts reach statistical parity (docs/lander.md) at a fraction of the cost.
VELOCITY_ITERATIONS = 60
POSITION_ITERATIONS = 20


@functools.lru_cache(maxsize=None)
def lander_model(velocity_iterations: int = VELOCITY_ITERATIONS, position_iterations: int = POSITION_ITERATIONS,
                 unroll: int = 1, kernel: str = "auto") -> physics2d.Model:
    """The (cached, static) lander model for the given solver iteration counts."""
    hull = physics2d.Polygon(
        body=0, vertices=tuple((x / SCALE, y / SCALE) for x, y in LANDER_POLY), density=5.0, friction=0.1,
        sensor=True,
    )
    box = ((-LEG_W, -LEG_H), (LEG_W, -LEG_H), (LEG_W, LEG_H), (-LEG_W, LEG_H))
    legs = tuple(physics2d.Polygon(body=k + 1, vertices=box, density=1.0, friction=0.2) for k in range(2))
    joints = []
    for k, i in enumerate(LEG_SIDES):
        lower, upper = (0.4, 0.9) if i == -1 else (-0.9, -0.4)
        joints.append(physics2d.RevoluteJoint(
            body_a=0, body_b=k + 1, local_anchor_a=(0.0, 0.0), local_anchor_b=(i * LEG_AWAY, LEG_DOWN),
            # pybox2d's joint definition with bodies stores their creation angle difference (i * 0.05)
            # as the reference angle, so the limits act on (leg - hull - 0.05 i)
            reference_angle=i * LEG_START_TILT,
            lower=lower, upper=upper, enable_limit=True, enable_motor=True, motor_speed=0.3 * i,
            max_motor_torque=LEG_SPRING_TORQUE,
        ))
    cfg = physics2d.SolverConfig(
        dt=1.0 / FPS, velocity_iterations=velocity_iterations, position_iterations=position_iterations,
        ground_friction=0.1, unroll=unroll, kernel=kernel,
    )
    return physics2d.make_model(3, (hull,) + legs, tuple(joints), cfg)


def initial_pose():
    """Body-origin positions (3, 2) and angles (3,) at creation, exactly as Gymnasium places them."""
    pos = [START] + [(START[0] - i * LEG_AWAY, START[1]) for i in LEG_SIDES]
    ang = [0.0] + [i * LEG_START_TILT for i in LEG_SIDES]
    return np.asarray(pos, np.float32), np.asarray(ang, np.float32)


@functools.lru_cache(maxsize=None)
def reset_projector(velocity_iterations: int = VELOCITY_ITERATIONS, position_iterations: int = POSITION_ITERATIONS,
                    unroll: int = 1) -> np.ndarray:
    """Exact velocity solve of the reset's no-op step (legs pressed into their limits by the motors).

    Box2D needs its 180 velocity passes to converge on this first step (legs dragged at the wrong
    arm lengths); the locked-joint projection reproduces that result at the cost of a 9x9 mat-vec.
    """
    m = lander_model(velocity_iterations, position_iterations, unroll)
    pos, ang = initial_pose()
    lc = m.local_com
    com = pos + np.stack([np.cos(ang) * lc[:, 0] - np.sin(ang) * lc[:, 1],
                          np.sin(ang) * lc[:, 0] + np.cos(ang) * lc[:, 1]], -1)
    return physics2d.locked_velocity_projector(m, com, ang).astype(np.float32)
