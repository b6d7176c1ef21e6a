"""``python -m shed_jax sweep`` through the host driver, as tests/test_run_cli.py checks ``run``: user
errors leave no sweep directory, the compile lines, a sweep of one point equal to the run of the same
seeds, a failed save in one line and a resume after it, the non-finite guard, signals in start-up.

The sweep's experiment is test_checkpoint.py's tiny CartPole PLR run (its preset patched in): a
group of one point and two seeds compiles the run's very program, so the persistent compilation
cache serves both, and its records must equal the run's byte for byte.
"""
import argparse
import contextlib
import dataclasses
import errno
import io
import json
import signal

import pytest

from shed_jax import checkpoint as ck
from shed_jax import configs
from shed_jax import errors
from shed_jax import sweep
from shed_jax.__main__ import main
from shed_jax.cli import sweep as sweep_cli

# the tiny CartPole experiment, its test levels, the patched run CLI and the straight run are test_checkpoint's
from test_checkpoint import cartpole_test_levels, patched, run_a, tiny_experiment  # noqa: E402,F401
from test_run_cli import error_line, failing_save, signal_as_the_evaluation_compiles, signal_during_compile, snapshot  # noqa: E402,E501

SEEDS = 2
BASE = ["--methods", "plr", "--seeds", str(SEEDS), "--chunk", "1"]


@pytest.fixture
def tiny_sweep(patched, monkeypatch):
    """The sweep command on the tiny experiment (its preset: tiny_experiment with the group's overrides)."""
    def make(env, preset, episodes=None, steps_per_episode=None, test_episode_every=None):
        def experiment(method, method_overrides, ppo_overrides):
            exp = tiny_experiment(**ppo_overrides)
            return dataclasses.replace(exp, method_config=configs.with_overrides(exp.method_config, method_overrides))
        return experiment

    monkeypatch.setattr(sweep, "preset_experiment", make)


def run_sweep_cli(argv):
    """``cli.sweep.main`` with stdout and stderr captured: (exit code, stdout, stderr)."""
    p = argparse.ArgumentParser()
    sweep_cli.add_arguments(p)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = sweep_cli.main(p.parse_args(argv))
    return code, out.getvalue(), err.getvalue()


@pytest.fixture
def cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.parametrize("argv, message", [
    (["--seeds", "0"], "argument --seeds: must be an integer >= 1, got 0"),
    (["--time-limit", "-5"], "argument --time-limit: must be a finite number >= 0, got -5"),
    (["--methods", "shed,shed"], "--methods lists a method twice: shed,shed"),
    (["--methods", ""], "--methods needs at least one method of"),
    (["--devices", "9"], "--devices must lie in [1, 1] (visible devices), got 9"),
    (["--grid", "eta=0,abc"], "sweep: method 'shed': hyperparameter eta needs a number, got 'abc'"),
    (["--set", "num_levels=0"], "sweep: SHEDConfig.num_levels must be a positive int, got 0"),
    (["--final-eval", "hard"], "sweep: --final-eval: --levels must be 'test', 'named' or an existing JSON file"),
    (["--resume", "nowhere"], "--resume nowhere: no sweep_args.json there"),
    (["--checkpoint-every", "60", "--no-checkpoint"], "--checkpoint-every sets how often checkpoints are saved and --no-checkpoint saves none"),
])
def test_user_errors_are_one_line_exit_2_and_leave_no_sweep_dir(cwd, capsys, argv, message):
    assert main(["sweep", "--preset", "quick", *argv]) == errors.EXIT_USAGE
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith("shed_jax: error:")]
    assert len(lines) == 1 and message in lines[0], err
    assert list(cwd.iterdir()) == []  # no runs/sweep-... directory for a sweep that never started


def test_a_sweep_of_one_point_is_the_run_and_a_signal_as_it_writes_its_results_lets_them_be_written(
        tiny_sweep, run_a, tmp_path, monkeypatch):
    """The sweep compiles and says so as run does, and its one point's records are the run's, byte for
    byte. A signal as its group's final evaluation compiles (after training) says that the group's
    results are written first, and they are (one sweep for both checks: the signal comes after every
    record is written)."""
    from shed_jax import driver

    s = tmp_path / "S"
    monkeypatch.setattr(driver, "in_worker", signal_as_the_evaluation_compiles(signal.SIGTERM))
    code, out, err = run_sweep_cli(["--out", str(s), *BASE, "--final-eval", "test", "--final-eval-episodes", "2"])
    assert "SIGTERM: writing the results of plr, then stopping before the next group" in err, out + err
    assert "finishing the current chunk" not in err
    assert (s / "plr" / "default" / "summary.json").exists() and (s / "plr" / "default" / "final_eval_test.json").exists()
    assert code == 0, out + err  # the last group: nothing was left to stop
    lines = out.splitlines()

    def index(text):
        hits = [i for i, line in enumerate(lines) if text in line]
        assert hits, f"{text!r} not in:\n{out}"
        return hits[0]

    compiling = index("[shed_jax] compiling the initial state and a chunk of 1 budget step(s)")
    assert compiling < index("[shed_jax] compiled in ") < index("plr: step 1/4") < index("plr: step 4/4")
    assert (s / "plr" / "default" / "metrics.jsonl").read_text() == (run_a / "metrics.jsonl").read_text()
    summary = json.loads((s / "plr" / "default" / "summary.json").read_text())
    run_summary = json.loads((run_a / "summary.json").read_text())
    for k in ("final_test_return_mean", "final_test_return_per_level", "student_env_steps_total", "budget_steps"):
        assert summary[k] == run_summary[k], k
    assert json.loads((s / sweep.ARGS_FILE).read_text())["methods"] == "plr"


def test_failed_save_is_one_line_and_the_sweep_resumes(tiny_sweep, run_a, tmp_path):
    f = tmp_path / "F"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ck.RunCheckpointer, "save", failing_save(3, OSError(errno.ENOSPC, "No space left on device")))
        code, out, err = run_sweep_cli(["--out", str(f), *BASE])
    line = error_line(err)
    ckpts = f / "checkpoints" / "plr" / "checkpoints"
    assert code == errors.EXIT_IO == 74
    assert line == (f"shed_jax: error: disk full (No space left on device) while saving checkpoint 3 in {ckpts}; "
                    f"safe on disk: checkpoint 2 of plr in {ckpts} (and its points' metrics.jsonl up to it), and the "
                    f"groups finished before; after freeing space continue with: python -m shed_jax sweep --resume {f}")
    # step 3's line comes when it is computed; its save fails in the writer thread while step 4 runs,
    # and the error (above) names checkpoint 2 as the one safe on disk; step 4 is never reported
    assert "plr: step 3/4" in out and "plr: step 4/4" not in out
    assert not (f / "plr" / "default" / "summary.json").exists()
    code, out, err = run_sweep_cli(["--resume", str(f)])
    assert code == 0, err
    assert "resumed at budget step 2/4" in out
    assert (f / "plr" / "default" / "metrics.jsonl").read_text() == (run_a / "metrics.jsonl").read_text()


@pytest.mark.parametrize("every", [[], ["--checkpoint-every", "1e6"]], ids=["every-chunk", "checkpoint-every"])
def test_nonfinite_guard_stops_the_sweep_without_saving_the_chunk(tiny_sweep, tmp_path, monkeypatch, every):
    """The bad chunk is not saved; the last good one is, also when --checkpoint-every skipped its save."""
    g = tmp_path / "G"
    original = ck.find_nonfinite

    def guard(metrics, state=None, start_step=0, tests_at=None):
        return ["metric test_return: NaN/Inf in 1 value(s) (seed(s) [1]), first at budget step 2"] if start_step == 2 \
            else original(metrics, state, start_step, tests_at)

    monkeypatch.setattr(ck, "find_nonfinite", guard)
    code, out, err = run_sweep_cli(["--out", str(g), *BASE, *every])
    assert code == errors.EXIT_NONFINITE == 3
    assert "[shed_jax] plr: non-finite values in budget steps 2-2; stopping without saving this chunk" in err
    assert f"this chunk's metrics: {g / 'plr' / 'default' / 'nonfinite_chunk.jsonl'}; the last good checkpoint is step 2" in err
    with ck.RunCheckpointer(g / "checkpoints" / "plr", create=False) as reader:
        assert reader.steps() == [2]
    assert len((g / "plr" / "default" / "metrics.jsonl").read_text().splitlines()) == 2 * SEEDS


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_during_startup_stops_at_once_and_keeps_nothing(tiny_sweep, tmp_path, monkeypatch, signum):
    from shed_jax import driver

    e = tmp_path / "E"
    before = signal.getsignal(signum)
    monkeypatch.setattr(driver, "in_worker", signal_during_compile(signum))
    code, out, err = run_sweep_cli(["--out", str(e), *BASE])
    assert code == 128 + signum
    assert f"[shed_jax] {signal.Signals(signum).name} during start-up, before the first budget step: stopped; nothing was kept" in err
    assert "Traceback" not in err and not e.exists()  # the command can simply be run again
    assert signal.getsignal(signum) == before


def test_signal_during_resume_startup_names_the_resume(tiny_sweep, tmp_path, monkeypatch):
    h = tmp_path / "H"
    code, _, err = run_sweep_cli(["--out", str(h), *BASE, "--time-limit", "0"])
    assert code == errors.EXIT_STOPPED, err
    before = snapshot(h)
    monkeypatch.setattr("shed_jax.driver.in_worker", signal_during_compile(signal.SIGTERM))
    code, _, err = run_sweep_cli(["--resume", str(h)])
    assert code == 143 and ("SIGTERM during start-up, before the first budget step: stopped; continue it with: "
                            f"python -m shed_jax sweep --resume {h}") in err
    assert {k: v for k, v in snapshot(h).items() if k.startswith("checkpoints")} == \
        {k: v for k, v in before.items() if k.startswith("checkpoints")}
