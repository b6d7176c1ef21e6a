"""Checkpoints of a whole run: resume is bitwise exact, mismatched or damaged checkpoints raise,
signals stop at a chunk boundary, the non-finite guard names the component and keeps the last
good checkpoint.

The run CLI is driven in-process (``main(args)``, i.e. ``shed_jax.driver.run``) on a tiny CartPole PLR experiment (PLR keeps a
level buffer in the method state, so buffers, optimiser states, RNG keys and the step counter all
go through the checkpoint). Every run compiles the same program, so after the first one the
persistent compilation cache (tests/conftest.py) serves it.
"""
import argparse
import gc
import json
import shutil
import signal
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from shed_jax import checkpoint as ck
from shed_jax import driver, errors, runtime
from shed_jax import experiment as xp
from shed_jax.cli import run as run_cli
from shed_jax.loop import LoopSpec, RunState, make_run
from shed_jax.methods.level_sampler import LevelSamplerConfig
from shed_jax.presets import Experiment
from shed_jax.student import PPOConfig

SEEDS = 2


def tiny_experiment(**ppo_overrides) -> Experiment:
    sizes = dict(num_envs=4, num_steps=8, update_epochs=1, num_minibatches=1, actor_hidden=(8,), critic_hidden=(8,))
    ppo = PPOConfig.for_env("cartpole", **{**sizes, **ppo_overrides})
    return Experiment(
        env="cartpole", method="plr", preset="tiny", ppo=ppo,
        method_config={"updates_per_step": 1, "sampler": LevelSamplerConfig(capacity=4, min_fill=0.5, replay_prob=0.9)},
        loop=LoopSpec(steps_per_episode=4, num_episodes=1, test_episodes=1, test_max_steps=20),
        test_set="cartpole-test",
    )


def cartpole_test_levels(env):
    from envs.cartpole import LEVELS

    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), LEVELS["default"](), LEVELS["moon"]())


def parse(argv):
    p = argparse.ArgumentParser()
    run_cli.add_arguments(p)
    return p.parse_args(argv)


@pytest.fixture(scope="module")
def patched():
    """The run CLI on the tiny experiment (presets only know lander/walker) and its test set."""
    original = xp.test_levels
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(xp, "experiment_from_args", lambda args, backend: tiny_experiment())
        mp.setattr(xp, "test_levels", lambda name, env: cartpole_test_levels(env) if name == "cartpole-test" else original(name, env))
        yield mp


def target_for(exp, seeds=SEEDS, root_seed=0):
    _, student, method, tests = xp.build(exp)
    init, _ = make_run(student, method, tests, exp.loop)
    return jax.eval_shape(jax.vmap(init), xp.seed_keys(root_seed, seeds))


def restore(run_dir, target, **kw):
    with ck.RunCheckpointer(run_dir, create=False) as reader:
        return reader.restore(target, **kw)


def steps_of(run_dir):
    with ck.RunCheckpointer(run_dir, create=False) as reader:
        return reader.steps()


def leaves_equal(a, b):
    la, lb = jax.tree_util.tree_leaves_with_path(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb)
    for (path, x), y in zip(la, lb):
        assert np.asarray(x).dtype == np.asarray(y).dtype, ck.path_name(path)
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=ck.path_name(path))


#: run A, made once per test process (its directory, output and recorded events): tests/test_run_cli.py
#: (as ``finished``) and tests/test_sweep_cli.py use it too, and a module fixture of each would start the
#: very same run again. No test writes into A: they copy it, or their resume is refused before it writes.
_RUN_A = {}


def straight_run(tmp_path_factory) -> dict:
    """A: the tiny run straight through (4 chunks of 1 budget step, --final-eval test with 3 episodes,
    the GIF attempted; the compile happens here), with its stdout and stderr and the order of its
    compiles and of the progress bar's creation. The caller holds ``patched``."""
    if not _RUN_A:
        import contextlib
        import io

        import tqdm

        a = tmp_path_factory.mktemp("runs") / "A"
        events = []
        original_worker, original_bar = driver.in_worker, tqdm.tqdm

        def worker(fn, name="compile", **kwargs):
            events.append((name, kwargs.get("what", "compiling")))
            return original_worker(fn, name)

        def bar(*args, **kw):
            events.append("bar")
            return original_bar(*args, **kw)

        out, err = io.StringIO(), io.StringIO()
        with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            mp.setattr(driver, "in_worker", worker)
            mp.setattr(tqdm, "tqdm", bar)
            code = run_cli.main(parse(["--out", str(a), "--seeds", str(SEEDS), "--chunk", "1", "--final-eval", "test",
                                       "--final-eval-episodes", "3"]))
        assert code == 0, err.getvalue()
        _RUN_A.update(dir=a, out=out.getvalue(), err=err.getvalue(), events=events)
    return _RUN_A


@pytest.fixture(scope="module")
def run_a(patched, tmp_path_factory):
    """A's directory (straight_run)."""
    return straight_run(tmp_path_factory)["dir"]


@pytest.fixture(scope="module")
def runs(run_a):
    """A, and B: the same run (--keep 2) stopped by a SIGTERM raised as its second chunk is called, so
    after 2 chunks (resumed by test_resume_is_bitwise_exact). While B ran, the order of its chunks and
    of its writer thread's first write was recorded (test_writes_overlap_the_next_chunk_and_a_stop_saves_the_last_one):
    chunk 0's write waits until chunk 1 has started (a sequential loop would time out there)."""
    import threading

    from shed_jax import reporting

    events, chunk1 = [], threading.Event()
    real_compile, real_append = driver.compile_batch, reporting.append_jsonl

    def compile_batch(*args, **kw):
        state, compiled = real_compile(*args, **kw)

        def wrap(f):
            def call(state, done):
                events.append(("chunk", int(done)))
                if done == 1:
                    chunk1.set()
                    signal.raise_signal(signal.SIGTERM)  # handled at the chunk boundary
                return f(state, done)
            return call
        return state, {n: wrap(f) for n, f in compiled.items()}

    def append(path, records):
        step = int(records[0]["step"])
        if step == 0:
            events.append(("chunk 1 started during write 0", chunk1.wait(timeout=60)))
        real_append(path, records)

    import contextlib
    import io

    b = run_a.parent / "B"
    before = signal.getsignal(signal.SIGTERM)
    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        mp.setattr(driver, "compile_batch", compile_batch)
        mp.setattr(reporting, "append_jsonl", append)
        rc_stop = run_cli.main(parse(["--out", str(b), "--seeds", str(SEEDS), "--chunk", "1", "--no-gif", "--keep", "2"]))
    # what the stop left, before a test resumes B
    seen = {"events": events, "steps": steps_of(b), "out": out.getvalue(), "err": err.getvalue(),
            "handler restored": signal.getsignal(signal.SIGTERM) == before,
            "history": restore(b, target_for(tiny_experiment())).history}
    return run_a, b, rc_stop, (b / "metrics.jsonl").read_text(), seen


def test_straight_run_writes_run_dir(run_a):
    a = run_a
    for name in ("config.json", "metrics.jsonl", "summary.json", "test_return.png", "test_return_per_level.png",
                 "generated_levels.png", "student_training.png"):
        assert (a / name).exists(), name
    config = json.loads((a / "config.json").read_text(), parse_constant=pytest.fail)  # strict JSON: no Infinity/NaN
    assert config["seeds"] == SEEDS and config["root_seed"] == 0 and config["chunk"] == 1
    assert config["commit"] == runtime.source_commit()  # the code the run started with (None in a copied tree)
    assert config["experiment"]["method_config"]["sampler"]["capacity"] == 4
    records = [json.loads(line) for line in (a / "metrics.jsonl").read_text().splitlines()]
    assert [(r["step"], r["seed"]) for r in records] == [(t, s) for t in range(4) for s in range(SEEDS)]
    with ck.RunCheckpointer(a, create=False) as reader:
        assert reader.steps() == [2, 3, 4]  # default --keep 3
        meta = reader.read_meta()
    assert meta["step"] == 4 and meta["config"] == config and meta["extra"]["wall_time_s"] > 0


def test_resume_is_bitwise_exact(runs, capsys):
    a, b, rc_stop, stopped_jsonl, _ = runs
    assert rc_stop == 128 + signal.SIGTERM
    assert len(stopped_jsonl.splitlines()) == 2 * SEEDS  # steps 0 and 1
    # a crash after the jsonl append of step 2 but before its checkpoint, and a line cut by the kill
    lines = (a / "metrics.jsonl").read_text().splitlines(keepends=True)
    with open(b / "metrics.jsonl", "a") as f:
        f.writelines(lines[2 * SEEDS: 3 * SEEDS])
        f.write('{"seed": 0, "step": 3, "test_ret')
    capsys.readouterr()
    # no output flags: the run's own --keep 2 and --no-gif carry over from its start
    assert run_cli.main(parse(["--resume", str(b)])) == 0
    out = capsys.readouterr().out
    assert "resuming" in out and "from budget step 2/4" in out
    # the same records, nothing duplicated, earlier lines untouched
    assert (b / "metrics.jsonl").read_text() == (a / "metrics.jsonl").read_text()
    assert (b / "metrics.jsonl").read_text().startswith(stopped_jsonl)
    # the same final state (every leaf, bitwise) and the same history
    exp = tiny_experiment()
    target = target_for(exp)
    ra = restore(a, target)
    rb = restore(b, target)
    assert ra.step == rb.step == 4
    leaves_equal(ra.state, rb.state)
    assert sorted(ra.history) == sorted(rb.history)
    for k in ra.history:
        np.testing.assert_array_equal(ra.history[k], rb.history[k], err_msg=k)
    assert ra.history["step"].shape == (SEEDS, 4)
    with ck.RunCheckpointer(b, create=False) as reader:  # the history alone, without a state target
        hist = reader.read_history()
    assert sorted(hist) == sorted(rb.history)
    for k in hist:
        np.testing.assert_array_equal(hist[k], rb.history[k], err_msg=k)
    # the student learned something (so equality is not trivially about untouched params)
    init = jax.jit(jax.vmap(make_run(*xp.build(exp)[1:], exp.loop)[0]))(xp.seed_keys(0, SEEDS))
    assert not np.array_equal(np.asarray(init.student.params["actor"]["MLP_0"]["Dense_0"]["kernel"]),
                              np.asarray(ra.state.student.params["actor"]["MLP_0"]["Dense_0"]["kernel"]))
    assert int(np.asarray(ra.state.step)[0]) == 4
    # summaries agree except for the wall time; --keep 2 kept the last two checkpoints
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (a, b))
    for k in sa:
        if not k.startswith("wall_time"):
            assert sa[k] == sb[k], k
    assert steps_of(b) == [3, 4]
    for name in ("test_return.png", "test_return_per_level.png", "generated_levels.png", "student_training.png"):
        assert (b / name).exists()
    assert not (b / "final_student.gif").exists()
    with ck.RunCheckpointer(b, create=False) as reader:
        assert reader.read_config()["output"] == {"keep": 2, "checkpoint_every": 0.0, "no_gif": True, "final_eval": None,
                                                  "final_eval_episodes": 10}


def test_output_settings_come_from_the_flag_then_the_saved_run_then_the_default():
    opts = driver.RunOptions(keep=5).with_output({"keep": 1, "no_gif": True})
    assert (opts.keep, opts.checkpoint_every, opts.no_gif) == (5, 0.0, True)
    assert driver.RunOptions().with_output(None).output() == {"keep": 3, "checkpoint_every": 0.0, "no_gif": False,
                                                              "final_eval": None, "final_eval_episodes": 10}
    assert driver.RunOptions(no_gif=False).with_output({"no_gif": True}).no_gif is False
    # the final evaluation's level sets and episodes: a run saved before they were saved gets the defaults
    saved = {"final_eval": "test", "final_eval_episodes": 3}
    assert (lambda o: (o.final_eval, o.final_eval_episodes))(driver.RunOptions().with_output(saved)) == ("test", 3)
    assert (lambda o: (o.final_eval, o.final_eval_episodes))(driver.RunOptions().with_output({"keep": 1})) == (None, 10)
    assert driver.RunOptions(final_eval="none", final_eval_episodes=5).with_output(saved).final_eval_episodes == 5


def test_config_mismatch_names_the_keys(runs, patched, capsys):
    a = runs[0]
    with ck.RunCheckpointer(a, create=False) as reader:
        saved = reader.read_config()
    assert saved["seeds"] == SEEDS and saved["root_seed"] == 0 and saved["experiment"]["env"] == "cartpole"
    other = tiny_experiment(num_steps=16)
    current = {"experiment": other.to_dict(), "seeds": SEEDS, "root_seed": 0}
    with pytest.raises(ck.ConfigMismatchError, match=r"experiment\.ppo\.num_steps") as err:
        restore(a, target_for(tiny_experiment()), config=current)
    assert err.value.keys == ["experiment.ppo.num_steps"]
    assert err.value.differences == [("experiment.ppo.num_steps", 8, 16)]
    # the CLI: a different seed count on --resume is refused with exit 2, naming the key
    assert run_cli.main(parse(["--resume", str(a), "--seeds", "3", "--no-gif"])) == errors.EXIT_CHECKPOINT
    assert "seeds: saved 2, now 3" in capsys.readouterr().err
    # a fresh run into an existing run directory is refused
    with pytest.raises(SystemExit, match="--resume"):
        run_cli.main(parse(["--out", str(a), "--no-gif"]))
    # the experiment round-trips through its saved dict (nested sampler config included)
    exp = xp.experiment_from_dict(saved["experiment"])
    assert ck.config_differences({"experiment": exp.to_dict()}, {"experiment": tiny_experiment().to_dict()}, ["experiment"]) == []
    assert exp.method_config.sampler == LevelSamplerConfig(capacity=4, min_fill=0.5, replay_prob=0.9)


def _copy_run(src, dst):
    shutil.copytree(src, dst)
    return dst


# a failed tensorstore read leaves a callback for orbax's closed event loop; collected below
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_damaged_or_missing_checkpoints_raise(runs, patched, tmp_path):
    a = runs[0]
    target = target_for(tiny_experiment())
    with pytest.raises(ck.CheckpointNotFoundError, match="no run directory"):
        ck.RunCheckpointer(tmp_path / "nothing", create=False)
    (tmp_path / "empty" / "checkpoints").mkdir(parents=True)
    with pytest.raises(ck.CheckpointNotFoundError, match="no complete checkpoint"):
        restore(tmp_path / "empty", target)
    # truncated array files
    d = _copy_run(a, tmp_path / "truncated")
    for f in (d / "checkpoints" / "4" / "state").rglob("d/*"):
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    with pytest.raises(ck.CheckpointCorruptError, match="checkpoints/4"):
        restore(d, target)
    # one flipped byte in every array file: unreadable or caught by the digest
    d = _copy_run(a, tmp_path / "flipped")
    for f in (d / "checkpoints" / "4" / "state").rglob("d/*"):
        data = bytearray(f.read_bytes())
        data[len(data) // 2] ^= 0xFF
        f.write_bytes(bytes(data))
    with pytest.raises(ck.CheckpointCorruptError):
        restore(d, target)
    # readable arrays that are not the ones saved with this metadata (step 3's state under step 4)
    d = _copy_run(a, tmp_path / "swapped")
    shutil.rmtree(d / "checkpoints" / "4" / "state")
    shutil.copytree(d / "checkpoints" / "3" / "state", d / "checkpoints" / "4" / "state")
    with pytest.raises(ck.CheckpointCorruptError, match="digest mismatch"):
        restore(d, target)
    # the same for the metrics history, read alone
    d = _copy_run(a, tmp_path / "swapped_history")
    shutil.rmtree(d / "checkpoints" / "4" / "history")
    shutil.copytree(d / "checkpoints" / "3" / "history", d / "checkpoints" / "4" / "history")
    with ck.RunCheckpointer(d, create=False) as reader:
        with pytest.raises(ck.CheckpointCorruptError, match="digest mismatch"):
            reader.read_history()
    # the metadata item deleted: the newest step is not a complete checkpoint any more
    d = _copy_run(a, tmp_path / "nometa")
    shutil.rmtree(d / "checkpoints" / "4" / "meta")
    with pytest.raises(ck.CheckpointError):
        restore(d, target)
    # a state of another structure (bigger network) is refused before anything is read
    with pytest.raises(ck.CheckpointCorruptError, match=r"student\.params\.actor\.MLP_0\.Dense_0\.kernel: saved float32\[2, 4, 8\]"):
        restore(a, target_for(tiny_experiment(actor_hidden=(16,))))
    # the CLI turns these into exit code 2
    assert run_cli.main(parse(["--resume", str(tmp_path / "truncated"), "--no-gif"])) == errors.EXIT_CHECKPOINT
    time.sleep(1.0)  # let the failed reads settle
    gc.collect()


def test_signal_stops_at_chunk_boundary_and_saves(runs):
    """Run B of the ``runs`` fixture: a SIGTERM (handled by the run's own handler) while its second
    chunk runs stops it at that chunk's end, with the chunk saved."""
    a, b, rc, stopped_jsonl, seen = runs
    assert rc == 128 + signal.SIGTERM
    assert "SIGTERM" in seen["err"] and f"--resume {b}" in seen["out"]
    assert seen["handler restored"]  # handlers restored
    # the chunk was finished and saved: step 2's checkpoint and records equal the straight run's
    # (test_resume_is_bitwise_exact resumes from it)
    assert seen["steps"] == [1, 2]  # --keep 2
    assert stopped_jsonl == "".join((a / "metrics.jsonl").read_text().splitlines(keepends=True)[:2 * SEEDS])
    ra = restore(a, target_for(tiny_experiment()))
    assert sorted(seen["history"]) == sorted(ra.history)
    for k, v in seen["history"].items():
        np.testing.assert_array_equal(v, ra.history[k][:, :2], err_msg=k)


def test_writes_overlap_the_next_chunk_and_a_stop_saves_the_last_one(runs):
    """The writer thread writes chunk k's records while the main thread runs chunk k+1: chunk 0's
    write waits until chunk 1 has started (a sequential loop would time out here). A signal during
    chunk 1 stops the run after chunk 1 with its records and checkpoint written (run B of the
    ``runs`` fixture); test_resume_is_bitwise_exact resumes B and checks that it gives the straight
    run's records and state bit for bit."""
    a, _, rc, stopped_jsonl, seen = runs
    events = seen["events"]
    assert rc == 128 + signal.SIGTERM
    assert ("chunk 1 started during write 0", True) in events
    assert [e for e in events if e[0] == "chunk"] == [("chunk", 0), ("chunk", 1)]
    assert seen["steps"][-1] == 2
    lines = (a / "metrics.jsonl").read_text().splitlines(keepends=True)
    assert stopped_jsonl == "".join(lines[:2 * SEEDS])


def test_nonfinite_guard_stops_and_keeps_last_good_checkpoint(runs, patched, tmp_path, capsys):
    """A run whose step-2 checkpoint holds a NaN in one student bias (written through the library,
    so its digest is valid): the resumed chunk is caught, named, and not saved."""
    a = runs[0]
    d = tmp_path / "D"
    d.mkdir()
    exp = tiny_experiment()
    good = restore(a, target_for(exp), step=2)
    config = good.config
    p = good.state.student.params
    bias = p["actor"]["MLP_0"]["Dense_0"]["bias"]
    p = {**p, "actor": {"MLP_0": {**p["actor"]["MLP_0"], "Dense_0": {**p["actor"]["MLP_0"]["Dense_0"], "bias": bias.at[0, 3].set(jnp.nan)}}}}
    with ck.RunCheckpointer(d) as writer:
        writer.save(2, good.state.replace(student=good.state.student.replace(params=p)), good.history, config)
    shutil.copy(a / "config.json", d / "config.json")
    (d / "metrics.jsonl").write_text("".join((a / "metrics.jsonl").read_text().splitlines(keepends=True)[: 2 * SEEDS]))
    capsys.readouterr()
    assert run_cli.main(parse(["--resume", str(d), "--no-gif"])) == errors.EXIT_NONFINITE
    err = capsys.readouterr().err
    assert "non-finite values in budget steps 2-2" in err
    assert "student.params.actor.MLP_0.Dense_0.bias: NaN in" in err and "after budget step 2" in err
    assert "last good checkpoint is step 2" in err
    assert steps_of(d) == [2]  # nothing saved after the bad chunk
    assert len((d / "metrics.jsonl").read_text().splitlines()) == 2 * SEEDS
    assert len((d / "nonfinite_chunk.jsonl").read_text().splitlines()) == SEEDS


def test_history_of_a_resumed_run_takes_keys_added_since_its_checkpoint():
    # a checkpoint of an older version lacks a key the new chunk records: NaN (0 for integers) before it
    old = {"a": np.arange(6.0).reshape(2, 3), "gone": np.ones((2, 3))}
    chunk = {"a": np.full((2, 2), 9.0), "new": np.full((2, 2, 4), 7.0, np.float32), "n": np.ones((2, 2), np.int32)}
    h = driver.extend_history(old, chunk)
    assert set(h) == {"a", "new", "n"}
    np.testing.assert_array_equal(h["a"], [[0, 1, 2, 9, 9], [3, 4, 5, 9, 9]])
    assert h["new"].shape == (2, 5, 4) and h["new"].dtype == np.float32
    assert np.isnan(h["new"][:, :3]).all() and (h["new"][:, 3:] == 7).all()
    np.testing.assert_array_equal(h["n"], [[0, 0, 0, 1, 1]] * 2)
    assert driver.extend_history({}, chunk) == chunk


def test_find_nonfinite_names_components():
    """Unit checks of the guard on hand-made pytrees: which leaves count as parameters, NaN vs Inf in
    metrics, test returns only on test steps."""
    state = RunState(
        student={"params": {"w": np.ones((2, 3), np.float32)}, "hparams": {"lr": np.full((2,), np.nan, np.float32)}},
        method={"ddpg": {"critic_params": {"k": np.array([[1.0, np.inf], [1.0, 1.0]], np.float32)},
                         "buffer": np.full((2, 4), np.nan, np.float32)}},
        key=np.zeros((2, 2), np.uint32), step=np.zeros((2,), np.int32),
    )
    metrics = {
        "test_return": np.array([[np.nan, 1.0, np.nan, 2.0]] * 2, np.float32),  # tests at steps 11 and 13
        "info/teacher_reward": np.full((2, 4), np.nan, np.float32),  # NaN: no teacher reward
        "info/extras/ppo/loss": np.array([[0.1, 0.2, -np.inf, 0.3], [0.1, 0.2, 0.3, 0.4]], np.float32),
        "step": np.array([[10, 11, 12, 13]] * 2, np.int32),
    }
    problems = ck.find_nonfinite(metrics, state, start_step=10, tests_at=LoopSpec(5, 4, test_every=2).tests_at)
    assert problems == [
        "method.ddpg.critic_params.k: Inf in 1 of 4 values (seed(s) [0]) after budget step 13",
        "metric info/extras/ppo/loss: Inf in 1 value(s) (seed(s) [0]), first at budget step 12",
    ]
    # with test_every 1 the NaN test returns at steps 10 and 12 are errors
    problems = ck.find_nonfinite(metrics, None, start_step=10, tests_at=LoopSpec(5, 4).tests_at)
    assert "metric test_return: NaN/Inf in 4 value(s) (seed(s) [0, 1]), first at budget step 10" in problems
    assert ck.find_nonfinite({"test_return": np.ones((2, 3), np.float32)}, None) == []


def test_config_differences_and_tree_helpers():
    saved = {"experiment": {"ppo": {"num_envs": 4, "actor_hidden": [8]}, "env": "cartpole"}, "seeds": 2, "root_seed": 0, "backend": "cpu"}
    current = {"experiment": {"ppo": {"num_envs": 4, "actor_hidden": (8, 8)}, "env": "cartpole"}, "seeds": 2, "root_seed": 1, "backend": "gpu"}
    assert ck.config_differences(saved, current) == [
        ("experiment.ppo.actor_hidden", [8], [8, 8]), ("root_seed", 0, 1)]  # backend is not compared
    assert ck.nest({"a/b": 1, "a/c": 2, "d": 3}) == {"a": {"b": 1, "c": 2}, "d": 3}
    assert {k: int(v) for k, v in ck.unnest({"a": {"b": 1, "c": 2}, "d": 3}).items()} == {"a/b": 1, "a/c": 2, "d": 3}
    x = {"a": np.arange(3, dtype=np.int32)}
    assert ck.tree_digest(x) == ck.tree_digest({"a": np.arange(3, dtype=np.int32)})
    assert ck.tree_digest(x) != ck.tree_digest({"a": np.arange(3, dtype=np.int64)})
    assert ck.tree_digest(x) != ck.tree_digest({"b": np.arange(3, dtype=np.int32)})


def test_chunks_are_lowered_from_empty_tracing_caches():
    # A jitted helper keeps the equations, and so the source locations, of its first trace. Pallas
    # kernels embed those locations in their Triton IR, which the compilation cache's key keeps: a
    # fresh run (its initial state traced first) and its resume (a restore target traced first)
    # lowered different 2-D walker chunks (experiments/lowering_determinism.py). The driver lowers
    # every chunk through lower_from_clean_caches, which traces the helpers again inside the chunk.
    traces = []

    @jax.jit
    def helper(x):
        traces.append(x.shape)  # Python runs once per trace
        return x * 2.0

    chunk = jax.jit(lambda x: helper(x) + 1.0)
    x = jnp.ones(3)
    helper(x)
    chunk.lower(x)
    assert len(traces) == 1  # the chunk reused the helper's first trace
    lowered = driver.lower_from_clean_caches(chunk, x, lowering_platforms=("cpu",))
    assert len(traces) == 2  # traced again, inside the chunk
    np.testing.assert_array_equal(lowered.compile()(x), np.full(3, 3.0, np.float32))
    assert lowered.as_text() == chunk.lower(x).as_text()


def test_no_initial_state_holds_a_weak_typed_leaf():
    # A restored checkpoint's arrays are strongly typed. A weakly typed leaf in the fresh state (e.g.
    # jnp.full(n, -jnp.inf)) would make every resume lower a different program from the fresh run's,
    # which misses the compilation cache: 390 s of recompiling on an H200 for PLR at DCD's budget.
    from shed_jax import sharding
    from shed_jax.methods.registry import METHODS
    from shed_jax.presets import build_experiment

    mesh = sharding.batch_mesh(jax.devices()[:1])
    for method in METHODS:  # the methods' own states (whole-episode slots included) are strong
        exp = build_experiment("lander", method, "quick")
        _, student, m, tests = xp.build(exp)
        init, _ = make_run(student, m, tests, exp.loop)
        leaves = jax.tree_util.tree_leaves_with_path(jax.eval_shape(init, jax.random.PRNGKey(0)))
        assert len(leaves) > 10
        assert [jax.tree_util.keystr(p) for p, x in leaves if x.weak_type] == [], method
    # and the driver makes any state strong, values and dtypes kept
    weak = {"a": jnp.full((3,), -jnp.inf), "b": jnp.float32(2.0) * 1.0, "n": jnp.arange(2) + 1, "k": jax.random.key(1)}
    assert jax.eval_shape(lambda: weak["a"]).weak_type
    strong = jax.jit(driver.strongly_typed)(weak)
    assert not any(jax.typeof(x).weak_type for x in jax.tree.leaves(strong))
    for k in ("a", "b", "n"):
        assert strong[k].dtype == weak[k].dtype
        np.testing.assert_array_equal(strong[k], weak[k])
    assert jax.random.key_impl(strong["k"]) == jax.random.key_impl(weak["k"])
    # the PPO trainer's student states (`python -m shed_jax ppo`, its resume included) hold none either
    import envs
    from shed_jax.student import make_student

    for name in envs.registered():
        env = envs.make(name)
        student = make_student(env, PPOConfig.for_env(name).replace(num_envs=2))
        levels = env.param_space.sample(jax.random.PRNGKey(0), (1,))
        state = jax.eval_shape(lambda k: student.assign_levels(student.init(k), k, levels), jax.random.PRNGKey(0))
        assert [jax.tree_util.keystr(p) for p, x in jax.tree_util.tree_leaves_with_path(state) if x.weak_type] == [], name
    batch = driver.make_batch(exp, xp.build(exp), [({}, {})], num_seeds=2, root_seed=0, chunk=2)
    target = driver.state_target(batch, driver.place(batch, mesh))
    assert not any(x.weak_type for x in jax.tree.leaves(target))
