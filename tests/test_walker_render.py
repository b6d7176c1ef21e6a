"""Walker renderer: frame shape/dtype, bodies drawn where the kinematics put them, GIF writing."""
import numpy as np
from PIL import Image

from envs.walker import constants as C
from envs.walker import model as M
from envs.walker import render as R
from envs.walker import terrain as T

HULL = (127, 51, 229)
GROUND = (102, 153, 76)
SKY = (230, 230, 255)


def test_frame_shows_hull_legs_and_ground(tmp_path):
    grid = T.make_grid(4)
    prof = np.full(grid.n, C.TERRAIN_HEIGHT, np.float32)
    q = M.start_qpos()
    w, h = 400, 267
    f = R.draw(q, prof, grid, w, h, lidar=False)
    assert f.shape == (h, w, 3) and f.dtype == np.uint8
    sx, sy = w / R.VIEW_W, h / R.VIEW_H
    to_px = lambda x, z: (int((x - (q[0] - R.VIEW_W / 4)) * sx), int(h - (z - (q[1] - R.VIEW_H / 2)) * sy))  # noqa: E731
    u, v = to_px(q[0], q[1])
    assert tuple(f[v, u]) == HULL  # the hull origin lies inside the hull polygon
    u, v = to_px(q[0] + 5.0, C.TERRAIN_HEIGHT - 1.0)
    assert tuple(f[v, u]) == GROUND
    assert tuple(f[2, w - 3]) == SKY
    # Leg boxes end where the joint chain puts the feet (just above the pad).
    polys = R.body_polygons(q)
    assert abs(polys["lower0"][:, 1].min() - (C.TERRAIN_HEIGHT + M.START_CLEARANCE)) < 0.03
    R.save_gif([f, R.draw(q, prof, grid, w, h, lidar=True)], tmp_path / "a.gif")  # (PIL merges equal frames)
    assert Image.open(tmp_path / "a.gif").n_frames == 2
