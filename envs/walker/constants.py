"""Box2D BipedalWalker constants (Gymnasium 1.4.0 / DCD), in metres (Box2D units = pixels / SCALE).

Kept in one module so the terrain generator, the MJCF builder, the lidar and the renderer agree.
"""
from __future__ import annotations

SCALE = 30.0
FPS = 50
CONTROL_DT = 1.0 / FPS

TERRAIN_STEP = 14.0 / SCALE  # 0.4667: width of one terrain column
TERRAIN_LENGTH = 200  # columns
TERRAIN_HEIGHT = 400.0 / SCALE / 4.0  # 3.333: y0, the resting ground height
TERRAIN_GRASS = 10  # grass stretches last randint(GRASS/2, GRASS) = 5..9 columns
TERRAIN_STARTPAD = 20  # flat columns before the first obstacle
FINISH_X = (TERRAIN_LENGTH - TERRAIN_GRASS) * TERRAIN_STEP  # 88.67: x beyond which the episode ends

# Terrain state machine codes (fixed codes; DCD numbers the present types consecutively, which only
# matters for the uniform choice among present types, done here with a mask).
GRASS, STUMP, STAIRS, PIT = 0, 1, 2, 3
STAIR_WIDTH = 4  # DCD's exclusive-bound randint(4, 5)
MAX_STAIR_STEPS = 9  # FULL range of the stair_steps parameter; randint(n) builds at most n-1 steps
PIT_DEPTH = 4  # pit floors lie 4 steps below the rim

# Thresholds on the high value of each (low, high) pair below which the obstacle type is absent.
STUMP_THRESHOLD = 0.2
PIT_THRESHOLD = 0.8
STAIR_THRESHOLD = 0.2

# Morphology (Gymnasium BipedalWalker).
HULL_POLY = ((-30, 9), (6, 9), (34, 1), (34, -8), (-30, -8))  # pixels; divide by SCALE
HULL_DENSITY = 5.0
LEG_DOWN = -8.0 / SCALE  # hip anchor below the hull origin
LEG_W = 8.0 / SCALE
LEG_H = 34.0 / SCALE  # 1.1333 full length of each leg segment
UPPER_LEG_MASS, UPPER_LEG_INERTIA = 0.302, 0.0341  # density 1, box 0.2667 x 1.1333 [measured]
LOWER_LEG_MASS, LOWER_LEG_INERTIA = 0.242, 0.0268  # density 1, box 0.2133 x 1.1333 [measured]
HIP_RANGE = (-0.8, 1.1)
KNEE_RANGE = (-1.6, -0.1)
SPEED_HIP = 4.0
SPEED_KNEE = 6.0
MOTORS_TORQUE = 80.0
GRAVITY = -10.0
TERRAIN_FRICTION = 2.5
LEG_FRICTION = 0.2
HULL_FRICTION = 0.1
INITIAL_RANDOM = 5.0  # horizontal push on the hull at reset (N, one control step)

LIDAR_RANGE = 160.0 / SCALE  # 5.333
LIDAR_N = 10
LIDAR_ANGLE_STEP = 0.15  # ray i points at angle 0.15 i from straight down, forward

# Reward.
SHAPING_X = 130.0 / SCALE
SHAPING_ANGLE = 5.0
TORQUE_COST = 0.00035 * MOTORS_TORQUE  # 0.028 per unit |a_j|
CRASH_REWARD = -100.0
