"""`python -m shed_jax demo --env bipedal`: the gait's outcomes, the frames, the table, the GIFs and the errors.

One compile: the demo's rollout of Gymnasium's gait on the flat level and on Stump, 300 steps.
"""
import argparse
import re

import numpy as np
import pytest
from PIL import Image

from shed_jax.errors import UsageError

STEPS, EVERY, NAMES = 300, 50, ("BipedalWalker", "Stump")


@pytest.fixture(scope="module")
def played():
    from envs.bipedal import demo as D
    from envs.bipedal.env import BipedalWalker
    from envs.bipedal.parity import heuristic_controller

    env = BipedalWalker()
    return D, env, D.play(env, NAMES, STEPS, heuristic_controller(), seed=0)


def test_gait_walks_the_flat_level_and_falls_at_a_stump(played):
    D, _, (stats, _, _) = played
    dist = stats["x"] - stats["x0"]
    # Gymnasium's gait keeps walking on the flat level: 28 m in 600 steps (2026-12-04); a controller
    # whose state or action lagged a step would stumble, stall or fall
    assert D.outcome(stats, 0) == "running" and stats["length"][0] == STEPS
    assert dist[0] > 8.0 and stats["ret"][0] > 20.0
    # and falls onto the first stump (step 224 with seed 0): the episode's end is kept, -100 included,
    # and the distance is where it fell, not where the body slid to later
    assert D.outcome(stats, 1) == "fell" and stats["length"][1] < STEPS and stats["ret"][1] < -50.0
    assert 2.0 < dist[1] < dist[0]


def test_a_frame_is_the_state_it_was_recorded_from(played):
    """Frames are drawn from the bodies recorded before each step, put into the start state: frame 0
    must be the start state's own drawing (a recording shifted by one step would differ)."""
    from envs.rendering import unstack

    D, env, (_, bodies, starts) = played
    for i in range(len(NAMES)):
        start = unstack(starts, i)
        assert np.array_equal(D.frame(env, start, unstack(unstack(bodies, 0), i)), env.render(start))
        assert not np.array_equal(D.frame(env, start, unstack(unstack(bodies, 2), i)), env.render(start))


def test_table_and_gifs(played, tmp_path, capsys):
    D, env, (stats, bodies, starts) = played
    D.report(env, NAMES, stats, bodies, starts, tmp_path, EVERY)
    rows = {m.group(1): m for m in re.finditer(
        r"^(\S+)\s+(-?\d+\.\d)\s+(\d+)\s+(running|fell|finished|time limit)\s+(-?\d+\.\d\d)$", capsys.readouterr().out, re.M)}
    assert set(rows) == set(NAMES)
    for i, name in enumerate(NAMES):
        row = rows[name]
        assert row.group(4) == D.outcome(stats, i) and int(row.group(3)) == stats["length"][i]
        assert float(row.group(2)) == pytest.approx(stats["ret"][i], abs=0.05)
        assert float(row.group(5)) == pytest.approx(stats["x"][i] - stats["x0"][i], abs=0.005)
        with Image.open(tmp_path / f"bipedal_{name}.gif") as im:  # a frame every EVERY steps up to the end
            assert im.n_frames == -(-int(stats["length"][i]) // EVERY)


def test_bad_input_is_one_line(tmp_path, capsys):
    from envs.bipedal import demo as D
    from shed_jax.__main__ import main

    args = dict(levels="BipedalWalker", steps=10, frame_every=1, seed=0, out=str(tmp_path), policy=None, no_gif=True)
    junk = tmp_path / "junk.msgpack"
    junk.write_bytes(b"not a policy")
    for bad, says in ((dict(levels="Flat"), "unknown level(s) Flat"), (dict(steps=0), "--steps and --frame-every"),
                      (dict(policy=str(tmp_path / "none.msgpack")), "no such file"),
                      (dict(policy=str(junk)), "is not a saved 2-D walker student")):
        with pytest.raises(UsageError, match=re.escape(says)):
            D.run_demo(argparse.Namespace(**{**args, **bad}))
    # the demos without a student player refuse --policy before any work
    assert main(["demo", "--env", "lander", "--policy", str(junk)]) == 2
    assert "--policy works with --env bipedal" in capsys.readouterr().err


def test_module_entry_point_reports_one_line():
    """``python -m envs.bipedal.demo`` prints a user error as one line and exits 2 (no compile)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "envs.bipedal.demo", "--levels", "Flat"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [r.stderr.strip()] and "unknown level(s) Flat" in r.stderr
