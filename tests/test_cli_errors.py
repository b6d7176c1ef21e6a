"""User errors of ``python -m shed_jax run``: one line on stderr, exit 2, no traceback, nothing written.

Every case here fails before anything is compiled (the real lander presets are built, which is
host-side only), through ``shed_jax.__main__.main`` exactly as the command line runs it. The
run-directory behaviours (resume, restart, damage, signals, full disks) are tests/test_run_cli.py.
"""
import argparse
import errno
import json
import re

import pytest

from shed_jax import errors as lib_errors
from shed_jax import experiment as xp
from shed_jax.__main__ import main
from shed_jax.cli import errors
from shed_jax.cli import run as run_cli
from shed_jax.presets import build_experiment
from shed_jax.teacher.reward import RewardConfig


def error_line(capsys) -> str:
    """The one 'shed_jax: error:' line of stderr; fails on a traceback or a second error line."""
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith(errors.PREFIX)]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture
def cwd(tmp_path, monkeypatch):
    """An empty working directory: the default --out (runs/...) would appear here."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.parametrize("argv, message", [
    # zero and negative counts are refused, not replaced by a default
    (["--seeds", "0"], "argument --seeds: must be an integer >= 1, got 0"),
    (["--episodes", "0"], "argument --episodes: must be an integer >= 1, got 0"),
    (["--steps-per-episode", "0"], "argument --steps-per-episode: must be an integer >= 1, got 0"),
    (["--steps-per-episode", "-3"], "argument --steps-per-episode: must be an integer >= 1, got -3"),
    (["--test-episode-every", "0"], "argument --test-episode-every: must be an integer >= 1, got 0"),
    (["--chunk", "0"], "argument --chunk: must be an integer >= 1, got 0"),
    (["--keep", "0"], "argument --keep: must be an integer >= 1, got 0"),
    (["--final-eval-episodes", "0"], "argument --final-eval-episodes: must be an integer >= 1, got 0"),
    (["--stop-after", "-1"], "argument --stop-after: must be an integer >= 1, got -1"),
    (["--seeds", "two"], "argument --seeds: must be an integer >= 1, got 'two'"),
    (["--time-limit", "-5"], "argument --time-limit: must be a finite number >= 0, got -5"),
    # names: the allowed values are listed
    (["--env", "foo"], "argument --env: invalid choice: 'foo' (choose from 'lander', 'lander-continuous', 'walker', 'bipedal')"),
    (["--method", "bogus"], "argument --method: invalid choice: 'bogus' (choose from 'dr', 'plr'"),
    # config fields: the field and what it takes
    (["--set", "bogus=1"], "--set: method 'shed' has no config field(s) 'bogus'; known: actor_lr, budget_steps"),
    (["--method", "dr", "--set", "eta=10"], "--set: method 'dr' has no config field(s) 'eta'; known: distribution, high"),
    (["--set", "psi=abc"], "--set psi: expected a number, got \"abc\""),
    (["--set", "eta=high"], "--set reward.eta: expected a number, got \"high\""),
    (["--set", 'reward={"etta": 1}'], "--set reward: RewardConfig has no field(s) 'etta'; known: code_cv"),
    (["--set", "num_levels=0"], "SHEDConfig.num_levels must be a positive int, got 0"),
    (["--set", "low=[1,2]"], "--set low: expected a list of 3 numbers for lander (gravity, wind_power, turbulence_power), "
                             "e.g. low=[-9,0.01,0.01], got [1, 2]"),
    (["--method", "dr", "--set", "high=[-1, 2]"], "--set high: expected a list of 3 numbers for lander"),
    (["--ppo", "lr=-1"], "PPOHyperparams.lr must be a finite value in (0.0, inf), got -1.0"),
    (["--ppo", "num_step=32"], "--ppo: unknown field 'num_step'"),
    (["--final-eval", "hard"], "--final-eval: --levels must be 'test', 'named' or an existing JSON file; 'hard' is none of these"),
    (["--final-eval", "test,none"], "--final-eval: 'none' cannot be combined with level sets"),
    # flag combinations
    (["--from-step", "2"], "--from-step N chooses the checkpoint that --resume DIR continues from"),
    (["--restart"], "--restart clears the run directory given with --out DIR: give --out"),
    (["--checkpoint-every", "60", "--no-checkpoint"], "--checkpoint-every sets how often checkpoints are saved and --no-checkpoint saves none"),
    (["--checkpoint-every", "inf"], "argument --checkpoint-every: must be a finite number >= 0, got inf"),
    (["--resume", "nowhere"], "--resume nowhere: no run directory nowhere"),
])
def test_user_errors_are_one_line_exit_2_and_leave_nothing(cwd, capsys, argv, message):
    assert main(["run", "--preset", "quick", *argv]) == errors.EXIT_USAGE
    line = error_line(capsys)
    assert message in line, line
    assert list(cwd.iterdir()) == []  # no runs/... directory for a run that never started


def test_out_pointing_at_a_file_is_refused(cwd, capsys):
    (cwd / "afile").write_text("x")
    assert main(["run", "--preset", "quick", "--out", "afile"]) == 2
    assert "--out afile is a file, not a directory" in error_line(capsys)
    assert sorted(p.name for p in cwd.iterdir()) == ["afile"]


def test_debug_shows_the_traceback_of_user_errors(cwd, capsys, monkeypatch):
    assert main(["run", "--preset", "quick", "--set", "bogus=1", "--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "UsageError" in err and err.rstrip().splitlines()[-1].startswith(errors.PREFIX)
    assert main(["--debug", "run", "--preset", "quick", "--set", "bogus=1"]) == 2  # before the command too
    assert "Traceback" in capsys.readouterr().err
    monkeypatch.setenv("SHED_JAX_DEBUG", "1")
    assert main(["run", "--preset", "quick", "--set", "bogus=1"]) == 2
    assert "Traceback" in capsys.readouterr().err
    monkeypatch.setenv("SHED_JAX_DEBUG", "0")
    assert main(["run", "--preset", "quick", "--set", "bogus=1"]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_bugs_keep_their_traceback(monkeypatch):
    """Anything but a user error propagates (Python prints the traceback, exit 1)."""
    def broken(args):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(run_cli, "main", broken)
    with pytest.raises(ZeroDivisionError, match="a bug"):
        main(["run"])


def test_a_plain_system_exit_message_is_a_usage_error(monkeypatch, capsys):
    monkeypatch.setattr(run_cli, "main", lambda args: (_ for _ in ()).throw(SystemExit("--x must be 1")))
    assert main(["run"]) == 2
    assert error_line(capsys) == "shed_jax: error: --x must be 1"


def parse(argv):
    p = argparse.ArgumentParser()
    run_cli.add_arguments(p)
    return p.parse_args(argv)


def test_set_routes_teacher_reward_keys_into_reward():
    """docs/running.md's `--set eta=10`: eta is a field of the teacher reward (RewardConfig), which
    SHEDConfig holds as `reward`; the key goes there, merged with a `reward` given as well."""
    exp = xp.experiment_from_args(parse(["--preset", "quick", "--set", "eta=10"]), "cpu")
    assert exp.method_config.reward == RewardConfig(eta=10)
    exp = xp.experiment_from_args(parse(["--preset", "quick", "--method", "hmdp", "--set", 'reward={"form": "signed_sum"}',
                                              "--set", "eta=10", "--set", "code_cv_weight=0.5"]), "cpu")
    assert exp.method_config.reward == RewardConfig(form="signed_sum", eta=10, code_cv_weight=0.5)
    _, _, method, _ = xp.build(exp)
    assert (method.config.reward.form, method.config.reward.eta) == ("signed_sum", 10)
    assert method.default_hparams.eta == 10.0  # the dynamic eta the teacher's reward uses
    # a later reward dict merges, an own field of the method is never routed
    assert xp.route_method_overrides("shed", {"eta": 1, "reward": {"form": "code_mean"}, "psi": 0.5}) == {
        "reward": {"eta": 1, "form": "code_mean"}, "psi": 0.5}
    assert xp.route_method_overrides("dr", {"eta": 1}) == {"eta": 1}  # no reward there: refused later


def test_presets_refuse_zero_counts_instead_of_using_the_default():
    with pytest.raises(ValueError, match="LoopSpec.num_episodes must be >= 1, got 0"):
        build_experiment("lander", "shed", "quick", episodes=0)
    with pytest.raises(ValueError, match="LoopSpec.steps_per_episode must be >= 1, got 0"):
        build_experiment("lander", "dr", "quick", steps_per_episode=0)
    e = build_experiment("lander", "shed", "quick", episodes=3, steps_per_episode=5)
    assert (e.loop.num_episodes, e.loop.steps_per_episode, e.method_config.budget_steps) == (3, 5, 5)


def test_disk_full_is_recognised_when_wrapped():
    full = OSError(errno.ENOSPC, "No space left on device")
    assert lib_errors.is_disk_full(full)
    try:
        try:
            raise full
        except OSError as inner:
            raise RuntimeError("orbax: save failed") from inner
    except RuntimeError as wrapped:
        assert lib_errors.is_disk_full(wrapped) and lib_errors.os_error_in(wrapped) is full
    assert lib_errors.is_disk_full(ExceptionGroup("saves", [ValueError("x"), full]))
    assert lib_errors.is_disk_full(ValueError("DATA_LOSS: write failed: No space left on device [tensorstore_spec=...]"))
    assert not lib_errors.is_disk_full(OSError(errno.EACCES, "Permission denied"))
    assert lib_errors.io_reason(full) == "disk full (No space left on device)"
    assert lib_errors.io_reason(PermissionError(errno.EACCES, "Permission denied", "/x")) == "Permission denied (/x)"
    assert lib_errors.one_line('a\n  b [tensorstore_spec=\'{"x": 1}\']') == "a b"


def test_usage_error_is_one_line_and_exit_2():
    err = lib_errors.UsageError("first\nsecond   part")
    assert str(err) == "first second part" and err.code == 2 and isinstance(err, SystemExit)
    assert json.loads(json.dumps(str(err))) == "first second part"


def test_ppo_unknown_level_is_one_line_and_the_bipedal_walker_has_dcds_levels(cwd, capsys):
    from shed_jax.evaluation import find_levels
    from shed_jax.training import resolve_level
    import envs
    from envs.walker.levels import LEVELS

    assert main(["ppo", "--env", "cartpole", "--level", "mars"]) == errors.EXIT_USAGE
    line = error_line(capsys)
    assert "--level: cartpole: unknown level 'mars'; known:" in line, line
    assert list(cwd.iterdir()) == []
    bipedal = envs.make("bipedal")  # shares the MJX walker's named levels (and builds no physics here)
    assert find_levels(bipedal) is LEVELS
    assert resolve_level(bipedal, "Stairs") == LEVELS["Stairs"]()


def test_ppo_command_takes_the_student_overrides_of_run(cwd, capsys):
    """`ppo --ppo KEY=VALUE` applies fields as `run --ppo` does (with --lr and --num-envs folded in), and a
    bad one is one line before anything is built."""
    import argparse

    from shed_jax.cli import ppo as ppo_cli

    args = argparse.Namespace(env="walker", ppo=["reset_draw=per_step", "num_steps=32"], num_envs=16, lr=1e-4)
    cfg = ppo_cli.ppo_config(args)
    assert (cfg.reset_draw, cfg.num_steps, cfg.num_envs, cfg.hparams.lr) == ("per_step", 32, 16, 1e-4)
    assert cfg.update_epochs == 10 and cfg.normalize_observations  # the rest is the walker preset
    assert ppo_cli.ppo_config(argparse.Namespace(env="walker", ppo=[], num_envs=None, lr=None)).reset_draw == "per_rollout"
    assert main(["ppo", "--env", "cartpole", "--ppo", "reset_draw=once"]) == errors.EXIT_USAGE
    assert "PPOConfig.reset_draw must be one of 'per_step', 'per_rollout', got 'once'" in error_line(capsys)
    assert main(["ppo", "--env", "cartpole", "--ppo", "num_step=32"]) == errors.EXIT_USAGE
    assert "--ppo: unknown field 'num_step'" in error_line(capsys)
    assert main(["ppo", "--env", "cartpole", "--lr", "1e-3", "--ppo", "lr=1e-4"]) == errors.EXIT_USAGE
    assert "--lr and --ppo lr=... both given; give one" in error_line(capsys)
    assert list(cwd.iterdir()) == []


def test_run_help_names_every_registered_method(capsys):
    # the --method help and the command list are what a user reads first; a method added to the
    # registry must appear in both
    from shed_jax.__main__ import COMMANDS
    from shed_jax.methods.registry import METHODS

    assert main(["run", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    listed = re.search(r"--method \{[^}]*\} (.*?) \(default", text).group(1).split(" | ")
    assert listed == list(METHODS)
    for m in METHODS:
        assert re.search(rf"(?<![\w-]){re.escape(m)}(?![\w-])", COMMANDS["run"]), m  # 'shed' not inside 'shed-x'


def test_a_commands_exit_code_is_returned_so_the_process_can_end_at_once(monkeypatch):
    # a second SIGTERM raises SystemExit(143) inside a command; main returns the code (and
    # shed_jax.__main__._exit then ends the process at once if a worker thread is still in XLA)
    from shed_jax.cli import eval as eval_cli

    def second_signal(args):
        raise SystemExit(143)

    monkeypatch.setattr(eval_cli, "main", second_signal)
    assert main(["eval", "--run", "nowhere"]) == 143
    monkeypatch.setattr(eval_cli, "main", lambda args: (_ for _ in ()).throw(SystemExit(None)))
    with pytest.raises(SystemExit):  # a bare exit still exits as before
        main(["eval", "--run", "nowhere"])
