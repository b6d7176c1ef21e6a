"""experiments.solver_convergence's figures, on hand-made per-world-step arrays."""
import numpy as np
import pytest

from experiments import solver_convergence as sc


def test_summarise_counts_worlds_without_a_stop_and_blocks_that_hold_one():
    n_v, n_p = 180, 60
    fixed = np.array([[180], [180], [40], [180]])  # one world of four reaches an exact fixed point
    last = np.array([[10, 20, 30, 40], [180, 180, 180, 180], [5, 6, 7, 8], [12, 180, 180, 180]])
    solved = np.array([[1], [1], [1], [1], [60]])  # the reset's step counts here too
    man = np.array([[1], [1], [2], [5]])
    out = sc.summarise({"fixed": fixed, "last_over": last, "solved_at": solved, "manifolds": man}, n_v, n_p, block=2)
    assert out["world_steps"] == 4 and out["position"]["world_steps"] == 5
    v = out["velocity"]
    assert v["exact_fixed_point_never"] == 0.75
    assert v["block_has_a_world_without_fixed_point"] == pytest.approx(1 - 0.25 ** 2, abs=1e-4)
    # at 1e-3 one world of four still changes in the last pass, at 1e-4 and finer two
    assert v["still_over_tolerance_at_the_last_pass"] == {"0.001": 0.25, "0.0001": 0.5, "1e-05": 0.5, "1e-06": 0.5}
    assert v["last_pass_over_tolerance_percentiles"]["0.001"]["100"] == 180.0
    p = out["position"]
    assert p["never_solved"] == 0.2 and p["block_has_a_world_never_solved"] == pytest.approx(1 - 0.8 ** 2, abs=1e-4)
    assert p["solved_at_percentiles"]["50"] == 1.0
    assert out["manifolds_with_points_histogram"] == [0, 2, 1, 0, 0, 1, 0, 0]
    assert out["manifolds_with_points_over"]["2"] == 0.25 and out["manifolds_with_points_over"]["5"] == 0.0


def test_bad_steps_are_one_line(capsys):
    assert sc.main(["--steps", "0", "--out", "x.json"]) == 2
    assert capsys.readouterr().err.strip() == "solver_convergence: --steps must be >= 1, got 0"
