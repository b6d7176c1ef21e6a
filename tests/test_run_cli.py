"""``python -m shed_jax run`` on run directories: resuming against the saved configuration, a finished
run left alone, --restart of a run without a checkpoint, damaged checkpoints and --from-step,
signals during start-up, failed writes (disk full), the progress lines and the per-level plot.

The run is test_checkpoint.py's tiny CartPole PLR experiment, driven in-process (same program, so
the persistent compilation cache serves both); one finished run (module fixture) is copied for
the cases that change a directory. Equality with that run is the check wherever a run continues.
"""
import argparse
import contextlib
import errno
import io
import json
import os
import re
import shutil
import signal
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from shed_jax import checkpoint as ck
from shed_jax import driver, errors, reporting, rundir
from shed_jax import experiment as xp
from shed_jax.cli import run as run_cli
from shed_jax.loop import make_run

# the tiny CartPole experiment, its test levels and the patched CLI are test_checkpoint's
from test_checkpoint import cartpole_test_levels, parse, patched, straight_run, tiny_experiment  # noqa: E402,F401

SEEDS = 2
BASE = ["--seeds", str(SEEDS), "--chunk", "1"]


def run(argv):
    """``run_cli.main`` with stdout and stderr captured: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = run_cli.main(parse(argv))
    return code, out.getvalue(), err.getvalue()


def error_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith("shed_jax: error:")]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="module")
def finished(patched, tmp_path_factory):
    """A: the tiny run straight through (4 chunks of 1 step, --final-eval test, the GIF attempted),
    with the order of the compile and of the progress bar's creation recorded: test_checkpoint's run
    A (made once per process, shared with test_checkpoint and test_sweep_cli)."""
    return straight_run(tmp_path_factory)


def copy_of(finished, tmp_path, name="copy"):
    return shutil.copytree(finished["dir"], tmp_path / name)


def same_records(a, b):
    assert (b / "metrics.jsonl").read_text() == (a / "metrics.jsonl").read_text()


def snapshot(d):
    return {str(p.relative_to(d)): (p.stat().st_mtime_ns, p.stat().st_size) for p in d.rglob("*") if p.is_file()}


# ---- progress --------------------------------------------------------------------------------

def test_progress_says_compiling_and_each_post_run_stage(finished):
    out = finished["out"]
    lines = out.splitlines()

    def index(text):
        hits = [i for i, line in enumerate(lines) if text in line]
        assert hits, f"{text!r} not in:\n{out}"
        return hits[0]

    compiling = index("[shed_jax] compiling the initial state and a chunk of 1 budget step(s)")
    compiled = index("[shed_jax] compiled in ")
    assert compiling < compiled < index("step     1/4") < index("step     4/4")
    assert float(lines[compiled].split("compiled in ")[1].split(" s")[0]) >= 0
    from shed_jax.driver import RUN_PROGRAMS
    for program in RUN_PROGRAMS:  # each looked up in the persistent cache: compiled (said at once) or read (named)
        missed = any(f"[shed_jax] {program} is not in the compilation cache (key {program}-" in line
                     for line in lines[compiling:compiled])
        assert missed != (program in lines[compiled]), out
    done = index("[shed_jax] training done (4/4 budget steps); writing the plots and summary.json")
    final = index("[shed_jax] final evaluation on 'test': 2 level(s) x 2 seed(s) x 3 episode(s)")
    gif = index("[shed_jax] rendering a GIF of seed 0's final student")
    assert index("step     4/4") < done < final < gif < index("no GIF: environment 'cartpole' has no renderer")
    # the bar (its rate and ETA) starts after the compile, so neither counts it; the final evaluation
    # compiles and runs in workers too (a heartbeat line while either takes long); each of the 4 chunks
    # runs in a worker, so that a signal is handled while XLA holds the thread that waits for it
    assert finished["events"] == [("compile", "compiling"), "bar",
                                  *[("chunk", f"training budget steps {i}-{i} of 4") for i in range(1, 5)],
                                  ("eval", "compiling"), ("eval", "evaluating")]


def test_chunk_sizes_compiled_ahead():
    assert driver.chunk_sizes(1, 0, 4) == [1]
    assert driver.chunk_sizes(3, 0, 4) == [3, 1]
    assert driver.chunk_sizes(4, 0, 8) == [4]
    assert driver.chunk_sizes(3, 2, 4) == [2]
    assert driver.chunk_sizes(5, 0, 4) == [4]
    assert driver.chunk_sizes(2, 4, 4) == []


def test_per_level_and_student_plots_are_small_multiples(finished, monkeypatch, tmp_path):
    a = finished["dir"]
    with ck.RunCheckpointer(a, create=False) as reader:
        hist = reader.read_history()
    seen = {}
    original = reporting.plot_panels

    def spy(x, series, path, **kw):
        seen[path.name] = dict(x=np.asarray(x), series=np.asarray(series), **kw)
        return original(x, series, path, **kw)

    monkeypatch.setattr(reporting, "plot_panels", spy)
    import envs

    driver.make_plots(tiny_experiment(), envs.make("cartpole"), hist, tmp_path)
    per_level = seen["test_return_per_level.png"]
    assert per_level["series"].shape == (SEEDS, 4, 2)
    np.testing.assert_array_equal(per_level["x"], np.cumsum(hist["info/env_steps_train"][0].astype(np.float64)))
    # the student's PPO statistics: one panel each, the run's values per budget step, own y scales
    student = seen["student_training.png"]
    assert student["names"] == [name for _, name in reporting.STUDENT_PANELS] and student["sharey"] is False
    assert student["series"].shape == (SEEDS, 4, len(reporting.STUDENT_PANELS))
    np.testing.assert_array_equal(student["x"], np.arange(4))
    for j, (key, _) in enumerate(reporting.STUDENT_PANELS):
        np.testing.assert_array_equal(student["series"][..., j], hist[f"info/extras/ppo/{key}"].astype(np.float64))
    from PIL import Image

    with Image.open(tmp_path / "test_return_per_level.png") as im:
        w, h = im.size
    assert w > 1.5 * h  # two panels side by side, not one axis with two overlaid bands
    with Image.open(tmp_path / "student_training.png") as im:
        w, h = im.size
    assert w > 1.2 * h  # two rows of three panels


# ---- resuming ---------------------------------------------------------------------------------

def test_resume_checks_flags_against_the_saved_run(finished):
    a = finished["dir"]
    before = snapshot(a)
    # the saved values (and a preset default the saved run used) are no difference
    for flags in (["--set", "updates_per_step=1"], ["--ppo", "num_steps=8"], ["--seeds", "2", "--seed", "0"],
                  ["--set", 'sampler={"capacity": 4, "min_fill": 0.5, "replay_prob": 0.9}'], ["--episodes", "1"]):
        code, out, err = run(["--resume", str(a), *flags])
        assert code == 0, (flags, err)
        assert "holds a finished run (budget step 4/4" in out and "nothing to do" in out
    # a different value is refused, naming only that field with the saved and the new value
    code, _, err = run(["--resume", str(a), "--set", "updates_per_step=2"])
    line = error_line(err)
    assert code == 2 and "experiment.method_config.updates_per_step: saved 1, now 2" in line
    assert line.count(": saved ") == 1
    code, _, err = run(["--resume", str(a), "--method", "dr", "--seeds", "3"])
    line = error_line(err)
    assert "experiment.method: saved 'plr', now 'dr'" in line and "seeds: saved 2, now 3" in line and line.count(": saved ") == 2
    with pytest.raises(SystemExit, match=r"--set: method 'plr' has no config field\(s\) 'nope'; known: high, level_switch, low"):
        run(["--resume", str(a), "--set", "nope=1"])
    # a finished run is left as it was: no summary, plot or checkpoint rewritten
    assert snapshot(a) == before


def test_restart_of_a_run_without_checkpoint(finished, patched, tmp_path):
    a = finished["dir"]
    d = tmp_path / "D"  # killed after its first records, before its first checkpoint completed
    (d / "checkpoints" / "1.orbax-checkpoint-tmp-17").mkdir(parents=True)
    shutil.copy(a / "config.json", d / "config.json")
    (d / "metrics.jsonl").write_text("".join((a / "metrics.jsonl").read_text().splitlines(keepends=True)[:SEEDS]))
    (d / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit, match=r"stopped before its first checkpoint .*start it over with --restart"):
        run_cli.main(parse(["--out", str(d), *BASE]))
    code, _, err = run(["--resume", str(d)])
    assert code == 2 and "holds no complete checkpoint" in error_line(err) and f"--out {d} --restart" in err
    code, out, err = run(["--out", str(d), "--restart", *BASE])
    assert code == 0, err
    assert "--restart: removed checkpoints/, config.json, metrics.jsonl from" in out
    same_records(a, d)  # the same seeds from scratch: the very same records
    assert (d / "notes.txt").read_text() == "mine"  # only the run's own files are cleared
    # a directory holding a checkpoint (or a finished run) is not cleared
    with pytest.raises(SystemExit, match=r"already holds a run with checkpoint\(s\) at budget step\(s\) 2, 3, 4; continue it with --resume"):
        run_cli.main(parse(["--out", str(a), "--restart", *BASE]))


# ---- damaged checkpoints ----------------------------------------------------------------------

def test_damaged_newest_checkpoint_is_named_and_older_ones_continue(finished, patched, tmp_path):
    a = finished["dir"]
    d = copy_of(finished, tmp_path, "truncated")
    (d / "summary.json").unlink()
    for f in (d / "checkpoints" / "4" / "state").rglob("d/*"):
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    code, _, err = run(["--resume", str(d)])
    line = error_line(err)
    assert code == errors.EXIT_CHECKPOINT
    assert f"checkpoint {d}/checkpoints/4 is damaged" in line
    assert "intact older checkpoint(s): 3, 2" in line and f"--resume {d} --from-step 3" in line
    assert len(line) < 1000 and "tensorstore_spec" not in line
    # --from-step 3 continues from there: the same records and final state as the straight run
    code, out, err = run(["--resume", str(d), "--from-step", "3"])
    assert code == 0, err
    assert "moved checkpoint(s) 4 to" in out and "resuming" in out and "from budget step 3/4" in out
    assert (d / rundir.DISCARDED_DIR / "4" / "state").is_dir()
    same_records(a, d)
    target = jax.eval_shape(jax.vmap(make_run(*xp.build(tiny_experiment())[1:], tiny_experiment().loop)[0]),
                            xp.seed_keys(0, SEEDS))
    with ck.RunCheckpointer(a, create=False) as ra, ck.RunCheckpointer(d, create=False) as rd:
        x, y = ra.restore(target), rd.restore(target)
    for p, u, v in zip(jax.tree_util.tree_leaves_with_path(x.state), jax.tree_util.tree_leaves(x.state),
                       jax.tree_util.tree_leaves(y.state)):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(v), err_msg=ck.path_name(p[0]))
    code, _, err = run(["--resume", str(d), "--from-step", "9"])
    assert code == 2 and "--from-step 9" in error_line(err) and "complete: 2, 3, 4" in err


def test_lost_state_metadata_reads_as_damage_not_as_another_configuration(finished, patched, tmp_path):
    d = copy_of(finished, tmp_path, "nometa")
    (d / "checkpoints" / "4" / "state" / "_METADATA").unlink()
    code, _, err = run(["--resume", str(d)])
    line = error_line(err)
    assert code == 2 and "checkpoints/4 is damaged: the array metadata of its state is missing" in line
    assert "does not match" not in line and "intact older checkpoint(s): 3, 2" in line


# ---- signals during start-up ------------------------------------------------------------------

def signal_during_compile(signum):
    """A stand-in for the compile worker that receives ``signum`` (sent from the worker thread, as
    from outside: the main thread handles it while it waits)."""
    def worker(fn, name="compile", **kwargs):
        def send():
            time.sleep(0.05)
            os.kill(os.getpid(), signum)

        t = threading.Thread(target=send)
        t.start()
        while t.is_alive():
            t.join(0.05)
        time.sleep(1.0)  # the handler runs in this wait, as in driver.in_worker's
        raise AssertionError("the signal did not stop the start-up")

    return worker


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_during_startup_stops_at_once_and_keeps_nothing(patched, tmp_path, monkeypatch, signum):
    e = tmp_path / "E"
    before = signal.getsignal(signum)
    monkeypatch.setattr(driver, "in_worker", signal_during_compile(signum))
    monkeypatch.setattr(driver, "EXIT_AT_ONCE", threading.Event())
    code, out, err = run(["--out", str(e), *BASE])
    assert code == 128 + signum
    assert driver.EXIT_AT_ONCE.is_set()  # XLA may still work in its threads: python -m shed_jax exits at once
    assert f"[shed_jax] {signal.Signals(signum).name} during start-up, before the first budget step: stopped; nothing was kept" in err
    assert "Traceback" not in err and not e.exists()  # the command can simply be run again
    assert signal.getsignal(signum) == before


@pytest.mark.parametrize("at_once", [False, True])
def test_exit_skips_the_interpreter_shutdown_after_an_interrupted_start_up(monkeypatch, at_once):
    """A shutdown under XLA's compile or execution threads aborts the process ("terminate called ...",
    exit 134, seen on a 2-D walker run interrupted 160 s into its compile); os._exit does not."""
    import shed_jax.__main__ as cli_main

    event = threading.Event()
    if at_once:
        event.set()
    monkeypatch.setattr(driver, "EXIT_AT_ONCE", event)
    ended = []

    def ending(how):
        def end(code):
            ended.append((how, code))
            raise SystemExit(code)  # neither returns
        return end

    monkeypatch.setattr(cli_main.os, "_exit", ending("os._exit"))
    monkeypatch.setattr(cli_main.sys, "exit", ending("sys.exit"))
    with pytest.raises(SystemExit):
        cli_main._exit(130)
    assert ended == [("os._exit" if at_once else "sys.exit", 130)]


def test_exit_names_a_worker_it_drops(monkeypatch, capsys):
    """A time limit can end a run while the final evaluation's compile still runs in its worker: the
    process ends at once, and says which work it dropped."""
    import shed_jax.__main__ as cli_main

    monkeypatch.setattr(driver, "EXIT_AT_ONCE", threading.Event())
    release = threading.Event()
    worker = threading.Thread(target=release.wait, name="shed_jax-final-eval-compile", daemon=True)
    worker.start()
    ended = []

    def end(code):
        ended.append(code)
        raise SystemExit(code)

    monkeypatch.setattr(cli_main.os, "_exit", end)
    try:
        with pytest.raises(SystemExit):
            cli_main._exit(75)
    finally:
        release.set()
        worker.join()
    assert ended == [75]
    assert "[shed_jax] exiting while shed_jax-final-eval-compile still runs: its work is dropped" in capsys.readouterr().err


def test_signal_during_resume_startup_names_the_resume(finished, patched, tmp_path, monkeypatch):
    d = copy_of(finished, tmp_path, "stopped")
    (d / "summary.json").unlink()
    shutil.rmtree(d / "checkpoints" / "4")  # a run stopped at budget step 3
    ckpts = snapshot(d / "checkpoints")
    monkeypatch.setattr(driver, "in_worker", signal_during_compile(signal.SIGTERM))
    code, _, err = run(["--resume", str(d)])
    assert code == 143 and f"SIGTERM during start-up, before the first budget step: stopped; continue it with: " \
                           f"python -m shed_jax run --resume {d}" in err
    assert snapshot(d / "checkpoints") == ckpts


def test_signal_during_the_final_evaluation_stops_at_once_and_a_resume_writes_the_results(finished, patched, tmp_path,
                                                                                          monkeypatch):
    """Training is over and saved: a first signal in the final evaluation stops the run at once (the
    evaluation may take an hour), not after it; nothing marks the run finished, and a resume
    writes the results."""
    d = copy_of(finished, tmp_path, "evaluating")
    (d / "summary.json").unlink()
    (d / "final_eval_test.json").unlink()
    ckpts = snapshot(d / "checkpoints")
    original = driver.in_worker

    def worker(fn, name="compile", **kwargs):
        if name == "eval":
            return signal_during_compile(signal.SIGTERM)(fn, name)
        return original(fn, name, **kwargs)

    monkeypatch.setattr(driver, "in_worker", worker)
    monkeypatch.setattr(driver, "EXIT_AT_ONCE", threading.Event())
    again = ["--resume", str(d)]  # the run's --final-eval test --final-eval-episodes 3 are saved with it
    code, out, err = run(again)
    assert code == 143, out + err
    assert driver.EXIT_AT_ONCE.is_set()  # the evaluation's worker may be inside XLA
    assert (f"[shed_jax] SIGTERM while writing the final evaluation on 'test': stopped; training is finished and its "
            f"checkpoint (budget step 4) is saved; write the plots, the final evaluation and summary.json with: "
            f"python -m shed_jax run --resume {d}") in err
    assert "final evaluation on 'test' failed" not in err and "Traceback" not in err
    assert not (d / "summary.json").exists() and not (d / "final_eval_test.json").exists()
    assert snapshot(d / "checkpoints") == ckpts
    monkeypatch.setattr(driver, "in_worker", original)
    code, out, err = run(again)
    assert code == 0, err
    unclocked = lambda path: {k: v for k, v in json.loads(path.read_text()).items() if "wall" not in k}  # noqa: E731
    assert unclocked(d / "summary.json") == unclocked(finished["dir"] / "summary.json")
    assert json.loads((d / "final_eval_test.json").read_text())["returns"] == \
        json.loads((finished["dir"] / "final_eval_test.json").read_text())["returns"]


def test_signal_during_the_last_chunk_saves_it_and_stops_before_the_results(finished, patched, tmp_path, monkeypatch):
    d = copy_of(finished, tmp_path, "last")
    for name in ("summary.json", "final_eval_test.json"):
        (d / name).unlink()
    shutil.rmtree(d / "checkpoints" / "4")  # stopped at budget step 3: the resume runs the last chunk
    real = driver.extend_history

    def extend_history(*args, **kwargs):  # after a chunk ran, before it is saved
        signal.raise_signal(signal.SIGTERM)  # the run's own handler
        return real(*args, **kwargs)

    monkeypatch.setattr(driver, "extend_history", extend_history)
    monkeypatch.setattr(driver, "EXIT_AT_ONCE", threading.Event())
    code, out, err = run(["--resume", str(d)])
    assert code == 143, out + err
    assert (f"SIGTERM while training the last budget step: stopped; training is finished and its checkpoint (budget "
            f"step 4) is saved; write the plots, the final evaluation and summary.json with: python -m shed_jax run "
            f"--resume {d}") in err
    assert (d / "checkpoints" / "4").is_dir() and not (d / "summary.json").exists()
    assert "training done" not in out  # no result was started


def test_a_signal_during_a_chunk_is_handled_at_once_and_a_second_one_stops_the_run(capsys, monkeypatch):
    """A chunk holds its thread inside XLA until its results are ready, and Python runs handlers only
    in the main thread: ``run_chunk`` waits in a worker, so the first signal's line comes while the
    chunk runs (not when it ends, minutes later for a long chunk on a CPU) and a second one stops at
    once; a long chunk says it is still training. The stand-in chunk is 4 s of one host callback inside
    a compiled program."""
    ended = threading.Event()

    def slow(x):
        time.sleep(4.0)
        ended.set()
        return x

    shape = jax.ShapeDtypeStruct((1, 1), jnp.float32)
    fn = jax.jit(lambda state, done: (state, {"m": jax.pure_callback(slow, shape, state)})).lower(
        jnp.ones((1, 1)), 0).compile()
    monkeypatch.setattr(driver, "EXIT_AT_ONCE", threading.Event())
    monkeypatch.setattr(driver, "HEARTBEAT_S", 0.5)
    pid, seen, said = os.getpid(), {}, []
    timers = [threading.Timer(0.2, os.kill, (pid, signal.SIGTERM)),
              threading.Timer(1.0, lambda: seen.update(signum=signals.signum, ended=ended.is_set())),
              threading.Timer(1.2, os.kill, (pid, signal.SIGTERM))]
    with driver.StopRequest() as signals:
        signals.startup = False  # training: a first signal lets the chunk finish
        t0 = time.time()
        for t in timers:
            t.start()
        with pytest.raises(SystemExit) as stop:
            driver.run_chunk(fn, jnp.ones((1, 1)), 0, rows=1, what="training the stand-in", say=said.append)
        elapsed, still_running = time.time() - t0, not ended.is_set()
    for t in timers:
        t.join()
    assert seen == {"signum": signal.SIGTERM, "ended": False}  # the first one was handled while the chunk ran
    assert stop.value.code == 143 and still_running, elapsed  # the second did not wait for the chunk to end
    assert driver.EXIT_AT_ONCE.is_set()  # python -m shed_jax then ends with os._exit, XLA still at work
    assert said and all(re.fullmatch(r"still training the stand-in \(\d+ s\)\.\.\.", line) for line in said), said
    err = capsys.readouterr().err
    assert "SIGTERM: finishing the current chunk, then saving (send it again to stop at once without saving)" in err
    assert "SIGTERM again: stopped at once, without saving (what was saved before stays)" in err
    assert ended.wait(10)  # the stand-in chunk ends (os._exit would not wait for it)


def test_run_chunk_returns_the_state_and_the_host_metrics_cut_to_the_rows():
    fn = jax.jit(lambda state, done: (state + done, {"a": {"b": jnp.arange(6.0).reshape(3, 2)}}))
    state, flat = driver.run_chunk(fn, jnp.float32(1), 2, rows=2)
    assert float(state) == 3.0 and list(flat) == ["a/b"]
    assert isinstance(flat["a/b"], np.ndarray) and flat["a/b"].tolist() == [[0.0, 1.0], [2.0, 3.0]]


def signal_as_the_evaluation_compiles(signum):
    """driver.in_worker that raises ``signum`` (handled by the command's own handler) as the final
    evaluation starts to compile, then does its work as usual."""
    original = driver.in_worker

    def worker(fn, name="compile", **kwargs):
        if name == "eval" and kwargs.get("what") == "compiling":
            signal.raise_signal(signum)
        return original(fn, name, **kwargs)

    return worker


def test_without_checkpoints_a_signal_in_the_final_evaluation_lets_the_results_be_written(patched, tmp_path, monkeypatch):
    """--no-checkpoint: nothing could write the results later, so the first signal does not cut them."""
    e = tmp_path / "E"
    monkeypatch.setattr(driver, "in_worker", signal_as_the_evaluation_compiles(signal.SIGINT))
    code, out, err = run(["--out", str(e), *BASE, "--no-checkpoint", "--no-gif", "--final-eval", "test",
                          "--final-eval-episodes", "3"])
    assert code == 0, out + err
    assert ("SIGINT: writing the results first (no checkpoint was saved, so they cannot be written later) "
            "(send it again to stop at once without saving)") in err
    assert (e / "summary.json").exists() and (e / "final_eval_test.json").exists()


def test_write_atomic_leaves_the_old_file_when_the_write_fails(tmp_path, monkeypatch):
    path = tmp_path / "summary.json"
    path.write_text("old")
    rundir.write_atomic(path, "new")
    assert path.read_text() == "new" and not (tmp_path / "summary.json.tmp").exists()

    def cut(self, text):
        open(self, "w").write(text[:2])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(type(path), "write_text", cut)
    with pytest.raises(OSError):
        rundir.write_atomic(path, "newer")
    monkeypatch.undo()
    assert path.read_text() == "new" and not (tmp_path / "summary.json.tmp").exists()


@pytest.mark.parametrize("case", ["saved", "finished", "finished-no-gif"])
def test_results_interrupted_says_what_is_kept(tmp_path, monkeypatch, capsys, case):
    monkeypatch.setattr(driver, "EXIT_AT_ONCE", threading.Event())
    if case.startswith("finished"):
        (tmp_path / "summary.json").write_text("{}")
    code = driver.results_interrupted(signal.SIGINT, "writing the plots", tmp_path, 7, case != "finished-no-gif")
    err = capsys.readouterr().err.strip()
    assert code == 130 and driver.EXIT_AT_ONCE.is_set() and err.startswith("[shed_jax] SIGINT while writing the plots: stopped; ")
    assert err.endswith({
        "saved": f"checkpoint (budget step 7) is saved; write the plots, the final evaluation and summary.json with: "
                 f"python -m shed_jax run --resume {tmp_path}",
        "finished": "summary.json are written); its GIF was not made, and a resume will not make it",
        "finished-no-gif": "the run is finished (its results and summary.json are written)"}[case])


def test_final_evaluation_flags_default_to_the_saved_run():
    """Not given, --final-eval and --final-eval-episodes parse to None, so a resume takes the run's own."""
    args = parse(["--out", "x"])
    assert args.final_eval is None and args.final_eval_episodes is None


def test_final_evaluation_compiled_during_training_gives_the_same_returns(finished, patched, tmp_path, monkeypatch,
                                                                         capsys):
    """--compile-final-eval early (auto's choice on a GPU): the evaluation's program compiles in a worker
    from the first chunk on, while the others run; the final evaluation uses it, and scores what run A
    (compiled after training) scored. A compile that fails there is left to the final evaluation."""
    assert parse(["--out", "x"]).compile_final_eval == "auto"
    assert driver.compile_early("auto") == (jax.default_backend() == "gpu")  # late on a CPU
    started, chunks_after, stages = [], [], []
    original = driver.FinalEvalCompile.__init__

    def spy(self, batch, final_sets, students, episodes, max_steps, say):
        started.append((len(final_sets), episodes, say.__qualname__))  # the bar's writer, not a bare print
        original(self, batch, final_sets, students, episodes, max_steps, say)

    monkeypatch.setattr(driver.FinalEvalCompile, "__init__", spy)
    original_chunk = driver._RunReporter.chunk
    monkeypatch.setattr(driver._RunReporter, "chunk",
                        lambda self, p, *a: (chunks_after.append(len(started)), original_chunk(self, p, *a))[1])
    original_wait = driver.heartbeat_wait
    monkeypatch.setattr(driver, "heartbeat_wait", lambda thunk, what: (stages.append(what), original_wait(thunk, what))[1])
    d = tmp_path / "early"
    code, out, err = run(["--out", str(d), *BASE, "--final-eval", "test", "--final-eval-episodes", "3",
                          "--compile-final-eval", "early"])
    assert code == 0, err
    assert started == [(1, 3, "_RunReporter.note")] and chunks_after == [0, 1, 1, 1]  # begun in the first chunk's report, once
    assert "final evaluation on 'test': 2 level(s) x 2 seed(s) x 3 episode(s) (compiled during training)" in out
    assert stages == ["evaluating"]  # the early program ran: the final evaluation compiled nothing
    ours, theirs = (json.loads((x / "final_eval_test.json").read_text()) for x in (d, finished["dir"]))
    assert ours["returns"] == theirs["returns"]
    # a warm-up whose compile failed: the final evaluation compiles its own, with the same result
    stages.clear()
    monkeypatch.setattr(driver.FinalEvalCompile, "program", lambda self, name, say=None: None)
    e = tmp_path / "failed"
    code, out, err = run(["--out", str(e), *BASE, "--final-eval", "test", "--final-eval-episodes", "3",
                          "--compile-final-eval", "early", "--no-gif"])
    assert code == 0 and "(compiling first)" in out and stages == ["compiling", "evaluating"]
    assert json.loads((e / "final_eval_test.json").read_text())["returns"] == theirs["returns"]
    # a program that does not take the final students (another seed count: JAX's TypeError at the call)
    # is dropped with a line and compiled again; errors of the evaluation itself are not caught
    from shed_jax import evaluation

    exp, env, student, tests, seeds, _, students = evaluation.restore_students(finished["dir"])
    resolved = evaluation.resolve_levels("test", env, exp, tests)
    other = evaluation.evaluation_program(student, resolved[0], 3, exp.loop.test_max_steps)
    three = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, x[:1]]), students)
    wrong = other.lower(three, xp.seed_keys(0, 3)).compile()
    body, _ = evaluation.evaluate_students(exp, env, student, students, seeds, resolved, episodes=3,
                                           max_steps=exp.loop.test_max_steps, compiled=wrong)
    assert body["returns"] == theirs["returns"]
    assert "[shed_jax] the evaluation program compiled earlier does not take these students (TypeError" in \
        capsys.readouterr().out

    def broken(state, keys):
        raise RuntimeError("an evaluation that fails")

    with pytest.raises(RuntimeError, match="an evaluation that fails"):
        evaluation.evaluate_students(exp, env, student, students, seeds, resolved, episodes=3, compiled=broken)


def test_compile_final_eval_takes_three_values(capsys):
    with pytest.raises(SystemExit):  # the command line's choices
        parse(["--out", "x", "--compile-final-eval", "soon"])
    assert "invalid choice: 'soon'" in capsys.readouterr().err
    # and the options of a caller that builds them itself
    with pytest.raises(errors.UsageError, match=r"--compile-final-eval must be one of auto, early, late, got 'soon'"):
        driver.RunOptions(out="x", compile_final_eval="soon").check()



def test_a_failed_early_compile_of_the_final_evaluation_is_said(monkeypatch, capsys):
    """The worker names its compile error at once (a run stopped by its time limit never asks for the
    program) and keeps it, and ``program`` names it again when it hands back None (before, a run's log
    said nothing of either)."""
    import types

    from shed_jax import evaluation

    class Broken:
        def lower(self, *a):
            raise RuntimeError("out of memory while autotuning\nsecond line")

    monkeypatch.setattr(evaluation, "evaluation_program", lambda *a, **k: Broken())
    batch = types.SimpleNamespace(student=None, num_seeds=2)
    early = driver.FinalEvalCompile(batch, [(None, None, "named")], {"w": jnp.zeros((2, 3))}, 3, 100)
    early.thread.join()
    assert capsys.readouterr().out == ("[shed_jax] the final evaluation's compile begun during training failed "
                                       "(RuntimeError: out of memory while autotuning); it compiles again after training\n")
    written = []  # a run passes its progress bar's writer: the worker's line goes there, not to a bare print
    driver.FinalEvalCompile(batch, [(None, None, "named")], {"w": jnp.zeros((2, 3))}, 3, 100, say=written.append).thread.join()
    assert written == ["the final evaluation's compile begun during training failed "
                       "(RuntimeError: out of memory while autotuning); it compiles again after training"]
    assert capsys.readouterr().out == ""
    lines = []
    assert early.program("named", say=lines.append) is None
    assert lines == ["the final evaluation's compile begun during training failed "
                     "(RuntimeError: out of memory while autotuning); compiling it again"]
    assert early.program("test", say=lines.append) is None and len(lines) == 1  # a set it never compiled

# ---- failed writes ------------------------------------------------------------------------------

def failing_save(at_step, exc):
    original = ck.RunCheckpointer.save

    def save(self, step, *a, **kw):
        if step == at_step:
            raise exc
        return original(self, step, *a, **kw)

    return save


def test_checkpoint_every_saves_only_when_due_and_at_a_stop(finished, patched, tmp_path):
    """With --checkpoint-every far above the run's length, chunks 1 and 2 are not saved and the stop
    after chunk 3 (--stop-after 3) is; the records of every chunk are written all the same."""
    a, e = finished["dir"], tmp_path / "E"
    code, out, err = run(["--out", str(e), *BASE, "--no-gif", "--checkpoint-every", "1e6", "--stop-after", "3"])
    assert code == errors.EXIT_STOPPED, err
    assert sorted(int(p.name) for p in (e / "checkpoints").iterdir() if p.name.isdigit()) == [3]
    lines = (a / "metrics.jsonl").read_text().splitlines(keepends=True)
    assert (e / "metrics.jsonl").read_text() == "".join(lines[:3 * SEEDS])


def test_a_save_slower_than_a_chunk_is_said_once(patched, tmp_path, monkeypatch):
    """Checkpoints that take longer than the chunks they follow hold training up: the run says so,
    once, and names --checkpoint-every."""
    real_save = ck.RunCheckpointer.save

    def slow_save(self, *args, **kw):
        time.sleep(1.5)
        return real_save(self, *args, **kw)

    monkeypatch.setattr(ck.RunCheckpointer, "save", slow_save)
    monkeypatch.setattr(driver, "SLOW_SAVE_S", 0.5)
    code, out, err = run(["--out", str(tmp_path / "S"), *BASE, "--no-gif", "--stop-after", "3"])
    assert code == errors.EXIT_STOPPED, err
    assert out.count("--checkpoint-every SECONDS saves checkpoints less often") == 1, out
    # the time said is the save's own: at least the 1.5 s sleep (more on a loaded machine)
    took = re.search(r"the last chunk's records and checkpoint took (\d+\.\d) s", out)
    assert took and float(took.group(1)) >= 1.5, out


def test_disk_full_is_reported_at_its_chunk_with_what_is_safe(finished, patched, tmp_path, monkeypatch):
    a, f = finished["dir"], tmp_path / "F"
    monkeypatch.setattr(ck.RunCheckpointer, "save", failing_save(3, OSError(errno.ENOSPC, "No space left on device")))
    code, out, err = run(["--out", str(f), *BASE, "--no-gif"])
    line = error_line(err)
    assert code == errors.EXIT_IO == 74
    assert line == (f"shed_jax: error: disk full (No space left on device) while saving checkpoint 3 in {f}/checkpoints; "
                     f"safe on disk: checkpoint 2 in {f}/checkpoints (and metrics.jsonl up to it); after freeing space "
                     f"continue with: python -m shed_jax run --resume {f}")
    # step 3's line comes when it is computed; its save fails in the writer thread while step 4 runs,
    # and the error (above) names checkpoint 2 as the one safe on disk; step 4 is never reported
    assert "step     3/4" in out and "step     4/4" not in out
    assert not (f / "summary.json").exists()
    monkeypatch.undo()
    code, out, err = run(["--resume", str(f), "--no-gif"])
    assert code == 0, err
    same_records(a, f)


def test_a_wrapped_failure_of_the_last_save_is_one_line(patched, tmp_path, monkeypatch):
    """orbax reports an asynchronous write's failure when it is waited for, wrapped in its own error."""
    f = tmp_path / "G"
    original_wait = ck.RunCheckpointer.wait

    def wait(self):
        original_wait(self)
        if self.latest_step() == 4:
            try:
                raise OSError(errno.ENOSPC, "No space left on device")
            except OSError as inner:
                raise RuntimeError("Checkpoint save failed") from inner

    monkeypatch.setattr(ck.RunCheckpointer, "wait", wait)
    code, out, err = run(["--out", str(f), *BASE, "--no-gif"])
    assert code == 74
    assert "disk full (No space left on device) while saving checkpoint 4" in error_line(err)
    assert "training done" not in out and not (f / "summary.json").exists()


def test_no_checkpoint_yet_says_so(patched, tmp_path, monkeypatch):
    f = tmp_path / "H"
    monkeypatch.setattr(ck.RunCheckpointer, "save", failing_save(1, OSError(errno.ENOSPC, "No space left on device")))
    code, _, err = run(["--out", str(f), *BASE, "--no-gif"])
    assert code == 74 and "no checkpoint was saved yet; after freeing space start over with: " \
                          f"python -m shed_jax run --out {f} --restart" in error_line(err)


# ---- metrics.jsonl on resume ------------------------------------------------------------------

def test_metrics_rebuild_names_only_a_backup_it_wrote(finished, tmp_path):
    a = finished["dir"]
    with ck.RunCheckpointer(a, create=False) as reader:
        hist = reader.read_history()
    path = tmp_path / "metrics.jsonl"
    note = rundir.reconcile_metrics_jsonl(path, hist, 3, SEEDS)  # no file at all
    assert note == f"metrics.jsonl: none beside the checkpoint; wrote its {3 * SEEDS} record(s) from the checkpoint's history"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.jsonl"]
    lines = (a / "metrics.jsonl").read_text().splitlines(keepends=True)
    records = [json.loads(x) for x in lines[: 3 * SEEDS]]  # rebuilt from the history: the same records
    assert [json.loads(x) for x in path.read_text().splitlines()] == records
    path.write_text("".join(lines[SEEDS: 3 * SEEDS]))  # step 0 missing
    note = rundir.reconcile_metrics_jsonl(path, hist, 3, SEEDS)
    assert "old file kept as metrics.jsonl.bak-3" in note
    assert (tmp_path / "metrics.jsonl.bak-3").read_text() == "".join(lines[SEEDS: 3 * SEEDS])
    assert [json.loads(x) for x in path.read_text().splitlines()] == records


def test_compile_heartbeat_keeps_start_up_from_going_silent(capsys):
    # a 0.35 s "compile" with a 0.1 s heartbeat: a line at about 0.1, 0.2 and 0.3 s, and the result
    assert driver.in_worker(lambda: time.sleep(0.35) or 7, heartbeat=0.1) == 7
    lines = [l for l in capsys.readouterr().out.splitlines() if l.startswith("[shed_jax] still compiling")]
    assert 2 <= len(lines) <= 4, lines
    assert driver.in_worker(lambda: 8) == 8 and "still" not in capsys.readouterr().out  # no heartbeat asked


def test_evaluation_heartbeat_names_its_stage(monkeypatch, capsys):
    # evaluate_students' wait in run --final-eval and eval: "still evaluating" while the roll-outs run
    monkeypatch.setattr(driver, "HEARTBEAT_S", 0.1)
    assert driver.heartbeat_wait(lambda: time.sleep(0.35) or 9, "evaluating") == 9
    lines = [l for l in capsys.readouterr().out.splitlines() if l.startswith("[shed_jax] still evaluating")]
    assert 2 <= len(lines) <= 4, lines


# ---- --profile-chunk ---------------------------------------------------------------------------

def test_profile_chunk_writes_where_the_time_went_and_changes_no_result(finished, patched, tmp_path):
    a, p = finished["dir"], tmp_path / "P"
    code, out, err = run(["--out", str(p), *BASE, "--profile-chunk", "2", "--final-eval", "none", "--no-gif"])
    assert code == 0, err
    same_records(a, p)  # the profiled run trains exactly as run A did
    record = json.loads((p / "profile_chunk2.json").read_text())
    assert record["traced_call"] == 2 and len(record["calls_wall_s"]) == 3  # chunks 1-3 timed, 4 untouched
    assert record["source"] == "host" and record["kernels"] > 0 and record["busy_s"] > 0
    assert record["union_s"] <= record["span_s"] + 1e-9
    assert sum(b["kernels"] for b in record["by_calls"]) <= record["kernels"]
    assert f"summary goes to {p / 'profile_chunk2.json'}" in out and "call 2 profiled" in out
    # a chunk this process never reaches: said, nothing written
    q = tmp_path / "Q"
    code, out, err = run(["--out", str(q), *BASE, "--profile-chunk", "9", "--final-eval", "none", "--no-gif"])
    assert code == 0, err
    assert "--profile-chunk 9: this process ran 4 chunk(s), so none was profiled" in out
    assert not list(q.glob("profile_chunk*.json"))


def test_profile_chunk_takes_a_count():
    with pytest.raises(SystemExit):
        parse(["--profile-chunk", "0"])
    from shed_jax.errors import UsageError

    with pytest.raises(UsageError, match="--profile-chunk must be an integer >= 1"):
        driver.RunOptions(profile_chunk=0).check()
