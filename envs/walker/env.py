"""Parametric BipedalWalker on MuJoCo MJX (DCD's 8-parameter level space).

Per env, the state carries the level's terrain profile (the heightfield samples), so the compiled
step is shared by every level: ``step_env`` writes the env's heightfield data and its vertical
offset into the MJX model (``tree_replace`` under ``vmap``) and runs ``substeps`` physics steps with
a velocity-servo motor torque recomputed every substep. ``reset_env`` generates a terrain (a short
``lax.scan``, see ``terrain.py``), places the walker and computes the first observation analytically
(no physics step), so the auto-reset that the base class evaluates at every step stays cheap.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from envs.core import EnvState, Environment
from envs.walker import constants as C
from envs.walker import levels as LV
from envs.walker import lidar as L
from envs.walker import model as M
from envs.walker import params as P
from envs.walker import terrain as T
from envs.walker.interface import WalkerInterface
from envs.walker.mjx_import import import_mjx
from envs.walker.options import WalkerOptions

mjx = import_mjx()  # MJX without its "Failed to import warp" lines

_SPEEDS = np.array([C.SPEED_HIP, C.SPEED_KNEE, C.SPEED_HIP, C.SPEED_KNEE], np.float32)


@struct.dataclass
class WalkerState(EnvState):
    qpos: jax.Array  # [7] x, z, angle, hip0, knee0, hip1, knee1
    qvel: jax.Array  # [7]
    qacc_warmstart: jax.Array  # [7] Newton warm start carried between control steps
    profile: jax.Array  # [grid.n] terrain heights (m) at the grid samples
    z_base: jax.Array  # heightfield base height for this level (m)
    prev_shaping: jax.Array
    contact: jax.Array  # [2] lower-leg ground contact (float 0/1)
    clipped: jax.Array  # bool: terrain exceeded the heightfield's vertical span (clipped)


class BipedalWalker(WalkerInterface, Environment):
    """DCD's parametric BipedalWalker on MJX. Options: see ``WalkerOptions`` (all static)."""

    name = "walker"
    ued = LV.UED  # Θ = FULL, ladder evaluation set, test sets A/B, named levels (envs/walker/levels.py)

    def __init__(self, **options):
        fields = {f.name for f in dataclasses.fields(WalkerOptions)}
        unknown = set(options) - fields
        if unknown:
            raise ValueError(f"walker: unknown option(s) {sorted(unknown)}; valid: {sorted(fields)}")
        self.options = WalkerOptions(**options)
        self.grid = T.make_grid(self.options.terrain_resolution)
        self.mj_model = M.build(self.options, self.grid)
        self.mjx_model = mjx.put_model(self.mj_model, impl="jax")
        self._data0 = mjx.make_data(self.mjx_model)
        self._terrain_geom = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_GEOM, "terrain")
        self._lower_geoms = np.array([mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_GEOM, f"lower{i}") for i in (0, 1)])
        self._qpos0 = jnp.asarray(M.start_qpos(), jnp.float32)
        self._push_dv = C.INITIAL_RANDOM * C.CONTROL_DT / M.total_mass()
        self._geom_pos0 = jnp.asarray(self.mj_model.geom_pos, jnp.float32)

    # spaces, params and the level's terrain: envs.walker.interface.WalkerInterface

    def _profile(self, terrain: T.Terrain):
        prof = T.rasterise(terrain, self.grid)
        z_base = jnp.min(prof) - 0.5
        clipped = (jnp.max(prof) - z_base) > self.options.z_span
        return prof, z_base, clipped

    def model_for(self, state: WalkerState):
        """The MJX model with this env's heightfield (call under vmap for a batch)."""
        data = jnp.clip((state.profile - state.z_base) / self.options.z_span, 0.0, 1.0)
        gpos = self._geom_pos0.at[self._terrain_geom, 2].set(state.z_base)
        return self.mjx_model.tree_replace({"hfield_data": jnp.concatenate([data, data]), "geom_pos": gpos})

    # ------------------------------------------------------------------ observation / reward
    def _obs(self, state: WalkerState) -> jax.Array:
        q, v = state.qpos, state.qvel
        lid = L.lidar(state.profile, self.grid, q[:2])
        return jnp.concatenate(
            [
                jnp.stack([q[2], 2.0 * v[2] / C.FPS, 0.3 * v[0] * (600 / C.SCALE) / C.FPS, 0.3 * v[1] * (400 / C.SCALE) / C.FPS]),
                jnp.stack([q[3], v[3] / C.SPEED_HIP, q[4] + 1.0, v[4] / C.SPEED_KNEE, state.contact[0]]),
                jnp.stack([q[5], v[5] / C.SPEED_HIP, q[6] + 1.0, v[6] / C.SPEED_KNEE, state.contact[1]]),
                lid,
            ]
        ).astype(jnp.float32)

    @staticmethod
    def shaping(qpos: jax.Array) -> jax.Array:
        """Gymnasium's potential: 130 x / SCALE - 5 |angle|."""
        return C.SHAPING_X * qpos[0] - C.SHAPING_ANGLE * jnp.abs(qpos[2])

    # ------------------------------------------------------------------ reset / step
    def reset_env(self, key: jax.Array, params: P.WalkerParams):
        k_terrain, k_push = jax.random.split(key)
        prof, z_base, clipped = self._profile(self.terrain(k_terrain, params))
        qpos = self._qpos0
        qvel = jnp.zeros(7, jnp.float32).at[0].set(jax.random.uniform(k_push, (), minval=-1.0, maxval=1.0) * self._push_dv)
        state = WalkerState(
            time=jnp.int32(0),
            episode_return=jnp.float32(0.0),
            qpos=qpos,
            qvel=qvel,
            qacc_warmstart=jnp.zeros(7, jnp.float32),
            profile=prof,
            z_base=z_base,
            prev_shaping=self.shaping(qpos),
            contact=jnp.zeros(2, jnp.float32),
            clipped=clipped,
        )
        return self._obs(state), state

    def physics(self, state: WalkerState, action: jax.Array):
        """``substeps`` MJX steps with the velocity-servo torque; returns the final mjx.Data."""
        m = self.model_for(state)
        d = self._data0.replace(qpos=state.qpos, qvel=state.qvel, qacc_warmstart=state.qacc_warmstart)
        target = jnp.asarray(_SPEEDS) * jnp.sign(action)
        limit = C.MOTORS_TORQUE * jnp.clip(jnp.abs(action), 0.0, 1.0)
        kv = self.options.kv

        def sub(d, _):
            tau = jnp.clip(kv * (target - d.qvel[3:]), -limit, limit)
            return mjx.step(m, d.replace(ctrl=tau)), None

        # MJX's matrix products at the configured precision: on GPUs JAX's default is TF32
        with jax.default_matmul_precision(self.options.matmul_precision):
            if self.options.unroll_substeps:
                for _ in range(self.options.substeps):
                    d, _ = sub(d, None)
            else:
                d, _ = jax.lax.scan(sub, d, None, length=self.options.substeps)
        return d

    def step_env(self, key, state: WalkerState, action, params: P.WalkerParams):
        d = self.physics(state, action)
        qpos, qvel = d.qpos, d.qvel
        finite = jnp.all(jnp.isfinite(qpos)) & jnp.all(jnp.isfinite(qvel))
        qpos = jnp.where(finite, qpos, state.qpos)
        qvel = jnp.where(finite, qvel, 0.0)
        warm = jnp.where(finite, d.qacc_warmstart, 0.0)

        con = d._impl.contact
        touching = con.dist <= self.options.contact_threshold
        contact = jnp.stack([jnp.any(touching & (con.geom[:, 1] == g)) for g in self._lower_geoms]).astype(jnp.float32)
        contact = jnp.where(finite, contact, 0.0)

        new = state.replace(qpos=qpos, qvel=qvel, qacc_warmstart=warm, contact=contact)
        shaping = self.shaping(qpos)
        torque_cost = C.TORQUE_COST * jnp.sum(jnp.clip(jnp.abs(action), 0.0, 1.0))
        reward = shaping - state.prev_shaping - torque_cost
        hull_hit = L.hull_touches_ground(state.profile, self.grid, qpos[0], qpos[1], qpos[2])
        crash = hull_hit | (qpos[0] < 0.0) | ~finite
        finish = qpos[0] > C.FINISH_X
        reward = jnp.where(crash, C.CRASH_REWARD, reward)
        new = new.replace(prev_shaping=shaping)
        info = {"hull_contact": hull_hit, "finished": finish & ~crash, "x": qpos[0], "terrain_clipped": state.clipped}
        return self._obs(new), new, reward, crash | finish, info

    # ------------------------------------------------------------------ rendering
    def render(self, state: WalkerState, params=None, width: int = 400, height: int = 267) -> np.ndarray:
        """One unbatched state -> RGB frame [height, width, 3] uint8 (PIL, host side)."""
        from envs.walker.render import draw

        return draw(np.asarray(state.qpos), np.asarray(state.profile), self.grid, width, height)
