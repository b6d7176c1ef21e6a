"""`python -m shed_jax demo --env bipedal`: its bookkeeping against the steps it ran, the gait's
outcomes, the frames, the table, the GIFs and the errors.

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


def test_stats_are_the_first_episodes_steps(played):
    """Return, length, end and x against the per-step trace: the first done ends the episode, its
    step (the -100 included) counts, and nothing after it does."""
    D, _, (stats, trace, _, _) = played
    for i in range(len(NAMES)):
        done = trace["done"][:, i]
        n = int(np.argmax(done)) + 1 if done.any() else STEPS
        assert stats["length"][i] == n and bool(stats["done"][i]) == bool(done.any())
        assert stats["ret"][i] == pytest.approx(trace["reward"][:n, i].sum(), rel=1e-5, abs=1e-3)
        assert stats["x"][i] == trace["x"][n - 1, i]
        assert bool(stats["fell"][i]) == bool(done.any() and trace["reward"][n - 1, i] == -100.0)


def test_gait_walks_the_flat_level_and_falls_at_a_stump(played):
    D, _, (stats, _, _, _) = played
    dist = stats["x"] - stats["x0"]
    # Gymnasium's gait walks off on the flat level (11-12 m in 300 steps, seeds 0-2, 2026-12-04; it
    # can fall there later, so only a start is asked for) and falls onto the first stump (steps 222-229)
    assert dist[0] > 2.0
    assert D.outcome(stats, 1) == "fell" and stats["length"][1] < STEPS and stats["ret"][1] < -50.0


def test_frames_are_the_states_they_were_recorded_from(played):
    """``bodies[t]`` is the state after t steps: ``bodies[0]`` the start state's own bodies exactly, and
    a frame is the start state drawn with them."""
    import jax

    from envs.rendering import unstack

    D, env, (_, _, bodies, starts) = played
    for i in range(len(NAMES)):
        start = unstack(starts, i)
        b0 = unstack(unstack(bodies, 0), i)
        assert all(np.array_equal(x, y) for x, y in zip(jax.tree_util.tree_leaves(b0),
                                                         jax.tree_util.tree_leaves(start.world.bodies)))
        assert np.array_equal(D.frame(env, start, b0), env.render(start))
        assert not np.array_equal(D.frame(env, start, unstack(unstack(bodies, 2), i)), env.render(start))


def test_table_and_gifs(played, tmp_path, capsys):
    D, env, (stats, _, bodies, starts) = played
    D.report(env, NAMES, stats, bodies, starts, tmp_path, EVERY)
    rows = {m.group(1): m for m in re.finditer(
        r"^(\S+)\s+(-?\d+\.\d)\s+(\d+)\s+(running|fell|finished|time limit)\s+(-?\d+\.\d\d)$", capsys.readouterr().out, re.M)}
    assert set(rows) == set(NAMES)
    for i, name in enumerate(NAMES):
        row = rows[name]
        assert row.group(4) == D.outcome(stats, i) and int(row.group(3)) == stats["length"][i]
        assert float(row.group(2)) == pytest.approx(stats["ret"][i], abs=0.05)
        assert float(row.group(5)) == pytest.approx(stats["x"][i] - stats["x0"][i], abs=0.005)
        with Image.open(tmp_path / f"bipedal_{name}.gif") as im:  # every EVERY-th state and the last
            assert im.n_frames == len(D.frame_steps(int(stats["length"][i]), EVERY))


def test_outcomes_levels_and_frame_steps():
    from envs.bipedal import demo as D

    stats = dict(done=np.array([0, 1, 1, 1], bool), fell=np.array([0, 1, 0, 0], bool),
                 terminated=np.array([0, 1, 1, 0], bool))
    assert [D.outcome(stats, i) for i in range(4)] == ["running", "fell", "finished", "time limit"]
    assert D.level_names(3) == list(D.DEMO_ORDER[:3]) and D.level_names("Stump,Insane") == ["Stump", "Insane"]
    assert D.level_names(99) == list(D.DEMO_ORDER)
    assert D.frame_steps(7, 3) == [0, 3, 6, 7] and D.frame_steps(6, 3) == [0, 3, 6] and D.frame_steps(1, 5) == [0, 1]


def test_bad_input_is_one_line(tmp_path, capsys):
    import jax

    import envs
    from envs.bipedal import demo as D
    from shed_jax.__main__ import main
    from shed_jax.student import PPOConfig, make_student
    from shed_jax.training import save_policy

    args = dict(levels="BipedalWalker", steps=10, frame_every=1, seed=0, out=str(tmp_path), policy=None, no_gif=True)
    junk = tmp_path / "junk.msgpack"
    junk.write_bytes(b"not a policy")
    lander = make_student(envs.make("lander-continuous"), PPOConfig.for_env("lander-continuous").replace(num_envs=1))
    save_policy(tmp_path / "lander.msgpack", jax.vmap(lander.init_policy)(jax.random.split(jax.random.PRNGKey(0), 2)))
    for bad, says in ((dict(levels="Flat"), "unknown level(s) Flat"), (dict(levels="0"), "--levels must be >= 1"),
                      (dict(steps=0), "--steps and --frame-every"),
                      (dict(policy=str(tmp_path / "none.msgpack")), "no such file"),
                      (dict(policy=str(junk)), "is not a flax msgpack file"),
                      # flax restores arrays of any shape: a lander's student must be refused by name
                      (dict(policy=str(tmp_path / "lander.msgpack")), "['obs_norm']['mean'] has shape (2, 8), expected (2, 24)")):
        with pytest.raises(UsageError, match=re.escape(says)):
            D.run_demo(argparse.Namespace(**{**args, **bad}))
    # the demos without a student player refuse --policy before any work
    assert main(["demo", "--env", "lander", "--policy", str(junk)]) == 2
    assert "--policy works with --env bipedal" in capsys.readouterr().err


def test_module_entry_point_reports_one_line():
    """``python -m envs.bipedal.demo`` prints a user error as one line and exits 2 (no compile)."""
    import subprocess
    import sys

    for argv, says in ((["--levels", "Flat"], "unknown level(s) Flat"), (["--steps", "x"], "argument --steps")):
        r = subprocess.run([sys.executable, "-m", "envs.bipedal.demo", *argv], capture_output=True, text=True, timeout=300)
        assert r.returncode == 2 and "Traceback" not in r.stderr
        last = r.stderr.strip().splitlines()[-1]
        assert last.startswith("shed_jax: error:") and says in last
