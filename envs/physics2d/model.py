"""Static description of a 2-D rigid-body world and the pytrees that hold its dynamic state.

The *model* (bodies' mass properties, polygon shapes, joints, solver settings) is plain Python /
numpy, frozen and hashable by identity: it is baked into the traced program as constants, so the
step compiles once per model. The *state* (`BodyState`, `WorldState`) is a ``flax.struct`` pytree
with fixed-size arrays, so a batch of worlds is a ``vmap`` away.

Conventions follow Box2D 2.3: a body's pose is its centre of mass ``com`` plus ``angle``; the body
origin (the point users place and observe) is ``com - R(angle) @ local_com``. Polygons are convex,
counter-clockwise, in the body-origin frame.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.physics2d.mass import polygon_mass
from envs.physics2d.vec import sincos


@dataclasses.dataclass(frozen=True)
class Polygon:
    """A convex polygon fixed to ``body`` (vertices CCW, body-origin frame, metres).

    ``sensor`` polygons only report touching (like a Box2D sensor / contact listener); they are not
    solved. Use it for shapes whose touch ends the episode anyway (e.g. a lander's hull).
    """

    body: int
    vertices: tuple
    density: float
    friction: float
    sensor: bool = False


@dataclasses.dataclass(frozen=True)
class RevoluteJoint:
    """A pin between ``body_a`` and ``body_b`` with an optional motor and angle limits (Box2D 2.3).

    Joint angle = angle_b - angle_a - reference_angle. The motor drives the relative angular
    velocity to ``motor_speed`` with at most ``max_motor_torque``.
    """

    body_a: int
    body_b: int
    local_anchor_a: tuple
    local_anchor_b: tuple
    reference_angle: float = 0.0
    lower: float = 0.0
    upper: float = 0.0
    enable_limit: bool = False
    enable_motor: bool = False
    motor_speed: float = 0.0
    max_motor_torque: float = 0.0


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """Time step, iteration counts and Box2D's tolerances (defaults = Box2D 2.3 b2Settings.h)."""

    dt: float = 1.0 / 50.0
    velocity_iterations: int = 8
    position_iterations: int = 3
    linear_slop: float = 0.005
    angular_slop: float = 2.0 / 180.0 * np.pi
    baumgarte: float = 0.2
    max_linear_correction: float = 0.2
    max_angular_correction: float = 8.0 / 180.0 * np.pi
    max_translation: float = 2.0
    max_rotation: float = 0.5 * np.pi
    contact_radius: float = 0.02  # polygon skin + edge skin (2 x b2_polygonRadius)
    ground_friction: float = 0.1
    linear_sleep_tolerance: float = 0.01
    angular_sleep_tolerance: float = 2.0 / 180.0 * np.pi
    time_to_sleep: float = 0.5
    warm_start: bool = True
    continuous: bool = True  # Box2D-style time of impact for solid slots hitting the ground
    toi_iterations: int = 4  # velocity passes of the per-body time-of-impact solve
    # run the time-of-impact passes as fused.per_world_fori_loops (one GPU kernel each, XLA loops on a
    # CPU) instead of unrolled (same arithmetic; a much smaller program for models with many solid
    # bodies: the walker's step compiles ~3x faster on CPU)
    toi_loop: bool = False
    # Box2D's TOI sub-step first pushes the body out at the time of impact (b2Island::SolveTOI: up to
    # 20 passes with b2_toiBaugarte 0.75, stopping at separation >= -1.5 slop), so it moves on from
    # Box2D's resting distance. 0 (the lander's setting) skips these passes.
    toi_position_iterations: int = 0
    toi_baumgarte: float = 0.75
    # Box2D's b2TimeOfImpact also reports a shape that starts the step closer than the TOI target
    # (+ 0.25 slop tolerance, but not overlapping) as touching at t = 0: the body goes back to its
    # start pose and is re-solved alone for the whole step. False (the lander's setting) skips this.
    toi_from_touching: bool = False
    # edge contacts' time of impact (physics2d/toi.py): distance samples per step, bisections of the
    # first interval under the target, and shapes tried per polygon (those nearest its swept box)
    toi_samples: int = 4
    toi_bisections: int = 8
    toi_candidates: int = 6
    # edge contacts: time-of-impact events per body and step (each searches the sweep left after the
    # previous one; Box2D allows up to 8 per contact). Each one is another copy of the search and solve.
    toi_events: int = 1
    # edge contacts: run a time-of-impact event's solve (its manifolds at the impact pose and its
    # passes) only when some world of the batch has an impact candidate (fused.batch_any: one branch
    # for the whole vmapped batch). Speed knob with the same results; off until timed on a GPU, where
    # the branch's predicate is read by the host
    toi_gate: bool = False
    # ground contacts of solid polygons: 0 = every polygon vertex against the polyline segment under it
    # (the lander's model); k > 0 = Box2D's edge-vs-polygon manifold (b2CollideEdgeAndPolygon, up to
    # two points, face A or face B) of each polygon against every ground edge as a separate Box2D edge
    # (no ghost vertices), the first k touching edges per polygon solved (Box2D's 2-point block solver)
    edge_contacts: int = 0
    # edge contacts: 0 = the velocity passes solve every manifold slot (edge_contacts per solid polygon),
    # touched or not; m > 0 = only the manifolds with points, packed in their order into m slots (the
    # same values while a world has at most m; one with more leaves out the last ones and says so in
    # the step's info["manifolds_crowded"]). Fewer slots make the fused velocity loop smaller
    velocity_manifolds: int = 0
    # edge contacts, experimental speed knob: the velocity passes solve each body's manifolds in a lane
    # of its own (``fused`` lanes: 4 GPU threads per world) after the joints; the same operations in the
    # same order per body, as a body's manifolds touch no other dynamic body. Needs 4 bodies with
    # manifolds, as many each (the walker's legs); the step's passes keep their form with
    # velocity_manifolds or another layout. The time of impact's velocity passes (manifolds alone, never
    # packed) take lanes too when they run as a loop (toi_loop), with or without velocity_manifolds
    velocity_lanes: bool = False
    # edge contacts, experimental speed knob: the position passes correct each body's contact points in a
    # lane of their own before the joints (the same layout as velocity_lanes, with or without
    # velocity_manifolds; the deepest separation is the minimum over the lanes)
    position_lanes: bool = False
    unroll: int = 1  # unroll factor of the solver-iteration loops (speed knob, no effect on results)
    # in the fused kernel, skip an edge contact point's position correction, and a body's time-of-impact
    # passes, in blocks of worlds none of which needs them (speed knob; results equal up to the sign of zero)
    skip_untouched: bool = True
    # stop the position passes once every world (of a kernel block, or of an XLA batch) is solved, as
    # Box2D's island solver breaks out of them (speed knob: a solved world's passes change nothing)
    position_early_stop: bool = True
    # how the iteration loops run: "auto" (one fused Pallas kernel per loop on GPU, XLA elsewhere),
    # "xla", "pallas" or "interpret" (the kernel through Pallas' interpreter); see physics2d/fused.py
    kernel: str = "auto"

    def __post_init__(self):
        if self.dt <= 0:
            raise ValueError(f"SolverConfig.dt must be > 0, got {self.dt}")
        if self.velocity_iterations < 1 or self.position_iterations < 0:
            raise ValueError(
                "SolverConfig needs velocity_iterations >= 1 and position_iterations >= 0, got "
                f"{self.velocity_iterations}, {self.position_iterations}"
            )
        if self.toi_position_iterations < 0:
            raise ValueError(f"SolverConfig.toi_position_iterations must be >= 0, got {self.toi_position_iterations}")
        for name, lo in (("toi_samples", 1), ("toi_bisections", 0), ("toi_candidates", 1), ("toi_events", 1)):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < lo:
                raise ValueError(f"SolverConfig.{name} must be an int >= {lo}, got {v!r}")
        if not isinstance(self.velocity_manifolds, int) or isinstance(self.velocity_manifolds, bool) \
                or self.velocity_manifolds < 0:
            raise ValueError(f"SolverConfig.velocity_manifolds must be an int >= 0, got {self.velocity_manifolds!r}")
        if self.edge_contacts < 0:
            raise ValueError(f"SolverConfig.edge_contacts must be >= 0, got {self.edge_contacts}")
        if self.unroll < 1:
            raise ValueError(f"SolverConfig.unroll must be >= 1, got {self.unroll}")
        if self.kernel not in ("auto", "xla", "pallas", "interpret"):
            raise ValueError(f"SolverConfig.kernel must be 'auto', 'xla', 'pallas' or 'interpret', got {self.kernel!r}")


@dataclasses.dataclass(frozen=True, eq=False)
class Model:
    """Bodies (mass from their polygons), joints, solver config; see ``make_model``."""

    num_bodies: int
    polygons: tuple
    joints: tuple
    config: SolverConfig
    mass: np.ndarray  # (B,)
    inertia: np.ndarray  # (B,) about the centre of mass
    local_com: np.ndarray  # (B, 2)
    # contact slots: one per vertex of every polygon, in polygon order
    slot_body: tuple
    slot_vertex: np.ndarray  # (V, 2) body-origin frame
    slot_friction: tuple
    slot_sensor: tuple
    slot_polygon: tuple

    @property
    def inv_mass(self) -> np.ndarray:
        return np.where(self.mass > 0, 1.0 / np.maximum(self.mass, 1e-30), 0.0)

    @property
    def inv_inertia(self) -> np.ndarray:
        return np.where(self.inertia > 0, 1.0 / np.maximum(self.inertia, 1e-30), 0.0)

    @property
    def num_slots(self) -> int:
        return len(self.slot_body)

    @property
    def edge_polygons(self) -> tuple:
        """Polygons solved against ground edges (``config.edge_contacts > 0``): the non-sensor ones."""
        return tuple(k for k, p in enumerate(self.polygons) if not p.sensor) if self.config.edge_contacts else ()

    @property
    def num_contacts(self) -> int:
        """Length of the solver's contact arrays: vertex slots, or 2 points x ``edge_contacts`` edges
        per solid polygon with edge contacts."""
        if self.config.edge_contacts:
            return 2 * self.config.edge_contacts * len(self.edge_polygons)
        return self.num_slots


def make_model(num_bodies: int, polygons, joints=(), config: Optional[SolverConfig] = None) -> Model:
    """Build a model; each body's mass, inertia and centre come from its polygons (Box2D formula)."""
    config = SolverConfig() if config is None else config
    polygons = tuple(polygons)
    joints = tuple(joints)
    for p in polygons:
        if not 0 <= p.body < num_bodies:
            raise ValueError(f"polygon body index {p.body} outside [0, {num_bodies})")
    for j in joints:
        if not (0 <= j.body_a < num_bodies and 0 <= j.body_b < num_bodies) or j.body_a == j.body_b:
            raise ValueError(f"joint bodies ({j.body_a}, {j.body_b}) invalid for {num_bodies} bodies")
        if j.enable_limit and j.lower > j.upper:
            raise ValueError(f"joint limits lower={j.lower} > upper={j.upper}")
    mass = np.zeros(num_bodies)
    first_moment = np.zeros((num_bodies, 2))
    inertia_origin = np.zeros(num_bodies)
    for p in polygons:
        m, c, i_origin = polygon_mass(np.asarray(p.vertices, np.float64), p.density)
        mass[p.body] += m
        first_moment[p.body] += m * c
        inertia_origin[p.body] += i_origin
    local_com = np.where(mass[:, None] > 0, first_moment / np.maximum(mass, 1e-30)[:, None], 0.0)
    inertia = inertia_origin - mass * np.sum(local_com**2, axis=1)
    slot_body, slot_vertex, slot_fric, slot_sensor, slot_poly = [], [], [], [], []
    for k, p in enumerate(polygons):
        for v in p.vertices:
            slot_body.append(p.body)
            slot_vertex.append(v)
            slot_fric.append(float(np.sqrt(p.friction * config.ground_friction)))  # Box2D mixing
            slot_sensor.append(p.sensor)
            slot_poly.append(k)
    return Model(
        num_bodies, polygons, joints, config, mass, inertia, local_com,
        tuple(slot_body), np.asarray(slot_vertex, np.float64).reshape(-1, 2), tuple(slot_fric),
        tuple(slot_sensor), tuple(slot_poly),
    )


@struct.dataclass
class BodyState:
    """Pose and velocity of every body (leading axis = body)."""

    com: jax.Array  # (B, 2) world position of the centre of mass
    angle: jax.Array  # (B,)
    vel: jax.Array  # (B, 2) linear velocity of the centre of mass
    omega: jax.Array  # (B,)


@struct.dataclass
class WorldState:
    """Everything the solver carries between steps."""

    bodies: BodyState
    sleep_time: jax.Array  # (B,) Box2D per-body sleep timers
    normal_impulse: jax.Array  # (V,) accumulated contact impulses, kept for warm starting
    tangent_impulse: jax.Array  # (V,)
    joint_impulse: jax.Array  # (J, 3) point (x, y) and limit impulses
    motor_impulse: jax.Array  # (J,)
    limit_state: jax.Array  # (J,) int32 joint limit state of the last step (see joint.py)
    touching: jax.Array  # (V,) bool: slot touched the ground at the start of the last step
    asleep: jax.Array  # () bool: the island fell asleep during the last step
    # edge contacts only (``SolverConfig.edge_contacts``; None otherwise, so other models' state is
    # unchanged): per contact point (round(1000 x edge start x), Box2D contact feature key), int32 (V, 2);
    # an impulse is warm started only when both match (Box2D matches points by feature per fixture pair)
    contact_key: Optional[jax.Array] = None


def body_origin(model: Model, bodies: BodyState) -> jax.Array:
    """World position of each body's origin (B, 2)."""
    lc = jnp.asarray(model.local_com, jnp.float32)
    s, c = sincos(bodies.angle)
    return bodies.com - jnp.stack([c * lc[:, 0] - s * lc[:, 1], s * lc[:, 0] + c * lc[:, 1]], -1)


def bodies_from_origin(model: Model, origin, angle, vel=None, omega=None) -> BodyState:
    """BodyState from body-origin positions (what a user places), COM computed from the model."""
    origin = jnp.asarray(origin, jnp.float32)
    angle = jnp.asarray(angle, jnp.float32)
    lc = jnp.asarray(model.local_com, jnp.float32)
    s, c = sincos(angle)
    com = origin + jnp.stack([c * lc[:, 0] - s * lc[:, 1], s * lc[:, 0] + c * lc[:, 1]], -1)
    vel = jnp.zeros_like(origin) if vel is None else jnp.asarray(vel, jnp.float32)
    omega = jnp.zeros_like(angle) if omega is None else jnp.asarray(omega, jnp.float32)
    return BodyState(com=com, angle=angle, vel=vel, omega=omega)


def init_world(model: Model, bodies: BodyState) -> WorldState:
    """A world at rest in the solver sense: no contacts, no accumulated impulses, awake."""
    v, j = model.num_contacts, len(model.joints)
    return WorldState(
        bodies=bodies,
        sleep_time=jnp.zeros((model.num_bodies,), jnp.float32),
        normal_impulse=jnp.zeros((v,), jnp.float32),
        tangent_impulse=jnp.zeros((v,), jnp.float32),
        joint_impulse=jnp.zeros((j, 3), jnp.float32),
        motor_impulse=jnp.zeros((j,), jnp.float32),
        limit_state=jnp.zeros((j,), jnp.int32),
        touching=jnp.zeros((v,), bool),
        asleep=jnp.zeros((), bool),
        contact_key=jnp.zeros((v, 2), jnp.int32) if model.config.edge_contacts else None,
    )
