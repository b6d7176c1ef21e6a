"""Gymnasium's BipedalWalker on ``envs.physics2d`` (Box2D-style solver in JAX) with DCD's level space.

A level is a ``WalkerParams`` (the MJX walker's: DCD's 8 parameters, terrain seed, replay flag,
Gymnasium-hardcore switch), with the same generator, named levels, samplers and edits (``ued``), so
every UED method runs on either walker unchanged. The rules (motors, lidar, observation, reward,
termination) are Gymnasium's; rigid-body dynamics are ``envs.physics2d``. See docs/bipedal.md.

Per env the state carries the level's terrain (polyline and obstacle boxes) and its height profile
(``max(polyline, box tops)`` sampled every ``TERRAIN_STEP / terrain_resolution``, the MJX walker's
``terrain.rasterise``). The legs collide, as in Gymnasium, with the polyline's edges and the obstacle
boxes as Box2D polygons in a window around the hull; the time of impact, the lidar and the hull test
read the profile, the same ground's upper outline.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import physics2d
from envs.physics2d import fused
from envs.physics2d.edge import first_true
from envs.physics2d.vec import rotate
from envs.bipedal import model as M
from envs.core import EnvState, Environment
from envs.walker import constants as C
from envs.walker import levels as LV
from envs.walker import lidar as L
from envs.walker import params as P
from envs.walker import terrain as T
from envs.walker.interface import WalkerInterface

KINDS = fused.MODES
CONTACTS = ("edge", "vertex")
OBSTACLES = ("polygon", "profile")


@dataclasses.dataclass(frozen=True)
class BipedalOptions:
    """Static configuration (changes the compiled program).

    velocity_iterations, position_iterations: solver passes per step (Gymnasium calls Box2D with 180 / 60).
    terrain_resolution: profile samples per TERRAIN_STEP (0.467 m); an obstacle's vertical face
                        becomes one sample wide (0.117 m at 4).
    window_columns:     terrain columns of the profile window the physics collides with (from 7
                        columns behind the hull); 16 columns = 7.5 m covers every leg pose.
    max_boxes:          obstacle box slots per level (the generator's; 64 covers DCD's FULL box).
    terrain_unroll:     columns per iteration of the terrain generator's 200-column loop (speed
                        only: the same terrain up to float32 rounding). Every auto-reset generates a terrain: on an H100 the
                        reset is about 5.3 of a step's 8.2 ms at a batch of 200 (docs/bipedal.md).
    terrain_kernel:     the terrain loop's ``physics2d.fused`` mode: "auto" runs it as one GPU kernel
                        on GPUs (the XLA loop elsewhere); speed only, the same terrain up to rounding.
    unroll, solver_kernel: physics2d's loop unroll (speed only) and ``SolverConfig.kernel``.
    light_reset:        the reset's physics step without edge manifolds (nothing touches at creation:
                        the passes solve the joints alone): the same result at a fraction of the
                        step's cost and compile (speed only).
    contacts:           "edge": the legs collide with the terrain as Box2D does with Gymnasium's
                        separate edge fixtures (``physics2d`` edge manifolds, ``terrain_edges``);
                        "vertex": each leg vertex against the profile polyline under it (the first
                        milestone's model).
    obstacles:          with edge contacts, what the legs touch: "polygon": Gymnasium's fixtures, the
                        polyline's edges (one per terrain column) and the obstacle boxes (stumps,
                        stair steps, pit walls) as Box2D polygons; "profile": the height profile's
                        edges (an obstacle's faces and top as profile segments; the model until
                        2026-12-02).
    continuous:         the time of impact (Box2D's ``continuousPhysics``, on in Gymnasium); off only
                        for diagnostics (``envs.bipedal.parity --no-toi``).
    toi_events:         time-of-impact events per leg and step (``SolverConfig.toi_events``; Box2D
                        allows up to 8 per contact); each is another copy of the search and its solve.
    toi_velocity_iterations: velocity passes of a leg's time-of-impact solve (``SolverConfig.toi_iterations``);
                        None: Box2D's, the step's ``velocity_iterations`` (``b2World::SolveTOI`` gives
                        its sub-step the step's velocity iterations and 20 position iterations). The
                        default stays 4: Box2D's 180 brings a lone shin's trajectory closer to pybox2d's
                        but not the walker's gait parity (docs/bipedal.md, "A lone shin thrown at a stump").
    velocity_manifolds: with edge contacts, the manifold slots of the velocity passes
                        (``SolverConfig.velocity_manifolds``): 0 solves all 12 (3 per leg) in every
                        pass, m packs the manifolds with points into m (exact while a world has at most
                        m; ``experiments.manifold_census`` never saw more than 6).
    window_boxes:       obstacle boxes the physics collides with per step ("polygon"): the first ones
                        that reach into the window (8 covers DCD's FULL space; ``tests/test_bipedal_env.py``).
    """

    velocity_iterations: int = M.VELOCITY_ITERATIONS
    position_iterations: int = M.POSITION_ITERATIONS
    terrain_resolution: int = 4
    window_columns: int = 16
    max_boxes: int = 64
    terrain_unroll: int = 1
    terrain_kernel: str = "auto"
    unroll: int = 1
    solver_kernel: str = "auto"
    contacts: str = "edge"
    light_reset: bool = True
    obstacles: str = "polygon"
    window_boxes: int = 8
    continuous: bool = True
    toi_events: int = 1
    toi_velocity_iterations: int | None = 4
    velocity_manifolds: int = 0

    def __post_init__(self):
        ints = dict(velocity_iterations=(1, 1000), position_iterations=(0, 1000), terrain_resolution=(1, 32),
                    window_columns=(12, 64), max_boxes=(8, 512), terrain_unroll=(1, 200), unroll=(1, 64),
                    window_boxes=(1, 64), toi_events=(1, 8), velocity_manifolds=(0, 4 * M.EDGE_CONTACTS))
        for name, (lo, hi) in ints.items():
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
                raise ValueError(f"BipedalOptions.{name} must be an int in [{lo}, {hi}], got {v!r}")
        for name in ("solver_kernel", "terrain_kernel"):
            if getattr(self, name) not in KINDS:
                raise ValueError(f"BipedalOptions.{name} must be one of {KINDS}, got {getattr(self, name)!r}")
        for name in ("light_reset", "continuous"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"BipedalOptions.{name} must be a bool, got {getattr(self, name)!r}")
        if self.contacts not in CONTACTS:
            raise ValueError(f"BipedalOptions.contacts must be one of {CONTACTS}, got {self.contacts!r}")
        if self.obstacles not in OBSTACLES:
            raise ValueError(f"BipedalOptions.obstacles must be one of {OBSTACLES}, got {self.obstacles!r}")
        v = self.toi_velocity_iterations
        if v is not None and (not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= 1000):
            raise ValueError(f"BipedalOptions.toi_velocity_iterations must be None (Box2D's: velocity_iterations) "
                             f"or an int in [1, 1000], got {v!r}")
        if self.window_boxes > self.max_boxes:
            raise ValueError(f"BipedalOptions.window_boxes must be <= max_boxes ({self.max_boxes}), got {self.window_boxes}")


BACK_COLUMNS = 7  # window columns behind the hull's column


def motor_targets(action: jax.Array):
    """Gymnasium's motor settings for an action (4,): Box2D motor speed SPEED * sign(a) and maximum
    torque 80 |a| clipped to [0, 80] (hips 4 rad/s, knees 6 rad/s). Returns (speed (4,), torque (4,))."""
    return jnp.asarray(M.JOINT_SPEEDS) * jnp.sign(action), C.MOTORS_TORQUE * jnp.clip(jnp.abs(action), 0.0, 1.0)


@struct.dataclass
class BipedalState(EnvState):
    world: physics2d.WorldState
    profile: jax.Array  # [grid.n] terrain heights (m) at the grid samples
    prev_shaping: jax.Array
    leg_contact: jax.Array  # (2,) bool, Gymnasium's lower legs' ground_contact after the last step
    leg_pairs: jax.Array  # (2, window_columns) bool, lower leg touching each terrain column's edge
    window: jax.Array  # int32 first terrain column of the window of the last step
    terrain: T.Terrain  # the level's polyline and boxes (the "polygon" obstacles' fixtures)
    leg_box_pairs: jax.Array  # (2, max_boxes) bool, lower leg touching each obstacle box


class BipedalWalker(WalkerInterface, Environment):
    """Gymnasium BipedalWalker (Box2D rules, physics2d solver) over DCD's level space."""

    name = "bipedal"
    ued = LV.UED  # the MJX walker's: Θ = FULL, edits, evaluation / test / named level sets

    def __init__(self, **options):
        fields = {f.name for f in dataclasses.fields(BipedalOptions)}
        unknown = set(options) - fields
        if unknown:
            raise ValueError(f"bipedal: unknown option(s) {sorted(unknown)}; valid: {sorted(fields)}")
        self.options = o = BipedalOptions(**options)
        self.model = M.walker_model(o.velocity_iterations, o.position_iterations, o.unroll, o.solver_kernel,
                                    M.EDGE_CONTACTS if o.contacts == "edge" else 0, o.continuous, o.toi_events,
                                    o.toi_velocity_iterations, o.velocity_manifolds if o.contacts == "edge" else 0)
        self.grid = T.make_grid(o.terrain_resolution)
        self._start = M.initial_pose()

    # spaces, params and the level's terrain: envs.walker.interface.WalkerInterface

    def ground_window(self, profile: jax.Array, hull_x: jax.Array):
        """The profile polyline the physics collides with: ``window_columns`` terrain columns from
        ``BACK_COLUMNS`` behind the hull's column (clamped to the grid). Returns (points (P, 2), first column)."""
        g, o = self.grid, self.options
        pad_left = int(round(-g.x_min / C.TERRAIN_STEP))
        n_cols = (g.n - 1) // o.terrain_resolution
        col = jnp.floor(hull_x / C.TERRAIN_STEP).astype(jnp.int32) - BACK_COLUMNS
        col = jnp.clip(col, -pad_left, n_cols - pad_left - o.window_columns)
        j0 = (col + pad_left) * o.terrain_resolution
        n = o.window_columns * o.terrain_resolution + 1
        xs = g.x_min + g.dx * (j0 + jnp.arange(n, dtype=jnp.int32)).astype(jnp.float32)
        return jnp.stack([xs, jax.lax.dynamic_slice(profile, (j0,), (n,))], -1), col

    def terrain_edges(self, ground: jax.Array):
        """The window polyline (P, 2) as separate Box2D edges, edge s starting at point s: a terrain
        column whose samples are collinear is one edge (Gymnasium's grass edge, TERRAIN_STEP long; its
        other segments invalid), any other column (an obstacle's face or top) one edge per sample
        segment. Returns (edges (P - 1, 2, 2), valid (P - 1,) bool)."""
        r = self.options.terrain_resolution
        seg = jnp.stack([ground[:-1], ground[1:]], 1)
        if r == 1:
            return seg, jnp.ones((seg.shape[0],), bool)
        start, end = ground[:-1:r], ground[r::r]  # (W, 2) column ends
        inner = ground[1:].reshape(-1, r, 2)[:, :-1]  # (W, r - 1, 2) samples inside each column
        frac = (inner[..., 0] - start[:, None, 0]) / (end[:, None, 0] - start[:, None, 0])
        chord_y = start[:, None, 1] + frac * (end[:, None, 1] - start[:, None, 1])
        straight = jnp.all(jnp.abs(inner[..., 1] - chord_y) < 1e-4, -1)  # (W,)
        s = jnp.arange(seg.shape[0])
        col, first = s // r, (s % r) == 0
        column_edge = jnp.stack([start[col], end[col]], 1)
        merged = straight[col]
        edges = jnp.where((merged & first)[:, None, None], column_edge, seg)
        return edges, ~merged | first

    def fixture_window(self, terrain: T.Terrain, ground: jax.Array, col: jax.Array):
        """Gymnasium's fixtures around the window: the polyline's edge of each window column (edge
        (x_c, y_c) -> (x_c+1, y_c+1); columns off the 199 edges invalid), and the first
        ``window_boxes`` obstacle boxes that reach into the window. Returns (edges (window_columns, 2, 2),
        valid (window_columns,), boxes (window_boxes, 4), box valid, box index (window_boxes,) int32
        into ``terrain.boxes``)."""
        o = self.options
        c = col + jnp.arange(o.window_columns)
        ci = jnp.clip(c, 0, C.TERRAIN_LENGTH - 2)
        edges = jnp.stack([jnp.stack([terrain.x[ci], terrain.y[ci]], -1),
                           jnp.stack([terrain.x[ci + 1], terrain.y[ci + 1]], -1)], 1)  # (W, 2, 2)
        valid = (c >= 0) & (c <= C.TERRAIN_LENGTH - 2)
        lo, hi = ground[0, 0], ground[-1, 0]
        reach = terrain.box_valid & (terrain.boxes[:, 1] >= lo) & (terrain.boxes[:, 0] <= hi)
        box_ok, index = first_true(reach, o.window_boxes)  # slot s: the s-th box in reach (empty: index 0)
        return edges, valid, terrain.boxes[index], box_ok, index

    # ------------------------------------------------------------------ observation / reward
    def hull_origin(self, world: physics2d.WorldState) -> jax.Array:
        return physics2d.body_origin(self.model, world.bodies)[M.HULL]

    def observation(self, world: physics2d.WorldState, leg_contact, profile) -> jax.Array:
        """Gymnasium's 24 floats: hull angle, spin, velocity; per leg hip/knee angle and speed, lower-leg
        contact; 10 lidar fractions from the hull origin."""
        b = world.bodies
        pos = self.hull_origin(world)
        joints = [self.model.joints[k] for k in M.MODEL_JOINT]  # Gymnasium's order
        ang = [b.angle[J.body_b] - b.angle[J.body_a] - J.reference_angle for J in joints]
        spd = [b.omega[J.body_b] - b.omega[J.body_a] for J in joints]
        c = leg_contact.astype(jnp.float32)
        head = [
            b.angle[M.HULL], 2.0 * b.omega[M.HULL] / C.FPS,
            0.3 * b.vel[M.HULL, 0] * (600 / C.SCALE) / C.FPS, 0.3 * b.vel[M.HULL, 1] * (400 / C.SCALE) / C.FPS,
            ang[0], spd[0] / C.SPEED_HIP, ang[1] + 1.0, spd[1] / C.SPEED_KNEE, c[0],
            ang[2], spd[2] / C.SPEED_HIP, ang[3] + 1.0, spd[3] / C.SPEED_KNEE, c[1],
        ]
        with jax.named_scope("observation"):
            return jnp.concatenate([jnp.stack(head), L.lidar(profile, self.grid, pos)]).astype(jnp.float32)

    def shaping(self, world: physics2d.WorldState) -> jax.Array:
        """Gymnasium's potential: 130 x / SCALE - 5 |hull angle| (x of the hull's body origin)."""
        return C.SHAPING_X * self.hull_origin(world)[0] - C.SHAPING_ANGLE * jnp.abs(world.bodies.angle[M.HULL])

    # ------------------------------------------------------------------ physics
    def physics(self, state: BipedalState, action: jax.Array, force=None, start_contacts: bool = True):
        """One Box2D-style step with Gymnasium's motor settings for ``action``; updates the contact flags.
        ``start_contacts=False`` (static): ``physics2d.step``'s, for a start pose clear of the ground.

        Returns (world, leg_contact, (leg_pairs, leg_box_pairs), window column, hull touched the ground)."""
        speed, torque = motor_targets(action)
        order = jnp.asarray(M.GYM_JOINT)  # to the model's (Box2D island) joint order
        speed, torque = speed[order], torque[order]
        o = self.options
        ground, col = self.ground_window(state.profile, self.hull_origin(state.world)[0])
        edges = valid = boxes = box_ok = None
        polygons = o.contacts == "edge" and o.obstacles == "polygon"
        if polygons:
            edges, valid, boxes, box_ok, box_index = self.fixture_window(state.terrain, ground, col)
        elif o.contacts == "edge" and start_contacts:
            edges, valid = self.terrain_edges(ground)
        world, info = physics2d.step(self.model, state.world, ground, C.GRAVITY, force=force,
                                     motor_speed=speed, max_motor_torque=torque, edges=edges, edge_valid=valid,
                                     start_contacts=start_contacts, boxes=boxes, box_valid=box_ok)
        # Gymnasium's ContactDetector: one Box2D contact per (lower leg, terrain edge) pair; BeginContact
        # sets the leg's flag, EndContact clears it even while the leg still touches another edge.
        pairs = info["pair_touching"][jnp.asarray([M.POLYGON[b] for b in M.LOWER])]  # per edge
        if not polygons:  # per profile segment: a column's edge covers its r segments
            pairs = pairs.reshape(2, self.options.window_columns, self.options.terrain_resolution).any(-1)
        shift = col - state.window  # the previous window, re-indexed to this one's columns
        idx = jnp.arange(self.options.window_columns) + shift
        ok = (idx >= 0) & (idx < self.options.window_columns)
        prev = jnp.where(ok[None], jnp.take(state.leg_pairs, jnp.clip(idx, 0, self.options.window_columns - 1), axis=1), False)
        began = jnp.any(pairs & ~prev, axis=1)
        ended = jnp.any(~pairs & prev, axis=1)
        box_pairs = state.leg_box_pairs
        if polygons:  # the same rule per (lower leg, obstacle box); boxes out of the window end their contact
            lower = info["box_touching"][jnp.asarray([M.POLYGON[b] for b in M.LOWER])] & box_ok[None]
            # per box: any window slot holding it touched (empty slots' lower is False)
            box_pairs = jnp.any(lower[:, :, None] & (box_index[:, None] == jnp.arange(box_pairs.shape[1]))[None], 1)
            began = began | jnp.any(box_pairs & ~state.leg_box_pairs, axis=1)
            ended = ended | jnp.any(~box_pairs & state.leg_box_pairs, axis=1)
        leg_contact = jnp.where(ended, False, jnp.where(began, True, state.leg_contact))
        return world, leg_contact, (pairs, box_pairs), col, info["polygon_touching"][M.POLYGON[M.HULL]]

    # ------------------------------------------------------------------ reset / step
    def reset_env(self, key: jax.Array, params: P.WalkerParams):
        """Gymnasium's reset: terrain, the walker created as Gymnasium places it, a random horizontal
        force U(-5, 5) on the hull, and one step with zero action (its observation is returned)."""
        k_terrain, k_push = jax.random.split(key)
        terrain = self.terrain(k_terrain, params)
        profile = T.rasterise(terrain, self.grid)
        pos, ang = self._start
        world = physics2d.init_world(self.model, physics2d.bodies_from_origin(self.model, pos, ang))
        state = BipedalState(
            time=jnp.int32(0), episode_return=jnp.float32(0.0), world=world, profile=profile,
            prev_shaping=jnp.float32(0.0), leg_contact=jnp.zeros((2,), bool),
            leg_pairs=jnp.zeros((2, self.options.window_columns), bool), window=jnp.int32(0),
            terrain=terrain, leg_box_pairs=jnp.zeros((2, self.options.max_boxes), bool))
        _, col = self.ground_window(profile, self.hull_origin(world)[0])
        state = state.replace(window=col)
        push = jax.random.uniform(k_push, (), jnp.float32, -C.INITIAL_RANDOM, C.INITIAL_RANDOM)
        force = jnp.zeros((M.NUM_BODIES, 2), jnp.float32).at[M.HULL, 0].set(push)
        # every level's first columns are flat at TERRAIN_HEIGHT and the feet are created 0.27 m above
        # them: no contact at the start pose (they land through the time of impact); the passes then
        # solve the joints alone (tests/test_bipedal_env.py checks this is the full step)
        world, contact, pairs, col, _ = self.physics(state, jnp.zeros((4,), jnp.float32), force,
                                                     start_contacts=not self.options.light_reset)
        state = state.replace(world=world, leg_contact=contact, leg_pairs=pairs[0], leg_box_pairs=pairs[1],
                              window=col, prev_shaping=self.shaping(world))
        return self.observation(world, contact, profile), state

    def step_env(self, key, state: BipedalState, action, params: P.WalkerParams):
        world, contact, pairs, col, hull_hit = self.physics(state, action)
        b = world.bodies
        finite = (jnp.all(jnp.isfinite(b.com)) & jnp.all(jnp.isfinite(b.vel)) & jnp.all(jnp.isfinite(b.angle))
                  & jnp.all(jnp.isfinite(b.omega)))
        world = jax.tree_util.tree_map(lambda n, o: jnp.where(finite, n, o), world, state.world)
        new = state.replace(world=world, leg_contact=contact, leg_pairs=pairs[0], leg_box_pairs=pairs[1], window=col)
        shaping = self.shaping(world)
        torque_cost = C.TORQUE_COST * jnp.sum(jnp.clip(jnp.abs(action), 0.0, 1.0))
        reward = shaping - state.prev_shaping - torque_cost
        x = self.hull_origin(world)[0]
        crash = hull_hit | (x < 0.0) | ~finite
        finish = x > C.FINISH_X
        reward = jnp.where(crash, C.CRASH_REWARD, reward)
        new = new.replace(prev_shaping=shaping)
        info = {"hull_contact": hull_hit, "finished": finish & ~crash, "x": x}
        return self.observation(world, contact, state.profile), new, reward, crash | finish, info

    # ------------------------------------------------------------------ rendering
    def body_polygons(self, state: BipedalState) -> dict:
        """One unbatched state's bodies as world polygons (numpy [k, 2]), keyed as the MJX walker's
        drawing keys them (``hull``, ``upper0``, ``lower0``, ``upper1``, ``lower1``)."""
        b = state.world.bodies
        origin = physics2d.body_origin(self.model, b)
        names = {M.HULL: "hull", **{M.UPPER[k]: f"upper{k}" for k in (0, 1)}, **{M.LOWER[k]: f"lower{k}" for k in (0, 1)}}
        return {names[p.body]: np.asarray(rotate(b.angle[p.body], jnp.asarray(p.vertices, jnp.float32)) + origin[p.body],
                                          np.float64)
                for p in self.model.polygons}

    def render(self, state: BipedalState, params=None, width: int = 400, height: int = 267) -> np.ndarray:
        """One unbatched state -> RGB frame [height, width, 3] uint8: the MJX walker's drawing, with each
        body where the solver holds it. Joints are soft constraints: after the reset step a knee is
        still 0.23 m apart (closed within a few dozen steps), which a skeleton rebuilt from the joint
        angles would hide. With Gymnasium's fixtures (``obstacles="polygon"``) the terrain drawn is
        theirs, the polyline and the obstacle boxes, not the profile the lidar reads."""
        from envs.walker.render import draw

        a = np.asarray(state.world.bodies.angle)
        pos = np.asarray(self.hull_origin(state.world))
        # the view and the lidar follow the hull; the joint angles are unused once polygons are given
        q = [pos[0], pos[1], a[0], a[1] - a[0], a[2] - a[1], a[3] - a[0], a[4] - a[3]]
        fixtures = {}
        if self.options.contacts == "edge" and self.options.obstacles == "polygon":  # what the legs touch
            t = state.terrain
            fixtures = dict(ground=(np.asarray(t.x), np.asarray(t.y)),
                            boxes=np.asarray(t.boxes) * np.asarray(t.box_valid)[:, None])
        return draw(np.asarray(q, np.float32), np.asarray(state.profile), self.grid, width, height,
                    polygons=self.body_polygons(state), **fixtures)
