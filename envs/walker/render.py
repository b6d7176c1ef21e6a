"""2-D drawing of a walker state with PIL (no GL): sky, terrain profile, hull, legs, lidar rays.

The view follows the hull like Gymnasium's (20 m wide, 13.3 m high). Kinematics are recomputed
from ``qpos`` with the same constants as the MJCF, so the picture is what the physics simulates.
"""
from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from envs.walker import constants as C
from envs.walker import lidar as L
from envs.walker.terrain import Grid

VIEW_W, VIEW_H = 600 / C.SCALE, 400 / C.SCALE


def _rot(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def body_polygons(qpos) -> dict:
    """World polygons of the hull and the 4 leg segments (boxes) for one ``qpos``."""
    q = np.asarray(qpos, np.float64)
    pos, th = q[:2], q[2]
    hull = (np.asarray(C.HULL_POLY) / C.SCALE) @ _rot(th).T + pos
    out = {"hull": hull}
    for i, (hip, knee) in enumerate([(q[3], q[4]), (q[5], q[6])]):
        top = pos + _rot(th) @ np.array([0.0, C.LEG_DOWN])
        for name, ang, w in (("upper", th + hip, C.LEG_W), ("lower", th + hip + knee, 0.8 * C.LEG_W)):
            box = np.array([[-w / 2, 0], [w / 2, 0], [w / 2, -C.LEG_H], [-w / 2, -C.LEG_H]])
            out[f"{name}{i}"] = box @ _rot(ang).T + top
            top = top + _rot(ang) @ np.array([0.0, -C.LEG_H])
    return out


def draw(qpos, profile, grid: Grid, width: int = 400, height: int = 267, lidar: bool = True, text: str | None = None,
         polygons: dict | None = None, ground: tuple | None = None, boxes=None) -> np.ndarray:
    """RGB frame [height, width, 3] uint8 of one walker state. ``polygons`` (world polygons keyed as
    ``body_polygons``'): the bodies as a simulator holds them, drawn instead of the rigid skeleton
    computed from ``qpos`` (which still places the view and the lidar). ``ground`` (column x, y) and
    ``boxes`` ([K, 4] x0, x1, y0, y1; all-zero rows unused): a simulator's terrain fixtures, drawn
    instead of the height profile (which the lidar still reads)."""
    q = np.asarray(qpos, np.float64)
    prof = np.asarray(profile, np.float64)
    x_left = q[0] - VIEW_W / 4
    z_bottom = q[1] - VIEW_H / 2
    sx, sy = width / VIEW_W, height / VIEW_H

    def px(p):
        p = np.atleast_2d(p)
        return [((x - x_left) * sx, height - (z - z_bottom) * sy) for x, z in p]

    img = Image.new("RGB", (width, height), (230, 230, 255))
    d = ImageDraw.Draw(img)
    gx = grid.x_min + grid.dx * np.arange(grid.n)
    if ground is None:
        sel = (gx >= x_left - grid.dx) & (gx <= x_left + VIEW_W + grid.dx)
        pts = np.stack([gx[sel], prof[sel]], -1)
    else:
        cx, cy = (np.asarray(v, np.float64) for v in ground)
        inside = np.nonzero((cx >= x_left) & (cx <= x_left + VIEW_W))[0]
        lo, hi = (max(inside[0] - 1, 0), min(inside[-1] + 2, len(cx))) if inside.size else (0, len(cx))
        pts = np.stack([cx[lo:hi], cy[lo:hi]], -1)
    if len(pts) > 1:
        poly = px(pts) + [((pts[-1, 0] - x_left) * sx, height + 10), ((pts[0, 0] - x_left) * sx, height + 10)]
        d.polygon(poly, fill=(102, 153, 76), outline=(76, 230, 76))
    for x0, x1, y0, y1 in np.asarray(boxes if boxes is not None else np.zeros((0, 4)), np.float64):
        if x1 > x0 and y1 > y0:
            d.polygon(px([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), fill=(102, 153, 76), outline=(76, 230, 76))
    if x_left < C.FINISH_X < x_left + VIEW_W:
        f = px([[C.FINISH_X, np.interp(C.FINISH_X, gx, prof)], [C.FINISH_X, np.interp(C.FINISH_X, gx, prof) + 2.0]])
        d.line(f, fill=(230, 50, 50), width=2)
    if lidar:
        fr = np.asarray(L.lidar(prof.astype(np.float32), grid, q[:2].astype(np.float32)))
        for f, dvec in zip(fr, L.RAY_DIRS):
            d.line(px([q[:2], q[:2] + f * C.LIDAR_RANGE * dvec]), fill=(255, 80, 80), width=1)
    polys = body_polygons(q) if polygons is None else polygons
    for name in ("upper1", "lower1", "hull", "upper0", "lower0"):
        shade = (0.7 if name.endswith("1") else 1.0) if name != "hull" else 1.0
        fill = (127, 51, 229) if name == "hull" else tuple(int(c * shade) for c in (178, 102, 153))
        d.polygon(px(polys[name]), fill=fill, outline=(76, 76, 127))
    if text:
        d.text((5, 5), text, fill=(0, 0, 0))
    return np.asarray(img, np.uint8)


def save_gif(frames, path, fps: int = 25) -> None:
    """Frames (uint8 [H, W, 3]) -> animated GIF."""
    ims = [Image.fromarray(f) for f in frames]
    ims[0].save(path, save_all=True, append_images=ims[1:], duration=int(1000 / fps), loop=0, optimize=True)
