"""``python -m shed_jax eval``: the table math on hand values, and the CLI on a tiny saved run
(test set, named levels, level files) with clear errors for bad level files.

The run is the same tiny CartPole PLR run as in test_checkpoint.py (same program, so the
persistent compilation cache serves both), driven in-process through the run CLI's ``main``.
"""
import argparse
import json
import math

import numpy as np
import pytest

from shed_jax import evaluation
from shed_jax import experiment as xp
from shed_jax.cli import eval as eval_cli
from shed_jax.cli import run as run_cli

# the tiny CartPole experiment and its test levels are test_checkpoint's
from test_checkpoint import cartpole_test_levels, tiny_experiment  # noqa: E402

SEEDS = 2


def parse(module, argv):
    p = argparse.ArgumentParser()
    module.add_arguments(p)
    return p.parse_args(argv)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    original = xp.test_levels
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(xp, "experiment_from_args", lambda args, backend: tiny_experiment())
        mp.setattr(xp, "test_levels", lambda name, env: cartpole_test_levels(env) if name == "cartpole-test" else original(name, env))
        d = tmp_path_factory.mktemp("eval") / "run"
        assert run_cli.main(parse(run_cli, ["--out", str(d), "--seeds", str(SEEDS), "--chunk", "1", "--no-gif",
                                            "--final-eval", "test", "--final-eval-episodes", "3"])) == 0
        yield d


def test_table_math_by_hand():
    # 2 seeds x 2 levels x 5 episodes
    r = np.array([
        [[10, 20, 30, 40, 500], [0, 0, 0, 0, 0]],
        [[30, 40, 50, 60, 70], [-100, 300, 300, 300, 300]],
    ], np.float64)
    t = evaluation.level_table(r, threshold=45.0, alpha=0.1)
    # seed means: level 0: 120 and 50 -> mean 85, SE = sd(ddof 1) / sqrt(2) = |120 - 50| / 2 = 35;
    # level 1: 0 and 220 -> mean 110, SE 110
    np.testing.assert_allclose(t["mean"], [85.0, 110.0])
    np.testing.assert_allclose(t["se"], [35.0, 110.0])
    # solved (> 45): level 0: 500, 50, 60, 70 -> 4/10; level 1: four 300s -> 4/10
    np.testing.assert_allclose(t["solved_rate"], [0.4, 0.4])
    # CVaR 10 % of 10 returns: the single worst one
    np.testing.assert_allclose(t["cvar"], [10.0, -100.0])
    o = t["overall"]
    # seed overall means: (600 + 0) / 10 = 60 and (250 + 1100) / 10 = 135
    assert o["mean"] == pytest.approx(97.5) and o["se"] == pytest.approx(37.5)
    assert o["solved_rate"] == pytest.approx(8 / 20)
    assert o["cvar"] == pytest.approx(-50.0)  # worst ceil(0.1 * 20) = 2 values: -100 and 0
    # ceil: 25 % of 10 -> 3 values; 30 % of 10 -> exactly 3 (no float round-up to 4)
    assert evaluation.cvar(np.arange(10.0), 0.25) == pytest.approx(1.0)
    assert evaluation.cvar(np.arange(10.0), 0.3) == pytest.approx(1.0)
    assert evaluation.cvar([5.0], 0.1) == 5.0
    # no threshold -> NaN solved rates; one seed -> SE 0
    t1 = evaluation.level_table(r[:1], threshold=None)
    assert np.all(np.isnan(t1["solved_rate"])) and math.isnan(t1["overall"]["solved_rate"])
    np.testing.assert_array_equal(t1["se"], [0.0, 0.0])
    with pytest.raises(ValueError, match="seeds, levels, episodes"):
        evaluation.level_table(r[0], 1.0)


def test_eval_test_set_writes_json(run_dir, capsys, monkeypatch):
    from shed_jax import driver

    stages, original = [], driver.heartbeat_wait
    monkeypatch.setattr(driver, "heartbeat_wait", lambda thunk, what: stages.append(what) or original(thunk, what))
    rc = eval_cli.main(parse(eval_cli, ["--run", str(run_dir), "--levels", "test", "--episodes", "3", "--max-steps", "30",
                                        "--solved-threshold", "15"]))
    assert rc == 0
    out = capsys.readouterr().out
    res = json.loads((run_dir / "eval_test.json").read_text())
    returns = np.asarray(res["returns"])
    assert returns.shape == (SEEDS, 2, 3)
    assert res["checkpoint_step"] == 4 and res["seeds"] == SEEDS and res["labels"] == ["test-0", "test-1"]
    assert res["device"].startswith("cpu: ") and res["date"].endswith(" UTC") and res["command"].startswith("python -m shed_jax")
    assert res["level_params"]["gravity"] == pytest.approx([9.8, 1.62])
    # cartpole pays 1 per step, capped at --max-steps 30
    assert np.all((returns >= 1) & (returns <= 30)) and np.all(returns == np.round(returns))
    table = evaluation.level_table(returns, 15.0)
    for j, row in enumerate(res["per_level"]):
        assert row["mean"] == pytest.approx(table["mean"][j])
        assert row["se"] == pytest.approx(table["se"][j])
        assert row["solved_rate"] == pytest.approx(np.mean(returns[:, j] > 15))
        assert row["cvar"] == pytest.approx(np.sort(returns[:, j].ravel())[0])  # ceil(0.1 * 6) = 1 episode
    assert res["overall"]["mean"] == pytest.approx(returns.mean())
    assert "| test-0 |" in out and "all levels" in out and "eval_test.json" in out
    # a start line, then the compile and the roll-outs each in a heartbeat worker
    assert "x 3 episode(s) (compiling first)..." in out and stages == ["compiling", "evaluating"]


def test_eval_named_and_file_levels(run_dir, tmp_path, capsys):
    # named: the cartpole module's LEVELS
    assert eval_cli.main(parse(eval_cli, ["--run", str(run_dir), "--levels", "named", "--episodes", "1", "--max-steps", "20",
                                          "--deterministic"])) == 0
    res = json.loads((run_dir / "eval_named.json").read_text())
    from envs.cartpole import LEVELS

    assert res["labels"] == list(LEVELS) and np.asarray(res["returns"]).shape == (SEEDS, len(LEVELS), 1)
    assert res["solved_threshold"] == 475.0 and res["deterministic"] is True
    # a file of vectors (gravity, length, force_mag) and one of objects by name
    vec = tmp_path / "my levels.json"
    vec.write_text(json.dumps([[9.8, 0.5, 10.0], [3.0, 0.9, 12.0], [15.0, 0.3, 7.0]]))
    out = tmp_path / "vec_eval.json"
    assert eval_cli.main(parse(eval_cli, ["--run", str(run_dir), "--levels", str(vec), "--episodes", "2", "--max-steps", "20",
                                          "--out", str(out)])) == 0
    res = json.loads(out.read_text())
    assert res["levels"] == "my_levels" and np.asarray(res["returns"]).shape == (SEEDS, 3, 2)
    assert res["level_params"]["length"] == pytest.approx([0.5, 0.9, 0.3])
    objs = tmp_path / "objs.json"
    objs.write_text(json.dumps({"levels": [{"gravity": 3.0, "label": "low-g"}, {"masspole": 0.5, "max_steps": 15}]}))
    assert eval_cli.main(parse(eval_cli, ["--run", str(run_dir), "--levels", str(objs), "--episodes", "2"])) == 0
    res = json.loads((run_dir / "eval_objs.json").read_text())
    returns = np.asarray(res["returns"])
    assert res["labels"] == ["low-g", "level-1"] and returns.shape == (SEEDS, 2, 2)
    assert np.all(returns[:, 1] <= 15)  # the level's own time limit
    assert res["level_params"]["gravity"] == pytest.approx([3.0, 9.8])  # missing fields: the defaults


def test_run_final_eval_equals_eval_on_the_saved_students(run_dir, tmp_path):
    """run --final-eval evaluates the final students in memory; eval on the last checkpoint, with the
    same seed, episodes and cap (the test set's 20 steps), must return the very same episodes."""
    final = json.loads((run_dir / "final_eval_test.json").read_text())
    assert final["budget_step"] == 4 and final["episodes"] == 3 and final["max_steps"] == 20
    assert final["device"].startswith("cpu: ") and final["date"].endswith(" UTC")
    summary = json.loads((run_dir / "summary.json").read_text())
    assert 0 < final["wall_time_s"] < summary["wall_time_s"]  # its own time, not in the run's wall time
    out = tmp_path / "again.json"
    assert eval_cli.main(parse(eval_cli, ["--run", str(run_dir), "--levels", "test", "--episodes", "3", "--max-steps", "20",
                                          "--out", str(out)])) == 0
    again = json.loads(out.read_text())
    np.testing.assert_array_equal(np.asarray(final["returns"]), np.asarray(again["returns"]))
    assert final["per_level"] == again["per_level"] and final["labels"] == ["test-0", "test-1"]


def test_final_eval_specs():
    import envs

    walker_default = envs.make("bipedal").ued.final_eval  # the walkers' UEDSpec (no MJX needed)
    assert evaluation.final_eval_specs(None, walker_default) == ["named"]  # DCD's levels by default
    assert evaluation.final_eval_specs(None, envs.make("lander").ued.final_eval) == []
    assert evaluation.final_eval_specs("none", walker_default) == []
    assert evaluation.final_eval_specs("test, named", "none") == ["test", "named"]
    with pytest.raises(SystemExit, match="'none' cannot be combined"):
        evaluation.final_eval_specs("none,test", "named")
    with pytest.raises(SystemExit, match="twice"):
        evaluation.final_eval_specs("test,test", "named")


def test_bad_final_eval_set_fails_before_training(tmp_path):
    d = tmp_path / "run"
    original = xp.test_levels
    with pytest.MonkeyPatch.context() as mp:  # the tiny experiment and its test set (not only in the suite's order)
        mp.setattr(xp, "experiment_from_args", lambda args, backend: tiny_experiment())
        mp.setattr(xp, "test_levels", lambda name, env: cartpole_test_levels(env) if name == "cartpole-test" else original(name, env))
        with pytest.raises(SystemExit, match="--final-eval: .*'hard' is none of these"):
            run_cli.main(parse(run_cli, ["--out", str(d), "--seeds", "1", "--no-gif", "--final-eval", "hard"]))
    assert not (d / "metrics.jsonl").exists() and not (d / "checkpoints").exists()


@pytest.mark.parametrize("content, message", [
    ("{not json", "not valid JSON"),
    ("[]", "non-empty JSON list"),
    ("[[9.8, 0.5]]", "level 0 has 2 values; cartpole levels are vectors of 3 (gravity, length, force_mag)"),
    ('[[9.8, 0.5, 10.0], {"gravity": 1.0}]', "all vectors (lists) or all objects"),
    ('[{"gravity": 1.0, "wind": 3}]', "unknown cartpole parameter(s) ['wind']"),
    ('[{"gravity": "high"}]', "level 0, gravity must be a finite number"),
    ('[{"max_steps": 10.5}]', "level 0, max_steps must be an integer"),
    ("[[9.8, -0.5, 10.0]]", "parameter 'length' must be a finite value in"),
])
def test_bad_level_files(tmp_path, content, message):
    import envs

    f = tmp_path / "levels.json"
    f.write_text(content)
    with pytest.raises(evaluation.LevelFileError) as err:
        evaluation.load_level_file(f, envs.make("cartpole"))
    assert message in str(err.value) and str(f) in str(err.value)


def test_eval_cli_errors(run_dir, tmp_path, capsys):
    assert eval_cli.main(parse(eval_cli, ["--run", str(tmp_path / "none")])) == eval_cli.EXIT_BAD_INPUT
    assert "no run directory" in capsys.readouterr().err
    assert eval_cli.main(parse(eval_cli, ["--run", str(run_dir), "--levels", "hard"])) == eval_cli.EXIT_BAD_INPUT
    assert "'test', 'named' or an existing JSON file" in capsys.readouterr().err
    assert eval_cli.main(parse(eval_cli, ["--run", str(run_dir), "--step", "1"])) == eval_cli.EXIT_BAD_INPUT
    assert "no checkpoint for step 1" in capsys.readouterr().err


def test_named_and_test_sets_of_lander_and_walker():
    """The level sets eval builds for the real envs (host side only, nothing compiled)."""
    import envs
    from envs.walker.levels import LEVELS
    from shed_jax import eval_sets
    from shed_jax.presets import build_experiment

    lander = envs.make("lander")
    exp = build_experiment("lander", "dr", "quick")
    tests = xp.test_levels(exp.test_set, lander)
    levels, labels, name = evaluation.resolve_levels("named", lander, exp, tests)
    assert name == "named" and labels == [f"eval-{i}" for i in range(10)] + [f"test-{i}" for i in range(10)]
    np.testing.assert_allclose(np.asarray(levels.gravity)[[0, 9, 10, 19]], [-0.01, -9.457, -2.0, -6.3], rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(levels.enable_wind)[:3], [False, True, False])
    assert np.all(np.asarray(levels.max_steps) == eval_sets.LANDER_MAX_STEPS)
    _, labels, _ = evaluation.resolve_levels("test", lander, exp, tests)
    assert labels == [f"test-{i}" for i in range(10)]

    walker = envs.make("walker")
    wexp = build_experiment("walker", "dr", "quick")
    levels, labels, _ = evaluation.resolve_levels("named", walker, wexp, None)
    assert labels == list(LEVELS) and np.asarray(levels.roughness).shape == (len(LEVELS),)
    assert np.all(np.asarray(levels.fixed_terrain))
    np.testing.assert_array_equal(np.asarray(levels.terrain_seed), 1000 + np.arange(len(LEVELS)))
