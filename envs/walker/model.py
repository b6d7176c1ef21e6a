"""The walker's MJCF model (built as a string from the Box2D constants) and its start pose.

Planar root: slide x, slide z, hinge about (0, -1, 0) so angles are CCW-positive as in Box2D.
Masses and inertias are Box2D's (set explicitly; geoms carry no mass). The hull has no collision
geom: hull-ground contact only ends the episode, so it is tested analytically against the terrain
profile (saves the most expensive heightfield pair). Legs are capsules (MJX collides heightfields
with capsules cheaper than with boxes; the rounded foot is the main geometric deviation), colliding
only with the terrain through explicit <pair>s with Box2D's sqrt(f1 f2) friction.
"""
from __future__ import annotations

import math

import mujoco
import numpy as np

from envs.walker import constants as C
from envs.walker.options import WalkerOptions
from envs.walker.terrain import Grid

HFIELD_HALF_Y = 0.5
HFIELD_BASE = 1.0
UPPER_R = C.LEG_W / 2  # capsule radius = half the box width
LOWER_R = 0.8 * C.LEG_W / 2
START_HIP = (-0.05, 0.05)  # Gymnasium: leg i in (-1, +1) starts at angle 0.05 i
START_KNEE = -0.1  # consistent with the knee limit (Box2D starts at 0, violating it by 0.1)
START_CLEARANCE = 0.005  # feet start this far above the flat start pad


def hull_centroid_inertia():
    """Box2D hull polygon (density 5): mass, centroid and central inertia about the normal."""
    p = np.asarray(C.HULL_POLY, np.float64)[::-1] / C.SCALE  # counter-clockwise
    x, y = p[:, 0], p[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cr = x * y1 - x1 * y
    area = cr.sum() / 2
    cx = ((x + x1) * cr).sum() / (6 * area)
    cy = ((y + y1) * cr).sum() / (6 * area)
    i_origin = ((x * x + x * x1 + x1 * x1 + y * y + y * y1 + y1 * y1) * cr).sum() / 12
    mass = C.HULL_DENSITY * area
    inertia = C.HULL_DENSITY * i_origin - mass * (cx * cx + cy * cy)
    return mass, (cx, cy), inertia


def leg_drop(hip: float, knee: float, r: float = LOWER_R) -> float:
    """Vertical distance from the hull origin down to the lowest point of a leg."""
    a_up, a_low = hip, hip + knee
    return -C.LEG_DOWN + C.LEG_H * math.cos(a_up) + (C.LEG_H - r) * math.cos(a_low) + r


def start_qpos() -> np.ndarray:
    """Start pose [x, z, angle, hip0, knee0, hip1, knee1]; feet just above the flat pad."""
    drop = max(leg_drop(h, START_KNEE) for h in START_HIP)
    x0 = C.TERRAIN_STEP * C.TERRAIN_STARTPAD / 2
    z0 = C.TERRAIN_HEIGHT + drop + START_CLEARANCE
    return np.array([x0, z0, 0.0, START_HIP[0], START_KNEE, START_HIP[1], START_KNEE], np.float64)


def total_mass() -> float:
    return hull_centroid_inertia()[0] + 2 * (C.UPPER_LEG_MASS + C.LOWER_LEG_MASS)


def mjcf(opts: WalkerOptions, grid: Grid) -> str:
    """MJCF text of the walker on a 2 x grid.n heightfield (data filled in per env)."""
    hm, (hcx, hcy), hI = hull_centroid_inertia()
    half_x = (grid.n - 1) * grid.dx / 2
    xc = grid.x_min + half_x
    f_leg = math.sqrt(C.LEG_FRICTION * C.TERRAIN_FRICTION)
    L = C.LEG_H

    def leg(i: int) -> str:
        rng_h = f"{C.HIP_RANGE[0]} {C.HIP_RANGE[1]}"
        rng_k = f"{C.KNEE_RANGE[0]} {C.KNEE_RANGE[1]}"
        return f"""
      <body name="upper{i}" pos="0 0 {C.LEG_DOWN}">
        <joint name="hip{i}" type="hinge" axis="0 -1 0" range="{rng_h}" limited="true"/>
        <inertial pos="0 0 {-L / 2}" mass="{C.UPPER_LEG_MASS}" diaginertia="{C.UPPER_LEG_INERTIA} {C.UPPER_LEG_INERTIA} {C.UPPER_LEG_INERTIA}"/>
        <geom name="upper{i}" type="capsule" fromto="0 0 {-UPPER_R} 0 0 {-(L - UPPER_R)}" size="{UPPER_R}" contype="0" conaffinity="0" rgba=".6 .3 .5 1"/>
        <body name="lower{i}" pos="0 0 {-L}">
          <joint name="knee{i}" type="hinge" axis="0 -1 0" range="{rng_k}" limited="true"/>
          <inertial pos="0 0 {-L / 2}" mass="{C.LOWER_LEG_MASS}" diaginertia="{C.LOWER_LEG_INERTIA} {C.LOWER_LEG_INERTIA} {C.LOWER_LEG_INERTIA}"/>
          <geom name="lower{i}" type="capsule" fromto="0 0 {-LOWER_R} 0 0 {-(L - LOWER_R)}" size="{LOWER_R}" contype="0" conaffinity="0" rgba=".6 .3 .5 1"/>
        </body>
      </body>"""

    pairs = [f'<pair geom1="terrain" geom2="lower{i}" condim="3" friction="{f_leg} {f_leg} 0.005 0.0001 0.0001"/>' for i in (0, 1)]
    if opts.collide_upper_legs:
        pairs += [f'<pair geom1="terrain" geom2="upper{i}" condim="3" friction="{f_leg} {f_leg} 0.005 0.0001 0.0001"/>' for i in (0, 1)]
    motors = "\n    ".join(f'<motor name="{j}" joint="{j}" gear="1" ctrllimited="false"/>' for j in ("hip0", "knee0", "hip1", "knee1"))
    return f"""<mujoco model="bipedal_walker">
  <compiler angle="radian" inertiafromgeom="false" autolimits="true"/>
  <option timestep="{opts.timestep}" gravity="0 0 {C.GRAVITY}" iterations="{opts.solver_iterations}"
          ls_iterations="{opts.ls_iterations}" solver="Newton" integrator="Euler" cone="pyramidal">
    <flag eulerdamp="disable"/>
  </option>
  <asset>
    <hfield name="terrain" nrow="2" ncol="{grid.n}" size="{half_x} {HFIELD_HALF_Y} {opts.z_span} {HFIELD_BASE}"/>
  </asset>
  <worldbody>
    <geom name="terrain" type="hfield" hfield="terrain" pos="{xc} 0 0" contype="0" conaffinity="0"/>
    <body name="hull" pos="0 0 0">
      <joint name="rootx" type="slide" axis="1 0 0"/>
      <joint name="rootz" type="slide" axis="0 0 1"/>
      <joint name="rooty" type="hinge" axis="0 -1 0"/>
      <inertial pos="{hcx} 0 {hcy}" mass="{hm}" diaginertia="{hI} {hI} {hI}"/>
      <geom name="hull" type="box" size="{34 / C.SCALE} 0.1 {8.5 / C.SCALE}" pos="{2 / C.SCALE} 0 {0.5 / C.SCALE}" contype="0" conaffinity="0" rgba=".5 .4 .9 1"/>{leg(0)}{leg(1)}
    </body>
  </worldbody>
  <contact>
    {chr(10).join('    ' + p for p in pairs).strip()}
  </contact>
  <actuator>
    {motors}
  </actuator>
</mujoco>
"""


def build(opts: WalkerOptions, grid: Grid) -> mujoco.MjModel:
    """Compile the MJCF into an MjModel (heightfield data zero until set per env)."""
    return mujoco.MjModel.from_xml_string(mjcf(opts, grid))
