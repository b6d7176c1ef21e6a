"""The walker's rigid bodies as a physics2d model: hull + two two-segment legs on motorised, limited pins.

Every number is Gymnasium BipedalWalker's (``envs.walker.constants``, in metres = pixels / SCALE).
Bodies: 0 hull, 1 upper leg (Gymnasium's i = -1), 2 its lower leg, 3 upper leg (i = +1), 4 its lower
leg. Gymnasium's joints are hip -1, knee -1, hip +1, knee +1 (actions and observations use that
order). The solver, though, runs Gauss-Seidel passes in the order Box2D's island builder visits the
walker (a depth-first search from the last body created, with its lists newest first): bodies
4, 3, 0, 1, 2 and joints knee +1, hip +1, hip -1, knee -1. Position passes that close a joint gap
(the reset step leaves one) end in an order-dependent pose, so the model lists polygons and joints in
that order; ``GYM_JOINT`` / ``MODEL_JOINT`` and ``POLYGON`` map between the orders.
The hull is a sensor: any touch of the ground ends the episode (Gymnasium's ``game_over``), so its
contacts never need solving. The legs collide with the ground only (Gymnasium's category/mask bits
keep them from touching each other and the hull).
"""
from __future__ import annotations

import functools

import numpy as np

from envs import physics2d
from envs.walker import constants as C

HULL = 0
UPPER = (1, 3)
LOWER = (2, 4)
LEG_SIDES = (-1, +1)
LEG_START_TILT = 0.05  # legs are created at angle i * 0.05
NUM_BODIES = 5
ISLAND_BODIES = (4, 3, 0, 1, 2)  # Box2D's island order: polygon k belongs to body ISLAND_BODIES[k]
POLYGON = {b: k for k, b in enumerate(ISLAND_BODIES)}  # body -> its polygon index
GYM_JOINT = (3, 2, 0, 1)  # model joint k is Gymnasium's joint GYM_JOINT[k]
MODEL_JOINT = tuple(GYM_JOINT.index(g) for g in range(4))  # Gymnasium's joint g is model joint MODEL_JOINT[g]

# Box2D's iterations as Gymnasium calls it: world.Step(1/FPS, 6 * 30, 2 * 30)
VELOCITY_ITERATIONS = 6 * 30
POSITION_ITERATIONS = 2 * 30

#: ground edges per leg segment solved with Box2D's edge-vs-polygon manifold (a shin spans at most
#: three 0.467 m terrain edges at the tilts the gait reaches; more touching edges are dropped)
EDGE_CONTACTS = 3

#: per joint (Gymnasium's order): motor speed of a full action, Box2D's SetMotorSpeed(SPEED * sign(a))
JOINT_SPEEDS = np.array([C.SPEED_HIP, C.SPEED_KNEE, C.SPEED_HIP, C.SPEED_KNEE], np.float32)

INIT_X = C.TERRAIN_STEP * C.TERRAIN_STARTPAD / 2
INIT_Y = C.TERRAIN_HEIGHT + 2 * C.LEG_H


def _box(hx: float, hy: float) -> tuple:
    return ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))  # Box2D's SetAsBox order (CCW)


@functools.lru_cache(maxsize=None)
def walker_model(velocity_iterations: int = VELOCITY_ITERATIONS, position_iterations: int = POSITION_ITERATIONS,
                 unroll: int = 1, kernel: str = "auto", edge_contacts: int = 0,
                 continuous: bool = True, toi_events: int = 1, toi_iterations: int | None = 4,
                 velocity_manifolds: int = 0) -> physics2d.Model:
    """The (cached, static) walker model for the given solver iteration counts; ``edge_contacts``:
    ``physics2d.SolverConfig.edge_contacts`` (0: leg vertices against the polyline); ``continuous``:
    the time of impact (Box2D's ``continuousPhysics``); ``toi_iterations``: the velocity passes of a
    time-of-impact solve (``BipedalOptions.toi_velocity_iterations``), None for Box2D's
    (``velocity_iterations``, as ``b2World::SolveTOI``); ``velocity_manifolds``: ``SolverConfig``'s."""
    # Gymnasium lists the hull clockwise; Box2D reorders any convex polygon counter-clockwise
    hull = physics2d.Polygon(body=HULL, vertices=tuple((x / C.SCALE, y / C.SCALE) for x, y in reversed(C.HULL_POLY)),
                             density=C.HULL_DENSITY, friction=C.HULL_FRICTION, sensor=True)
    polygons, joints = {HULL: hull}, []
    for k, i in enumerate(LEG_SIDES):
        up, lo = UPPER[k], LOWER[k]
        polygons[up] = physics2d.Polygon(up, _box(C.LEG_W / 2, C.LEG_H / 2), density=1.0, friction=C.LEG_FRICTION)
        polygons[lo] = physics2d.Polygon(lo, _box(0.8 * C.LEG_W / 2, C.LEG_H / 2), density=1.0, friction=C.LEG_FRICTION)
        # pybox2d's joint definition with bodies stores their creation angle difference as the
        # reference angle: i * 0.05 at the hip (hull at 0, leg at i * 0.05), 0 at the knee
        joints.append(physics2d.RevoluteJoint(
            body_a=HULL, body_b=up, local_anchor_a=(0.0, C.LEG_DOWN), local_anchor_b=(0.0, C.LEG_H / 2),
            reference_angle=i * LEG_START_TILT, lower=C.HIP_RANGE[0], upper=C.HIP_RANGE[1], enable_limit=True,
            enable_motor=True, motor_speed=float(i), max_motor_torque=C.MOTORS_TORQUE))
        joints.append(physics2d.RevoluteJoint(
            body_a=up, body_b=lo, local_anchor_a=(0.0, -C.LEG_H / 2), local_anchor_b=(0.0, C.LEG_H / 2),
            reference_angle=0.0, lower=C.KNEE_RANGE[0], upper=C.KNEE_RANGE[1], enable_limit=True,
            enable_motor=True, motor_speed=1.0, max_motor_torque=C.MOTORS_TORQUE))
    polygons = tuple(polygons[b] for b in ISLAND_BODIES)
    joints = tuple(joints[g] for g in GYM_JOINT)
    cfg = physics2d.SolverConfig(dt=C.CONTROL_DT, velocity_iterations=velocity_iterations,
                                 position_iterations=position_iterations, ground_friction=C.TERRAIN_FRICTION,
                                 unroll=unroll, kernel=kernel, toi_loop=True, toi_position_iterations=20,
                                 toi_from_touching=True, edge_contacts=edge_contacts, continuous=continuous,
                                 toi_events=toi_events, velocity_manifolds=velocity_manifolds,
                                 toi_iterations=velocity_iterations if toi_iterations is None else toi_iterations)
    return physics2d.make_model(NUM_BODIES, tuple(polygons), tuple(joints), cfg)


def initial_pose():
    """Body-origin positions (5, 2) and angles (5,) at creation, exactly as Gymnasium places them.

    Gymnasium puts the upper legs' centres at ``init_y - LEG_H / 2 - LEG_DOWN`` (LEG_DOWN < 0), so
    their top anchors sit 2 |LEG_DOWN| = 0.53 m above the hips; the first (reset) step's position
    iterations pull the legs down and the hull up, as Box2D does.
    """
    pos = [(INIT_X, INIT_Y)]
    ang = [0.0]
    for i in LEG_SIDES:
        pos += [(INIT_X, INIT_Y - C.LEG_H / 2 - C.LEG_DOWN), (INIT_X, INIT_Y - C.LEG_H * 3 / 2 - C.LEG_DOWN)]
        ang += [i * LEG_START_TILT, i * LEG_START_TILT]
    return np.asarray(pos, np.float32), np.asarray(ang, np.float32)
