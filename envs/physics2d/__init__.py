"""A small 2-D rigid-body solver in JAX (Box2D 2.3-style sequential impulses), fixed-size and vmappable.

Bodies carry convex polygons; contacts are polygon vertices against a static height-field polyline,
or (``SolverConfig.edge_contacts``) Box2D's edge-vs-polygon manifolds against separate ground edges
and polygon-vs-polygon manifolds against static box obstacles (with friction, no restitution, warm starting and non-linear position correction); revolute joints
have motors and angle limits; Box2D-style sleep timers say when the island comes to rest. Nothing
here knows about any particular game: environments build a ``Model`` and call ``step``.
"""
from envs.physics2d.locked import locked_velocity_projector
from envs.physics2d.mass import polygon_mass
from envs.physics2d.model import (
    BodyState,
    Model,
    Polygon,
    RevoluteJoint,
    SolverConfig,
    WorldState,
    bodies_from_origin,
    body_origin,
    init_world,
    make_model,
)
from envs.physics2d.world import apply_impulse, collide, slot_points, step

__all__ = [
    "BodyState", "Model", "Polygon", "RevoluteJoint", "SolverConfig", "WorldState", "apply_impulse",
    "bodies_from_origin", "body_origin", "collide", "init_world", "locked_velocity_projector", "make_model", "polygon_mass",
    "slot_points", "step",
]
