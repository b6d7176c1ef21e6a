"""experiments.bipedal_shin_stump: the outcome classifier and the penetration depth by hand, the random
starts' ranges, placement and determinism, Box2D's time-of-impact event count on two throws whose
events are known, and four starts agreeing with pybox2d over five steps without the time of impact.
The full comparison is run by hand (docs/bipedal.md, "A lone shin thrown at a stump")."""
import numpy as np
import pytest

from experiments import bipedal_shin_stump as X

STUMP = (1.0, 1.5, 0.0, 0.5)
HALF = (0.1, 0.5)


def test_outcome_by_final_centre_x():
    # final x: before the face, on it (inclusive), on the far side (inclusive), beyond; the first
    # trajectory went beyond the stump and came back: only the final step counts
    finals = [0.9, 1.0, 1.5, 1.6]
    traj = np.zeros((4, 3, 3))
    traj[:, 1, 0] = 2.0
    traj[:, -1, 0] = finals
    np.testing.assert_array_equal(X.classify(traj, STUMP), [0, 1, 1, 2])
    assert X.OUTCOMES[0] == "stopped" and X.OUTCOMES[2] == "beyond"


def test_penetration_depth_by_hand():
    pen = lambda x, y, a: float(X.penetration(x, y, a, HALF, STUMP))  # noqa: E731
    assert pen(0.93, 0.5, 0.0) == pytest.approx(0.03)  # upright, its right face 3 cm inside the stump's left face
    assert pen(0.8, 0.5, 0.0) == pytest.approx(-0.1)  # upright, 10 cm left of the face
    assert pen(1.25, 0.5 + 0.1 - 0.02, np.pi / 2) == pytest.approx(0.02)  # lying on the top, 2 cm into it
    assert pen(1.25, 0.5 + 0.1 + 0.05, -np.pi / 2) == pytest.approx(-0.05)  # lying 5 cm above the top
    # tilted 45 degrees, its rightmost corner on the stump's top-left corner: touching (0); 4 cm left of
    # that, the gap is 4 cm along x and 4 cos 45 cm along the shin's bottom normal: the widest counts
    c = np.cos(np.pi / 4)
    corner = np.array([[c, -c], [c, c]]) @ np.array([HALF[0], -HALF[1]])  # its lower-right corner, rotated
    centre = np.array([STUMP[0], STUMP[3]]) - corner
    assert pen(centre[0], centre[1], np.pi / 4) == pytest.approx(0.0, abs=1e-12)
    assert pen(centre[0] - 0.04, centre[1], np.pi / 4) == pytest.approx(-0.04)
    out = X.penetration(np.array([0.93, 0.8]), 0.5, np.zeros((3, 1)), HALF, STUMP)  # broadcasts
    assert out.shape == (3, 2) and out[0] == pytest.approx([0.03, -0.1])


@pytest.mark.parametrize("grid, side", [("base", 1), ("wide", 2)])
def test_starts_ranges_placement_and_determinism(grid, side):
    s = X.starts(grid, side, seed=0, n=384)
    for k, (lo, hi) in X.GRIDS[grid]["ranges"].items():
        assert s[k].shape == (384,) and lo <= s[k].min() and s[k].max() < hi
        assert s[k].max() - s[k].min() > 0.9 * (hi - lo)  # spread over the range
    # the shin's corners: the lowest is d above the stump's top, the rightmost gap left of its face
    hx, hy = X.shin_half()
    assert (hx, hy) == pytest.approx((0.8 * 8 / 30 / 2, 34 / 30 / 2))
    local = np.array([(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)])
    c, s_ = np.cos(s["angle"])[:, None], np.sin(s["angle"])[:, None]
    px = s["x"][:, None] + c * local[:, 0] - s_ * local[:, 1]
    py = s["y"][:, None] + s_ * local[:, 0] + c * local[:, 1]
    x0, _, _, y1 = X.stump_box(side)
    np.testing.assert_allclose(py.min(1), y1 + s["d"], atol=1e-12)
    np.testing.assert_allclose(px.max(1), x0 - s["gap"], atol=1e-12)
    assert x0 == pytest.approx(3 * 14 / 30) and y1 == pytest.approx(side * 14 / 30)
    again, other = X.starts(grid, side, seed=0, n=384), X.starts(grid, side, seed=1, n=384)
    assert all(np.array_equal(s[k], again[k]) for k in s) and not np.array_equal(s["vx"], other["vx"])
    edges = X.ground_edges(grid)
    assert edges.shape == (X.GRIDS[grid]["last_column"] + 2, 2, 2) and edges[0, 0, 0] == pytest.approx(-2 * 14 / 30)
    np.testing.assert_array_equal(edges[1:, 0], edges[:-1, 1])  # a connected ground at y = 0


def test_box2d_time_of_impact_events_per_step():
    """Two throws of tests/test_physics2d_toi.py at its stump (face at x = 1): upright at 20 m/s, 0.3 m
    up, meets the face in its second step (one event); at (28, -4) m/s just above the ground it meets
    the ground and then the face in its first step (two events)."""
    b2 = pytest.importorskip("Box2D")
    hy = X.shin_half()[1]
    stump = (1.0, 1.4667, 0.0, 0.4667)
    edges = np.array([((-2.0, 0.0), (1.0, 0.0)), ((1.0, 0.0), (1.4667, 0.0)), ((1.4667, 0.0), (4.0, 0.0))])
    start = dict(x=np.array([0.3, 0.45]), y=np.array([hy + 0.3, hy + 0.03]), angle=np.zeros(2),
                 vx=np.array([20.0, 28.0]), vy=np.array([0.0, -4.0]), omega=np.zeros(2))
    ref = X.box2d_trajectories(b2, start, edges, stump, True, steps=3)
    np.testing.assert_array_equal(X.box2d_toi_events(b2, start, edges, stump, ref), [[0, 1, 0], [2, 0, 0]])


def test_four_starts_agree_with_pybox2d_without_time_of_impact():
    b2 = pytest.importorskip("Box2D")
    start, edges, stump = X.starts("base", 1, seed=0, n=4), X.ground_edges("base"), X.stump_box(1)
    ours = X.physics2d_trajectories(X.physics2d_rollout(X.shin_model(X.CONFIGS["no_toi"]), steps=5), start, edges, stump)
    ref = X.box2d_trajectories(b2, start, edges, stump, continuous=False, steps=5)
    assert ours.shape == ref.shape == (4, 5, 3)
    np.testing.assert_allclose(ours, ref, atol=1e-5)
    res = X.compare(ref, ours, stump)
    assert res["off_diagonal"] == 0 and sum(res["outcomes"]["box2d"].values()) == 4
    assert res["position_difference_m"]["step5"]["max"] < 1e-5 and res["over_1cm_any_step"] == 0
    assert abs(res["max_penetration_m"]["box2d"] - res["max_penetration_m"]["physics2d"]) < 1e-5


def test_unknown_names_are_one_line_errors(capsys):
    assert X.main(["--grids", "base,nope"]) == 2
    assert X.main(["--configs", "walker,fast"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["bipedal_shin_stump: unknown grid 'nope' (choose from base, wide)",
                   "bipedal_shin_stump: unknown config 'fast' (choose from walker, toi_events3, toi_velocity180, no_toi)"]
