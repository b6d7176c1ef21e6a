"""The parity harness with a saved PPO policy (``envs.bipedal.parity --policy``): the same deterministic
actions in both engines, short episodes in each, and a record that keeps the gait's rows."""
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.bipedal import BipedalWalker, parity
from shed_jax.student import PPOConfig, make_student
from shed_jax.training import load_policy, save_policy


def _saved_policy(tmp_path, seeds=2):
    # the walker student's networks; one env slot (the file holds no env state) keeps init cheap
    student = make_student(BipedalWalker(), PPOConfig.for_env("bipedal").replace(num_envs=1))
    states = jax.vmap(student.init_policy)(jax.random.split(jax.random.PRNGKey(7), seeds))
    # observation statistics away from the identity, so that a harness that skipped them would differ
    mean = jax.random.normal(jax.random.PRNGKey(8), states.obs_norm.mean.shape) * 0.3
    states = states.replace(obs_norm=states.obs_norm.replace(mean=mean, var=jnp.full_like(mean, 4.0)))
    path = tmp_path / "policy.msgpack"
    save_policy(path, states)
    return student, states, path


def test_policy_controller_is_the_students_deterministic_action(tmp_path):
    student, states, path = _saved_policy(tmp_path)
    loaded = load_policy(student, path)  # the seed count comes from the file
    assert loaded.obs_norm.count.shape == (2,)
    obs = jax.random.normal(jax.random.PRNGKey(9), (5, 24))
    for i in range(2):
        state = jax.tree_util.tree_map(lambda x: x[i], loaded)
        first, next_ = parity.policy_controller(student)
        want = jax.vmap(lambda o: student.act(jax.tree_util.tree_map(lambda x: x[i], states), None, o, True))(obs)
        got_first = jax.vmap(lambda o: first(state, o)[0])(obs)
        got_next = jax.vmap(lambda o: next_(state, jnp.int32(0), o)[0])(obs)
        np.testing.assert_allclose(got_first, want, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(got_next, want, rtol=1e-6, atol=1e-6)
        assert np.all(np.abs(np.asarray(want)) <= 1.0)  # clipped to the action box


def test_policy_episodes_in_both_engines_respect_the_limit(tmp_path):
    student, states, path = _saved_policy(tmp_path)
    state = jax.tree_util.tree_map(lambda x: x[0], load_policy(student, path))
    act = jax.jit(lambda o: student.act(state, None, o, True))
    gym = parity.gym_episodes("BipedalWalker-v3", 2, seed=3, policy=lambda s: np.asarray(act(jnp.asarray(s, jnp.float32))),
                              max_steps=30)
    # the harness's contract does not depend on the physics options; without the time of impact (half
    # the walker's program) the episode scan compiles in a third of the time
    ours, = parity.jax_episodes("BipedalWalker", 2, seed=3, chunk=2, controller=parity.policy_controller(student),
                                thetas=[state], max_steps=30, continuous=False)
    for d in (gym, ours):
        assert d["ret"].shape == (2,) and np.all(np.isfinite(d["ret"]))
        assert np.all((d["length"] >= 1) & (d["length"] <= 30))


def test_policy_rows_are_added_to_an_existing_record(tmp_path):
    _, _, path = _saved_policy(tmp_path, seeds=1)
    out = tmp_path / "bipedal.json"
    out.write_text(json.dumps({"device": "x", "parity": {"flat": {"pass": True}}}))
    assert parity.main(["--policy", str(path), "--episodes", "1", "--gym-only", "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["device"] == "x" and rec["parity"]["flat"] == {"pass": True}
    row = rec["parity"]["policy_flat"]
    assert row["seeds"] == 1 and row["episodes_per_seed"] == 1 and np.isfinite(row["gym_mean"])
    assert "ours_mean" not in row and row["command"].startswith("python -m envs.bipedal.parity --policy")
    # where its episode ended: one fall site or one time-limit site at most, counted once
    assert sum(row["gym_fall_sites"].values()) == round(row["gym_fall"])
    assert sum(row["gym_fall_sites"].values()) + sum(row["gym_limit_sites"].values()) <= 1


def test_gait_rows_replace_the_header_and_keep_the_rest(tmp_path):
    out = tmp_path / "bipedal.json"
    out.write_text(json.dumps({"device": "x", "steps_per_second_best": 5.0,
                               "parity": {"policy_flat": {"pass": True}, "flat": {"old": 1}}}))
    assert parity.main(["--episodes", "1", "--settings", "flat", "--gym-only", "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["steps_per_second_best"] == 5.0 and rec["parity"]["policy_flat"] == {"pass": True}
    assert rec["device"] == "cpu" and rec["command"].startswith("python -m envs.bipedal.parity --episodes 1")
    row = rec["parity"]["flat"]
    assert "old" not in row and row["episodes"] == 1 and np.isfinite(row["gym_mean"])
    assert row["command"] == rec["command"] and row["date"] == rec["date"]


def test_terrain_resolution_option_is_checked_recorded_and_reaches_our_env(tmp_path, capsys, monkeypatch):
    with pytest.raises(SystemExit) as err:
        parity.main(["--terrain-resolution", "0", "--gym-only"])
    assert err.value.code == 2 and "terrain_resolution must be an int in [1, 32], got 0" in capsys.readouterr().err
    policy = tmp_path / "p.msgpack"
    policy.write_bytes(b"")
    with pytest.raises(SystemExit):  # the policy check plays our default terrain only
        parity.main(["--policy", str(policy), "--terrain-resolution", "2"])
    assert "drop --gym-chain/--iterations/--terrain-resolution" in capsys.readouterr().err
    seen = {}

    def fake_episodes(level, episodes, seed=0, chunk=100, **options):  # records what our env would be made with
        seen.update(level=level, **options)
        return [dict(ret=np.zeros(episodes), length=np.ones(episodes, int), fall=np.zeros(episodes, bool),
                     x=np.zeros(episodes), obstacles=[[]] * episodes)]

    monkeypatch.setattr(parity, "jax_episodes", fake_episodes)
    out = tmp_path / "r.json"
    assert parity.main(["--episodes", "2", "--settings", "hardcore", "--jax-only", "--terrain-resolution", "2",
                        "--iterations", "90/30", "--out", str(out)]) == 0
    options = {"velocity_iterations": 90, "position_iterations": 30, "terrain_resolution": 2}
    assert seen == {"level": "Hardcore", **options}
    assert json.loads(out.read_text())["ours_options"] == options
