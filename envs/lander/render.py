"""Host-side renderer of one lander state (numpy + PIL, no GL): sky, moon, helipad flags, lander, flames."""
from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from envs import physics2d
from envs.lander import model as M

VIEW_W, VIEW_H = 600, 400


def _px(p):
    """World metres -> image pixels (y up -> y down)."""
    return (float(p[0]) * M.SCALE, VIEW_H - float(p[1]) * M.SCALE)


def render_state(env, state) -> np.ndarray:
    """RGB uint8 (400, 600, 3) of one unbatched LanderState."""
    img = Image.new("RGB", (VIEW_W, VIEW_H), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    ty = np.asarray(state.terrain_y, np.float64)
    ground = [_px((x, y)) for x, y in zip(M.CHUNK_X, ty)]
    draw.polygon(ground + [(VIEW_W, VIEW_H), (0, VIEW_H)], fill=(0, 0, 0))
    # helipad flags
    for x in (M.HELIPAD_X1, M.HELIPAD_X2):
        base = _px((x, M.HELIPAD_Y))
        top = (base[0], base[1] - 50)
        draw.line([base, top], fill=(255, 255, 255), width=1)
        draw.polygon([top, (top[0], top[1] + 10), (top[0] + 25, top[1] + 5)], fill=(204, 204, 0))
    bodies = state.world.bodies
    origin = np.asarray(physics2d.body_origin(env.model, bodies))
    angle = np.asarray(bodies.angle)
    hull_angle = float(angle[0])
    tip = np.array([np.sin(hull_angle), np.cos(hull_angle)])
    side = np.array([-tip[1], tip[0]])
    # flames (last engine throttles), drawn under the bodies
    mp, sp = float(state.main_power), float(state.side_power)
    if mp > 0:
        p0 = origin[0] - tip * M.MAIN_ENGINE_Y_LOCATION
        p1 = p0 - tip * (0.4 + 0.4 * mp)
        draw.line([_px(p0), _px(p1)], fill=(255, 140, 0), width=6)
    if abs(sp) > 0:
        p0 = origin[0] + tip * M.SIDE_ENGINE_HEIGHT - side * np.sign(sp) * M.SIDE_ENGINE_AWAY
        p1 = p0 - side * np.sign(sp) * 0.4
        draw.line([_px(p0), _px(p1)], fill=(255, 140, 0), width=3)
    for poly in env.model.polygons:
        i = poly.body
        c, s = np.cos(angle[i]), np.sin(angle[i])
        pts = [_px(origin[i] + np.array([c * x - s * y, s * x + c * y])) for x, y in poly.vertices]
        draw.polygon(pts, fill=(128, 102, 230), outline=(77, 77, 128))
    return np.asarray(img, np.uint8)
