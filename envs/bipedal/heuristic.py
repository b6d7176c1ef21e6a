"""Gymnasium's scripted BipedalWalker gait (``BipedalWalkerHeuristics``) as a jittable, vmappable function.

The controller is a three-phase state machine (stay on one leg, put the other down, push off) with
PD targets on the hips and knees; its state is carried explicitly in ``HeuristicState``. Gymnasium's
``if targ:`` tests skip a target of exactly 0.0 as well as an unset one; so does this version.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

STAY_ON_ONE_LEG, PUT_OTHER_DOWN, PUSH_OFF = 1, 2, 3
SPEED = 0.29
SUPPORT_KNEE_ANGLE = 0.1


@struct.dataclass
class HeuristicState:
    phase: jax.Array  # int32: STAY_ON_ONE_LEG, PUT_OTHER_DOWN or PUSH_OFF
    moving_leg: jax.Array  # int32 0 or 1
    supporting_knee_angle: jax.Array  # float32


def heuristic_init() -> HeuristicState:
    """A fresh controller (Gymnasium's class defaults)."""
    return HeuristicState(jnp.int32(STAY_ON_ONE_LEG), jnp.int32(0), jnp.float32(SUPPORT_KNEE_ANGLE))


def heuristic(h: HeuristicState, s: jax.Array):
    """One ``step_heuristic(s)``: (action (4,), new controller state) for an observation (24,)."""
    s = jnp.asarray(s, jnp.float32)
    legs = jnp.arange(2)
    moving = h.moving_leg
    supporting = 1 - moving
    mb, sb = 4 + 5 * moving, 4 + 5 * supporting
    is_mov, is_sup = legs == moving, legs == supporting
    hip_t, hip_on = jnp.zeros(2, jnp.float32), jnp.zeros(2, bool)
    knee_t, knee_on = jnp.zeros(2, jnp.float32), jnp.zeros(2, bool)
    phase, ska = h.phase, h.supporting_knee_angle

    def put(t, on, cond, mask, value):
        sel = cond & mask
        return jnp.where(sel, value, t), on | sel

    p1 = phase == STAY_ON_ONE_LEG
    hip_t, hip_on = put(hip_t, hip_on, p1, is_mov, 1.1)
    knee_t, knee_on = put(knee_t, knee_on, p1, is_mov, -0.6)
    ska1 = jnp.minimum(ska + 0.03 + jnp.where(s[2] > SPEED, 0.03, 0.0), SUPPORT_KNEE_ANGLE)
    ska = jnp.where(p1, ska1, ska)
    knee_t, knee_on = put(knee_t, knee_on, p1, is_sup, ska)
    phase = jnp.where(p1 & (s[sb] < 0.10), PUT_OTHER_DOWN, phase)

    p2 = phase == PUT_OTHER_DOWN
    hip_t, hip_on = put(hip_t, hip_on, p2, is_mov, 0.1)
    knee_t, knee_on = put(knee_t, knee_on, p2, is_mov, SUPPORT_KNEE_ANGLE)
    knee_t, knee_on = put(knee_t, knee_on, p2, is_sup, ska)
    down = p2 & (s[mb + 4] != 0)
    phase = jnp.where(down, PUSH_OFF, phase)
    ska = jnp.where(down, jnp.minimum(s[mb + 2], SUPPORT_KNEE_ANGLE), ska)

    p3 = phase == PUSH_OFF
    knee_t, knee_on = put(knee_t, knee_on, p3, is_mov, ska)
    knee_t, knee_on = put(knee_t, knee_on, p3, is_sup, 1.0)
    switch = p3 & ((s[sb + 2] > 0.88) | (s[2] > 1.2 * SPEED))
    phase = jnp.where(switch, STAY_ON_ONE_LEG, phase)
    moving = jnp.where(switch, 1 - moving, moving)

    hip_s, hip_v = s[jnp.asarray([4, 9])], s[jnp.asarray([5, 10])]
    knee_s, knee_v = s[jnp.asarray([6, 11])], s[jnp.asarray([7, 12])]
    hip_todo = jnp.where(hip_on & (hip_t != 0), 0.9 * (hip_t - hip_s) - 0.25 * hip_v, 0.0)
    knee_todo = jnp.where(knee_on & (knee_t != 0), 4.0 * (knee_t - knee_s) - 0.25 * knee_v, 0.0)
    hip_todo = hip_todo - (0.9 * (0 - s[0]) - 1.5 * s[1])  # PID to keep the head straight
    knee_todo = knee_todo - 15.0 * s[3]  # vertical speed, to damp oscillations
    a = jnp.clip(0.5 * jnp.stack([hip_todo[0], knee_todo[0], hip_todo[1], knee_todo[1]]), -1.0, 1.0)
    return a, HeuristicState(phase.astype(jnp.int32), moving.astype(jnp.int32), ska.astype(jnp.float32))
