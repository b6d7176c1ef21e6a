"""Presets: the docs/design.md §10.3 budgets, T kept in sync with the teacher's done flag, and every method
constructible from every preset through the registry (construction only; no compile)."""
import pytest

import envs
from shed_jax.methods.registry import METHODS, config_class, make_method
from shed_jax.presets import build_experiment
from shed_jax.student import make_student


def test_paper_lander_budget_matches_spec():
    e = build_experiment("lander", "shed", "paper")
    # C = 10 updates x 40 envs x 128 steps = 51,200; T = 20 -> 1.024e6 student steps per episode
    assert e.env_steps_per_budget_step == 51_200
    assert (e.loop.steps_per_episode, e.loop.num_episodes) == (20, 50)
    assert e.method_config.budget_steps == 20 and e.method_config.num_levels == 5
    assert (e.loop.test_episodes, e.loop.test_max_steps, e.test_set) == (10, 500, "lander-test")
    dr = build_experiment("lander", "dr", "paper")
    assert dr.loop.num_episodes == 1 and dr.loop.total_steps * dr.env_steps_per_budget_step == 1_024_000
    # the test set runs in teacher episodes 0, 10, ..., 40 and the last (49); baselines test always
    tested = [ep for ep in range(50) if e.loop.tests_at(ep * 20)]
    assert tested == [0, 10, 20, 30, 40, 49]
    assert dr.loop.test_episode_every == 1
    assert build_experiment("lander", "shed", "paper", test_episode_every=1).loop.test_episode_every == 1
    with pytest.raises(ValueError, match="test_episode_every"):  # 0 is an error, not "use the default"
        build_experiment("lander", "shed", "paper", test_episode_every=0)


def test_walker_paper_budget_is_1e7_steps():
    e = build_experiment("walker", "accel", "paper")
    assert e.env_steps_per_budget_step * e.loop.steps_per_episode == 1024 * 64 * 3 * 50  # 9.83e6
    shed = build_experiment("walker", "shed", "paper")  # docs/design.md §10.3: n = 4, E_eval = 4, N_ep = 20
    assert shed.method_config.num_levels == 4 and shed.method_config.num_eval_episodes == 4
    assert shed.loop.num_episodes == 20 and build_experiment("lander", "shed", "paper").method_config.num_eval_episodes == 8


def test_walker_students_draw_resets_per_rollout_and_the_lander_per_step():
    """The walkers' resets are costly (a terrain build each), so their students draw one per slot and
    rollout; the lander keeps the env's own auto-reset, the setting of every recorded lander result."""
    for env in ("walker", "bipedal"):
        for preset in ("paper", "quick"):
            assert build_experiment(env, "dr", preset).ppo.reset_draw == "per_rollout"
    assert build_experiment("lander", "shed", "paper").ppo.reset_draw == "per_step"
    assert build_experiment("walker", "dr", "quick", ppo_overrides={"reset_draw": "per_step"}).ppo.reset_draw == "per_step"


@pytest.mark.parametrize("method", ["dr", "shed"])
def test_bipedal_runs_the_walker_protocol_with_the_walker_student(method):
    """The physics2d walker shares the MJX walker's levels, so its presets, student and default final
    evaluation are the walker's; the method builds on it (construction only)."""
    from shed_jax.experiment import ENVS

    for preset in ("paper", "quick"):
        b, w = build_experiment("bipedal", method, preset), build_experiment("walker", method, preset)
        assert b.env == "bipedal" and (b.ppo, b.method_config, b.loop, b.test_set) == (w.ppo, w.method_config, w.loop, w.test_set)
    env = envs.make("bipedal")
    assert b.ppo.normalize_observations and "bipedal" in ENVS and env.ued.final_eval == "named"
    make_method(method, env, make_student(env, b.ppo), b.method_config)


def test_walker_baselines_test_every_fifth_budget_step_and_the_last():
    import numpy as np

    dr = build_experiment("walker", "dr", "paper").loop
    tested = np.flatnonzero(dr.tests_at(np.arange(dr.total_steps)))
    assert list(tested) == list(range(4, 50, 5))  # 10 points, the last step (49) among them
    shed = build_experiment("walker", "shed", "paper").loop  # the teacher: every step of its tested episodes
    assert shed.test_every == 1 and shed.test_episode_every == 10
    assert build_experiment("lander", "dr", "paper").loop.test_every == 1


def test_steps_per_episode_override_reaches_the_teacher():
    e = build_experiment("lander", "hmdp", "quick", steps_per_episode=7, episodes=3)
    assert e.loop.steps_per_episode == 7 and e.loop.num_episodes == 3 and e.method_config.budget_steps == 7


def test_bad_preset_and_env_are_named():
    with pytest.raises(ValueError, match="unknown preset"):
        build_experiment("lander", "shed", "fast")
    with pytest.raises(ValueError, match="cartpole"):
        build_experiment("cartpole", "shed", "quick")


@pytest.mark.parametrize("method", METHODS)
def test_every_method_builds_from_the_quick_preset(method):
    e = build_experiment("lander", method, "quick")
    env = envs.make(e.env)
    assert type(e.method_config) is config_class(method)  # the experiment holds the typed config
    m = make_method(method, env, make_student(env, e.ppo), e.method_config)
    assert m.name == method and m.config == e.method_config


def test_ppo_overrides_reach_the_student_config_and_the_cli_flag():
    import argparse

    from shed_jax import experiment as xp
    from shed_jax.cli import run as run_cli
    from shed_jax.student.config import parse_overrides

    # full-episode native rollouts for the lander: same C = 10 x 5,120 student steps per budget step
    e = build_experiment("lander", "dr", "paper", ppo_overrides=parse_overrides(["num_envs=8", "num_steps=640", "lr=1e-4"]))
    assert (e.ppo.num_envs, e.ppo.num_steps, e.ppo.hparams.lr) == (8, 640, 1e-4)
    assert e.env_steps_per_budget_step == 51_200
    assert e.ppo.hparams.gamma == build_experiment("lander", "dr", "paper").ppo.hparams.gamma  # the rest: preset
    assert e.to_dict()["ppo"]["num_steps"] == 640  # saved in config.json, so --resume rebuilds it
    p = argparse.ArgumentParser()
    run_cli.add_arguments(p)
    args = p.parse_args(["--env", "lander", "--method", "dr", "--preset", "quick", "--ppo", "num_steps=32"])
    assert xp.experiment_from_args(args, "cpu").ppo.num_steps == 32
    assert xp.experiment_flags_given(p.parse_args(["--ppo", "num_steps=32"]))  # checked against a resume
    with pytest.raises(SystemExit, match="unknown field 'num_step'"):
        xp.experiment_from_args(p.parse_args(["--ppo", "num_step=32"]), "cpu")
    with pytest.raises(ValueError, match="PPOConfig.num_envs must be a positive int"):  # PPOConfig validates
        build_experiment("lander", "dr", "paper", ppo_overrides={"num_envs": 0})
    with pytest.raises(ValueError, match="unknown field"):
        build_experiment("lander", "dr", "paper", ppo_overrides={"hparams": None})


def test_saved_configs_round_trip_and_older_ones_record_every_level():
    from shed_jax import experiment as xp

    e = build_experiment("walker", "dr", "paper")
    d = e.to_dict()
    assert d["loop"]["max_recorded_levels"] == 64 and xp.experiment_from_dict(d) == e
    # a config.json written before LoopSpec.max_recorded_levels existed keeps its old behaviour on
    # --resume: every level recorded, so the metrics arrays of its steps keep one shape
    del d["loop"]["max_recorded_levels"]
    assert xp.experiment_from_dict(d).loop.max_recorded_levels is None


def test_default_seeds_by_preset():
    from shed_jax import experiment as xp

    assert xp.default_seeds(build_experiment("walker", "dr", "quick")) == 2  # CPU too, now the deadlock is avoided
    assert xp.default_seeds(build_experiment("lander", "dr", "quick")) == 2
    assert xp.default_seeds(build_experiment("walker", "shed", "paper")) == 5


def test_default_chunk_keeps_walker_progress_under_a_minute():
    from shed_jax.presets import default_chunk

    # walker paper: 2 of the 50 budget steps per chunk (a SHED step costs ~15 s on an H200); else an episode
    assert default_chunk(build_experiment("walker", "shed", "paper")) == 2
    assert default_chunk(build_experiment("walker", "dr", "paper")) == 2
    # a T the preset's chunk does not divide: its largest divisor not above the chunk, never one long chunk
    assert default_chunk(build_experiment("walker", "dr", "paper", steps_per_episode=15)) == 1
    assert default_chunk(build_experiment("walker", "dr", "dcd", steps_per_episode=1001)) == 7
    assert default_chunk(build_experiment("walker", "dr", "dcd", steps_per_episode=3000)) == 8
    assert default_chunk(build_experiment("lander", "shed", "paper")) == 20
    assert default_chunk(build_experiment("walker", "shed", "quick")) == 4
    # runs and sweeps share the default (a walker sweep once ran its 50 budget steps as one chunk)
    from shed_jax import driver
    from shed_jax.experiment import build

    exp = build_experiment("walker", "dr", "paper")
    assert driver.make_batch(exp, build(exp), [({}, {})], num_seeds=1, root_seed=0).chunk == 2


@pytest.mark.parametrize("env", ["walker", "bipedal"])
def test_dcd_preset_is_dcds_budget_with_the_paper_student_and_twenty_test_points(env):
    import numpy as np

    from shed_jax import experiment as xp
    from shed_jax.presets import default_chunk

    paper, dr = build_experiment(env, "dr", "paper"), build_experiment(env, "dr", "dcd")
    steps = dr.env_steps_per_budget_step * dr.loop.steps_per_episode
    assert steps == 196_608 * 3360 and abs(steps / 6.6e8 - 1) < 1e-3  # DCD's 6.6e8 student steps, to 0.1 %
    assert dr.ppo == paper.ppo and dr.method_config == paper.method_config and dr.test_set == paper.test_set
    for method in ("dr", "accel", "shed"):  # one student: every method, the episodic ones in one teacher episode
        loop = build_experiment(env, method, "dcd").loop
        assert loop.num_episodes == 1
        tested = np.flatnonzero(loop.tests_at(np.arange(loop.total_steps)))
        assert list(tested) == list(range(167, 3360, 168))  # 20 points, the last step among them
    assert build_experiment(env, "shed", "dcd").method_config.budget_steps == 3360
    assert default_chunk(dr) == 8 and xp.default_seeds(dr) == 5
    assert dr.loop.max_recorded_levels == 8 and paper.loop.max_recorded_levels == 64  # a small record over 3,360 steps


def test_a_preset_an_env_lacks_names_the_env_s_presets():
    with pytest.raises(ValueError, match=r"environment 'lander' has no preset 'dcd'; its presets: quick, paper"):
        build_experiment("lander", "dr", "dcd")


def test_every_tested_episode_tests_its_last_step_whatever_its_length():
    import numpy as np

    def tested(loop):
        return list(np.flatnonzero(loop.tests_at(np.arange(loop.total_steps))))

    # a shortened DCD-budget run: T = 100 is no multiple of 168, yet its last step is tested
    assert tested(build_experiment("bipedal", "shed", "dcd", steps_per_episode=100).loop) == [99]
    # two episodes of 3,000: each tests at the same steps of the episode, its last one among them
    two = tested(build_experiment("bipedal", "shed", "dcd", steps_per_episode=3000, episodes=2).loop)
    per_episode = list(range(167, 3000, 168)) + [2999]
    assert two == per_episode + [3000 + t for t in per_episode]
    # the walker's baselines at T = 12 (every 5th step): steps 4, 9 and the last, 11
    assert tested(build_experiment("walker", "dr", "paper", steps_per_episode=12).loop) == [4, 9, 11]
    # schedules whose T the period divides are unchanged
    assert tested(build_experiment("walker", "dr", "paper").loop) == list(range(4, 50, 5))
