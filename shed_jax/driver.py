"""The host driver: every run and every sweep group is trained, checked, saved and reported here.

A :class:`Batch` is one compiled program: the points of one shape group (a run is a group of one
point) times the seeds, laid out point-major (row = point * seeds + seed) on one leading axis and
split over a device mesh (``shed_jax.sharding``; a run uses a mesh of one device, a sweep every
visible device). The compiled part is ``shed_jax.loop`` (PureJaxRL's ``make_train`` for UED); this
module is the host side around it:

* ``compile_batch``: the initial state and every chunk length, compiled ahead of time in a worker
  thread ("compiling ...", a "still compiling (N s)" line every 45 s, "compiled in N s"), so that
  SIGINT/SIGTERM during start-up stop at once (:class:`StopRequest`);
* ``train``: the chunks of budget steps. After each, the host checks the chunk for non-finite values
  (``checkpoint.find_nonfinite``; the chunk is not saved), calls the caller's :class:`Reporter`
  (Brax's ``progress_fn`` split: the run prints its progress line, the sweep its per-point returns),
  stops at a chunk boundary on a signal, ``--stop-after`` or a deadline (:class:`StopRules`), and
  starts the next chunk. Meanwhile a writer thread (:class:`Background`) appends each point's records
  to its ``metrics.jsonl`` and saves a checkpoint of the whole batch (at most every ``Output.every``
  seconds, ``--checkpoint-every``; the last chunk and a stop always save), so the device does not
  wait for the disk unless a write takes longer than a chunk. The next chunk's results wait for that write; a failed write is reported then, naming
  the chunk and what is safe on disk (:class:`shed_jax.errors.WriteFailedError`). A stop waits for
  the last write, so a stopped run always has its last chunk saved. The computations and their order
  are those of a sequential loop, so the results are bitwise the same;
* ``write_results``: each point's plots, final evaluations and, last, ``summary.json`` (a point with
  a summary is finished).

``run`` is ``python -m shed_jax run`` on these; ``shed_jax.sweep.run_group`` is a sweep's group.
"""
from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import signal
import sys
import threading
import time
from typing import Any, Callable, Literal, get_args

import numpy as np

from shed_jax import errors
from shed_jax import experiment as xp
from shed_jax import rundir
from shed_jax.errors import EXIT_NONFINITE, EXIT_STOPPED, UsageError, WriteFailedError

HEARTBEAT_S = 45.0  # a "still compiling" line at least this often


# ---------------------------------------------------------------------------------------------
# signals, the compile worker, stopping
# ---------------------------------------------------------------------------------------------

class StartupInterrupted(Exception):
    """SIGINT/SIGTERM before the first chunk ran: the run stops at once (nothing to save yet)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class ResultsInterrupted(BaseException):
    """SIGINT/SIGTERM while a finished run writes its results (plots, final evaluation, summary, GIF):
    the run stops at once; its last checkpoint is saved, and a resume writes the results again. A
    BaseException, so that the ``except Exception`` guards of the final evaluation and the GIF (whose
    failures must not fail a run) let it through."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class StopRequest:
    """SIGINT/SIGTERM set ``signum``; the loop finishes its chunk, saves and exits 128 + signum.

    While ``startup`` is true (validation, building, compiling: before the first chunk runs) a
    signal raises :class:`StartupInterrupted` in the main thread instead; the compile runs in a
    worker thread meanwhile (``in_worker``), so this happens at once. While ``results`` is true
    (training is over and saved; the results are being written) it raises
    :class:`ResultsInterrupted` likewise. A second signal aborts at once (the last complete
    checkpoint stays). Handlers are installed only in the main thread and restored on exit.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.signum: int | None = None
        self.startup = True
        self.results = False
        self.finishing = "finishing the current chunk, then saving"  # what a first signal lets happen (its line)
        self._previous: dict = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc):
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous.clear()
        return False

    def _handle(self, signum, frame):
        if self.signum is not None:
            # the chunk's worker may be inside XLA (and an interrupted join can report it finished):
            # python -m shed_jax ends the process with os._exit, not an interpreter shutdown under it
            EXIT_AT_ONCE.set()
            print(f"\n[shed_jax] {signal.Signals(signum).name} again: stopped at once, without saving (what was "
                  f"saved before stays)", file=sys.stderr, flush=True)
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            raise SystemExit(128 + signum)
        self.signum = signum
        if self.startup:
            raise StartupInterrupted(signum)
        if self.results:
            raise ResultsInterrupted(signum)
        print(f"\n[shed_jax] {signal.Signals(signum).name}: {self.finishing} "
              f"(send it again to stop at once without saving)", file=sys.stderr, flush=True)

    def poll(self) -> int | None:
        """The signal received so far (checked once per chunk)."""
        return self.signum


@dataclasses.dataclass
class StopRules:
    """When training stops at a chunk boundary (checked in this order); ``stopped`` records why (the
    non-finite guard's stop included)."""

    signals: StopRequest | None = None
    stop_after: int | None = None  # budget steps
    deadline: float | None = None  # a time.time() value
    time_limit: float | None = None  # the seconds the deadline came from (for the message)
    stopped: tuple | None = None  # (exit code, reason) once a rule fired

    def check(self, done: int) -> tuple[int, str] | None:
        if self.signals is not None and self.signals.poll() is not None:
            self.stopped = (128 + self.signals.signum, f"interrupted by {signal.Signals(self.signals.signum).name}")
        elif self.stop_after is not None and done >= self.stop_after:
            self.stopped = (EXIT_STOPPED, f"--stop-after {self.stop_after} reached")
        elif self.deadline is not None and time.time() >= self.deadline:
            self.stopped = (EXIT_STOPPED, f"--time-limit {self.time_limit:g}s reached")
        return self.stopped

    def signalled(self) -> bool:
        """A signal came (checked before a sweep's next group trains)."""
        if self.signals is not None and self.signals.poll() is not None:
            self.stopped = (128 + self.signals.signum, f"interrupted by {signal.Signals(self.signals.signum).name}")
            return True
        return False


def _say(text: str) -> None:
    print(f"[shed_jax] {text}", flush=True)


def in_worker(fn, name: str = "compile", heartbeat: float | None = None, what: str = "compiling",
              say: Callable[[str], None] = _say):
    """``fn()`` in a worker thread while the main thread waits, so that SIGINT/SIGTERM are handled at
    once (a compile inside XLA would hold off the Python handlers until it returns). With
    ``heartbeat`` (seconds), a "still <what>" line every so often (through ``say``, e.g. a progress
    bar's writer), so the run is never silent longer."""
    box: dict = {}

    def work():
        try:
            box["value"] = fn()
        except BaseException as err:  # noqa: BLE001 - re-raised in the main thread
            box["error"] = err

    worker = threading.Thread(target=work, name=f"shed_jax-{name}", daemon=True)  # __main__._exit knows the prefix
    worker.start()
    start = time.time()
    beat = start + heartbeat if heartbeat else float("inf")
    while worker.is_alive():
        worker.join(0.1)
        if time.time() >= beat and worker.is_alive():
            say(f"still {what} ({time.time() - start:.0f} s)...")
            beat += heartbeat
    if "error" in box:
        raise box["error"]
    return box["value"]


# Set once a signal has stopped a start-up. XLA may still be compiling, or running the initial state,
# in threads of its own (not the compile worker's: that one may have returned already); an interpreter
# shutdown under them aborts ("terminate called ...", exit 134), so ``python -m shed_jax`` then ends
# the process at once (shed_jax/__main__.py, ``_exit``).
EXIT_AT_ONCE = threading.Event()


def results_interrupted(signum: int, stage: str, out: pathlib.Path, saved: int, gif: bool) -> int:
    """The line for a signal after training (checkpoint ``saved``), before or while a finished run writes
    its results: what was cut, what is kept (``gif``: the run makes a GIF); 128 + signum."""
    EXIT_AT_ONCE.set()  # the final evaluation may be inside XLA in its worker thread
    name = signal.Signals(signum).name
    if (out / "summary.json").exists():
        kept = "the run is finished (its results and summary.json are written)" + (
            "; its GIF was not made, and a resume will not make it" if gif else "")
    else:
        kept = (f"training is finished and its checkpoint (budget step {saved}) is saved; write the plots, the "
                f"final evaluation and summary.json with: {rundir.resume_command(out)}")
    print(f"[shed_jax] {name} while {stage}: stopped; {kept}", file=sys.stderr, flush=True)
    return 128 + signum


def startup_interrupted(signum: int, resume: str | None, made: list) -> int:
    """The line for a signal during start-up: how to continue (``resume``), or what was removed; 128 + signum."""
    EXIT_AT_ONCE.set()
    name = signal.Signals(signum).name
    if resume is not None:
        what = f"continue it with: {resume}"
    else:
        removed = rundir.remove_made(made)
        what = f"nothing was kept (removed {removed})" if removed else "nothing was written"
    print(f"[shed_jax] {name} during start-up, before the first budget step: stopped; {what}", file=sys.stderr, flush=True)
    return 128 + signum


# ---------------------------------------------------------------------------------------------
# a batch: what one compiled program runs
# ---------------------------------------------------------------------------------------------

@dataclasses.dataclass
class Batch:
    """The points of one shape group x seeds, built (every value validated) and ready to compile."""

    exp: Any  # presets.Experiment shared by the points
    env: Any
    student: Any
    method: Any
    tests: Any  # test levels
    student_hparams: Any  # PPOHyperparams stacked over the points [P]
    method_hparams: Any  # the method's hyperparameters stacked [P], or None (it has none)
    num_points: int
    num_seeds: int
    root_seed: int
    chunk: int
    init: Callable  # shed_jax.loop.make_run's, for one run
    run: Callable

    @property
    def total(self) -> int:
        return self.exp.loop.total_steps

    def rows(self, tree, p: int):
        """Point ``p``'s rows of a batched tree (leading axis point * seeds + seed)."""
        import jax

        S = self.num_seeds
        return jax.tree_util.tree_map(lambda x: x[p * S:(p + 1) * S], tree)


def make_batch(exp, parts, overrides: list[tuple[dict, dict]], *, num_seeds: int, root_seed: int,
               chunk: int | None = None) -> Batch:
    """A :class:`Batch` of ``parts`` (``experiment.build(exp)``'s env, student, method, test levels).

    ``overrides``: per point, ``(student hyperparameters, method hyperparameters)`` to set over the
    experiment's (a run: one point, ``[({}, {})]``). Values are checked here (ValueError).
    ``chunk``: budget steps per compiled call; None takes the preset's (``presets.default_chunk``),
    for runs and sweeps alike.
    """
    from shed_jax.loop import make_run
    from shed_jax.presets import default_chunk
    from shed_jax.student.config import PPOHyperparams

    env, student, method, tests = parts
    shp = PPOHyperparams.stack([exp.ppo.hparams.replace(**_floats(s, exp.method, "ppo.")) for s, _ in overrides])
    mhp = None
    if hasattr(method, "default_hparams"):
        base = method.default_hparams
        mhp = type(base).stack([base.replace(**_floats(m, exp.method)) for _, m in overrides])
    elif any(m for _, m in overrides):
        raise ValueError(f"method {exp.method!r} has no dynamic hyperparameters")
    init, run = make_run(student, method, tests, exp.loop)
    return Batch(exp, env, student, method, tests, shp, mhp, len(overrides), num_seeds, root_seed,
                 chunk or default_chunk(exp), init, run)


def _floats(values: dict, method: str, prefix: str = "") -> dict:
    out = {}
    for k, v in values.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"method {method!r}: hyperparameter {prefix}{k} needs a number, got {v!r}")
        out[k] = float(v)
    return out


def batch_init(init: Callable, method) -> Callable:
    """``(key, student_hparams, method_hparams) -> RunState``: the loop's init, then the method's hparams,
    with every leaf strongly typed (:func:`strongly_typed`)."""

    def init_point(key, student_hp, method_hp):
        state = init(key, student_hp)
        if method_hp is not None:
            state = state.replace(method=method.with_hparams(state.method, method_hp))
        return strongly_typed(state)

    return init_point


def strongly_typed(tree):
    """``tree`` with each weakly typed leaf (e.g. ``jnp.full(n, -jnp.inf)``) made strong, same dtype and values.

    A restored checkpoint's arrays are strongly typed; a fresh state must be too, or a resumed run lowers
    another program than the fresh run's and misses the compilation cache (minutes on the walkers).
    """
    import jax
    from jax import lax

    return jax.tree.map(lambda x: lax.convert_element_type(x, x.dtype) if jax.typeof(x).weak_type else x, tree)


def batch_inputs(batch: Batch):
    """Host arrays (keys [B, 2], student hparams [B], method hparams [B] or None), row = point * S + seed.

    Seed i of every point has ``experiment.seed_keys``'s key i (common random numbers).
    """
    import jax

    S = batch.num_seeds
    keys = np.tile(np.asarray(xp.seed_keys(batch.root_seed, S)), (batch.num_points, 1))
    rep = lambda tree: None if tree is None else jax.tree_util.tree_map(lambda x: np.repeat(np.asarray(x), S, axis=0), tree)
    return keys, rep(batch.student_hparams), rep(batch.method_hparams)


@dataclasses.dataclass
class Placed:
    """A batch's inputs placed for a mesh: padded to a multiple of its size (``n`` runs are real)."""

    mesh: Any
    inputs: tuple
    n: int

    @property
    def size(self) -> int:
        from shed_jax import sharding

        return sharding.batch_size(self.inputs)


def place(batch: Batch, mesh, pad: bool = True) -> Placed:
    from shed_jax import sharding

    inputs, n = sharding.pad_batch(batch_inputs(batch), mesh.size, pad=pad)
    return Placed(mesh, inputs, n)


def kernel_worlds(batch: Batch, placed: Placed) -> int:
    """The environments a training rollout steps side by side on one device: the device's runs times
    the student's training envs; the largest batch in a run's programs but for rare evaluations."""
    return placed.size // placed.mesh.size * batch.student.train_envs


def state_target(batch: Batch, placed: Placed):
    """The shapes and dtypes of the batch's initial state (a checkpoint's restore target), nothing computed."""
    import jax

    return jax.eval_shape(jax.vmap(batch_init(batch.init, batch.method)), *placed.inputs)


def on_mesh(state, placed: Placed):
    """A (restored) state split over the mesh as the compiled chunks take it."""
    import jax

    from shed_jax import sharding

    return jax.device_put(state, sharding.batch_sharding(placed.mesh))


def lower_from_clean_caches(jitted, *args, **lower_kwargs):
    """``jitted.trace(*args).lower(**lower_kwargs)`` after emptying JAX's tracing caches, so the lowered program is the same
    whatever this process traced before (a fresh run's initial state, a resume's restore target).

    A jitted helper (many ``jnp`` functions are) is traced once per process and its cached equations
    keep the source locations of that first call. Outside a kernel the persistent compilation cache
    ignores locations; inside a Pallas kernel they are part of the Triton IR the program embeds, so a
    fresh run and its resume lowered different programs and every first resume of a 2-D walker run
    missed the cache (7 minutes of compile on an H200). Tracing from empty caches makes the locations
    those of the chunk's own calls.
    """
    import jax

    jax.clear_caches()
    return jitted.trace(*args).lower(**lower_kwargs)


def chunk_sizes(chunk: int, done: int, total: int) -> list[int]:
    """The distinct chunk lengths a run from ``done`` to ``total`` calls: full chunks, then a shorter last one."""
    left = total - done
    if left <= 0:
        return []
    sizes = [min(chunk, left)]
    if left > chunk and left % chunk:
        sizes.append(left % chunk)
    return sizes


#: the programs ``compile_batch`` compiles, as JAX names them: the initial state and the chunk
RUN_PROGRAMS = ("jit_init_point", "jit_chunk")


def cache_report(say: Callable):
    """``(looked_up, cached)``: ``looked_up(program, hit, key)`` for ``runtime.cache_lookups`` says at
    once when one of ``RUN_PROGRAMS`` is not in the compilation cache (the compile that follows may
    take minutes) and lists in ``cached`` those read from it, each once."""
    cached: list[str] = []

    def looked_up(program: str, hit: bool, key: str) -> None:
        if program not in RUN_PROGRAMS:
            return
        if not hit:
            say(f"[shed_jax] {program} is not in the compilation cache (key {key[:48]}...): compiling it")
        elif program not in cached:
            cached.append(program)

    return looked_up, cached


def say(text: str) -> None:
    print(text, flush=True)


def compile_batch(batch: Batch, placed: Placed, done: int, state=None, say: Callable = say):
    """``(state, {chunk length: compiled chunk})``: the initial state when ``state`` is None, and every
    chunk length from budget step ``done`` to the end, compiled ahead of time in a worker thread."""
    from shed_jax import runtime, sharding

    fresh = state is None
    sizes = chunk_sizes(batch.chunk, done, batch.total)
    # every program of the run (chunks, the final evaluation) pads its GPU kernels to the training batch,
    # also a resume with no chunk left, whose final evaluation is lowered next
    runtime.pad_kernels_to(kernel_worlds(batch, placed))
    if not sizes and not fresh:
        return state, {}
    t0 = time.time()
    chunks = (f"a chunk of {sizes[0]} budget step(s)" if len(sizes) == 1 else
              f"chunks of {sizes[0]} and {sizes[1]} budget steps" if sizes else "")
    what = " and ".join(x for x in ("the initial state" if fresh else "", chunks) if x)
    say(f"[shed_jax] compiling {what} (minutes for a large program)...")
    run_chunk = sharding.sharded_run(batch.run, placed.mesh)

    def compile_all(state):
        if state is None:
            init = sharding.sharded_init(batch_init(batch.init, batch.method), placed.mesh)
            state = init(*sharding.put_batch(placed.inputs, placed.mesh))
        return state, {n: lower_from_clean_caches(run_chunk, state, n, done).compile() for n in sizes}

    looked_up, cached = cache_report(say)
    with runtime.cache_lookups(looked_up):
        state, compiled = in_worker(lambda: compile_all(state), heartbeat=HEARTBEAT_S)
    read = f" ({', '.join(cached)} read from the compilation cache)" if cached else ""
    say(f"[shed_jax] compiled in {time.time() - t0:.1f} s{read}")
    return state, compiled


# ---------------------------------------------------------------------------------------------
# training
# ---------------------------------------------------------------------------------------------

@dataclasses.dataclass
class Progress:
    """Where a batch's training stands (host side)."""

    state: Any
    done: int = 0  # budget steps done
    history: dict = dataclasses.field(default_factory=dict)  # flat metrics [B, done, ...]
    previous_wall: float = 0.0  # wall time of earlier processes (from the checkpoint)
    t0: float = dataclasses.field(default_factory=time.time)  # this process's start (compile included)
    first_chunk_s: float | None = None  # compile plus first chunk
    chunk_s: list = dataclasses.field(default_factory=list)  # per chunk of this process: its call to its results
    write_s: list = dataclasses.field(default_factory=list)  # per chunk: its records and checkpoint (writer thread)
    saved: int | None = None  # the last checkpoint known to be complete on disk

    def wall(self) -> float:
        return self.previous_wall + time.time() - self.t0

    def wall_per_chunk(self) -> list[float]:
        """``chunk_s`` rounded to the millisecond (``summary.json``'s ``wall_time_per_chunk_s``)."""
        return [round(x, 3) for x in self.chunk_s]


class Reporter:
    """The caller's side of training: called once before the first chunk, after every chunk, at the end."""

    def begin(self, progress: Progress, total: int) -> None:
        pass

    def chunk(self, progress: Progress, steps: int, flat: dict) -> None:
        pass

    def note(self, text: str) -> None:
        """A one-off advice line (e.g. checkpoints that hold the run up)."""
        print(f"[shed_jax] {text}", flush=True)

    def end(self) -> None:
        pass


#: the loop says once that checkpoints hold it up when it waited this long for one (and a fifth of a chunk)
SLOW_SAVE_S = 1.0


class Writes:
    """Names the write in progress (``stage``); a failed write (disk full, ...) leaving the block
    becomes one :class:`WriteFailedError`: '<reason> while <stage>; <what is safe on disk>'."""

    def __init__(self, safe: Callable[[], str], stage: str = ""):
        self.safe, self.stage = safe, stage

    def __enter__(self):
        return self

    def __exit__(self, typ, err, tb):
        if isinstance(err, Exception) and errors.is_write_failure(err):  # not UsageError: a SystemExit
            raise WriteFailedError(f"{errors.io_reason(err)} while {self.stage}; {self.safe()}") from err
        return False


@dataclasses.dataclass
class Output:
    """Where a batch's files go and how its checkpoints are kept."""

    dirs: list  # per point: its run directory (metrics.jsonl, summary.json, plots, final evaluations)
    names: list  # per point: its name (messages)
    ckpt_dir: pathlib.Path | None  # RunCheckpointer's run_dir (checkpoints/ under it); None: no checkpoints
    keep: int
    config: dict  # saved in every checkpoint
    extra: Callable[[Progress], dict]  # caller extras saved in every checkpoint (wall time, ...)
    label: str | None = None  # a sweep group's label (message prefix); None for a run
    writer: bool = True  # this process writes (process 0 of several hosts)
    every: float = 0.0  # seconds between checkpoints (0: after every chunk); the last chunk and a stop always save

    def __post_init__(self):
        if isinstance(self.every, bool) or not isinstance(self.every, (int, float)) or not 0 <= self.every < math.inf:
            raise ValueError(f"Output.every must be a finite number of seconds >= 0, got {self.every!r}")


def train(batch: Batch, compiled: dict, progress: Progress, out: Output, stop: StopRules, reporter: Reporter,
          safe: Callable[[], str]) -> tuple[int, str] | None:
    """Run the chunks from ``progress.done`` to the end (see the module doc).

    Returns None when the batch finished, ``(exit code, reason)`` when a stop rule fired (the last
    chunk is saved) or the non-finite guard stopped it (``EXIT_NONFINITE``; that chunk is not saved).
    Raises WriteFailedError for a failed write.
    """
    from shed_jax.checkpoint import RunCheckpointer

    if stop.signals is not None:
        stop.signals.startup = False
    ckpt = None
    with Writes(safe, "opening the checkpoint directory") as w:
        try:
            if out.ckpt_dir is not None:
                ckpt = RunCheckpointer(out.ckpt_dir, keep=out.keep, create=True)
            reporter.begin(progress, batch.total)
            outcome = _chunks(batch, compiled, progress, out, stop, reporter, ckpt, w)
        except BaseException:
            reporter.end()
            if ckpt is not None:
                _close_quietly(ckpt)
            raise
        reporter.end()
        if ckpt is not None:
            ckpt.close()
    return outcome


class Background:
    """One writer thread: ``submit(fn)`` runs ``fn`` there once the previous job is done; ``wait()``
    blocks until the last job is done and re-raises its exception, if any (the job's ``Writes``
    stage names what failed). Jobs run in order, one at a time."""

    def __init__(self):
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def submit(self, fn: Callable[[], None]) -> None:
        self.wait()

        def job():
            try:
                fn()
            except BaseException as err:  # noqa: BLE001 - re-raised by wait() in the caller's thread
                self._error = err

        self._thread = threading.Thread(target=job, name="shed_jax-writer", daemon=True)
        self._thread.start()

    def wait(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._error is not None:
            err, self._error = self._error, None
            raise err


def _chunks(batch, compiled, progress, out, stop, reporter, ckpt, w) -> tuple[int, str] | None:
    writes = Background()  # the last chunk's records and checkpoint, written while the next chunk runs
    try:
        outcome = _chunk_loop(batch, compiled, progress, out, stop, reporter, ckpt, w, writes)
        writes.wait()
        return outcome
    except BaseException:
        try:  # let a write in flight finish (its checkpoint stays whole); the error already raised wins
            writes.wait()
        except BaseException:  # noqa: BLE001
            pass
        raise


def extend_history(history: dict, chunk: dict) -> dict:
    """The run's per-step records ``{key: [S, steps, ...]}`` with a chunk's ``[S, n, ...]`` appended on the step
    axis. A key the history lacks (a run resumed from a checkpoint of a version that did not record it) is
    NaN for the earlier steps; an integer or boolean one is 0 / False there, which reads as a value, so
    such keys should be diagnostics, not counts. A key the chunk lacks is dropped."""
    import jax.numpy as jnp  # JAX is running by now; the module itself imports it late

    if not history:
        return dict(chunk)
    done = next(iter(history.values())).shape[1]
    out = {}
    for k, v in chunk.items():
        old = history.get(k)
        if old is None:
            fill = np.nan if jnp.issubdtype(v.dtype, jnp.inexact) else 0  # jnp's: bfloat16 counts as inexact
            old = np.full(v.shape[:1] + (done,) + v.shape[2:], fill, v.dtype)
        out[k] = np.concatenate([old, v], axis=1)
    return out


def run_chunk(fn: Callable, state, done: int, rows: int, what: str = "training a chunk",
              say: Callable[[str], None] = _say) -> tuple:
    """``fn(state, done)``: the new state and the chunk's metrics on the host, flattened (padding cut
    to ``rows``). It runs in a worker thread (``in_worker``) because XLA holds the calling thread until
    the results are ready and Python runs signal handlers only in the main thread: run there, a signal
    would wait for the chunk to end (minutes for a long chunk on a CPU), so the first one's line would
    come late and a second one could not stop the run at once. A chunk longer than ``HEARTBEAT_S``
    says "still <what>" through ``say`` meanwhile."""
    from shed_jax import reporting, sharding

    def work():
        new_state, metrics = fn(state, done)
        return new_state, reporting.flatten_tree(sharding.unpad(sharding.to_host(metrics), rows))

    return in_worker(work, name="chunk", heartbeat=HEARTBEAT_S, what=what, say=say)


def _chunk_loop(batch, compiled, progress, out, stop, reporter, ckpt, w, writes) -> tuple[int, str] | None:
    from shed_jax import reporting
    from shed_jax.checkpoint import find_nonfinite

    S, total = batch.num_seeds, batch.total
    last_save = time.time()  # the last checkpoint handed to the writer (--checkpoint-every)
    saving_every_chunk, hinted = ckpt is not None and out.every <= 0, False
    where = f"{out.label}: " if out.label else ""
    while progress.done < total:
        done = progress.done
        n = min(batch.chunk, total - done)
        t_chunk = time.time()
        new_state, flat = run_chunk(compiled[n], progress.state, done, batch.num_points * S,
                                    what=f"training budget steps {done + 1}-{done + n} of {total}"
                                    + (f" ({out.label})" if out.label else ""),
                                    say=reporter.note)
        progress.chunk_s.append(time.time() - t_chunk)
        if progress.first_chunk_s is None:
            progress.first_chunk_s = time.time() - progress.t0
        t_wait = time.time()
        writes.wait()  # the previous chunk's records and checkpoint; a failed write raises here
        waited = time.time() - t_wait
        if (not hinted and saving_every_chunk and progress.write_s
                and waited > max(SLOW_SAVE_S, 0.2 * progress.chunk_s[-1])):
            hinted = True
            reporter.note(f"{where}the last chunk's records and checkpoint took {progress.write_s[-1]:.1f} s to "
                          f"write, longer than a chunk ({progress.chunk_s[-1]:.1f} s), and training waited {waited:.1f} s "
                          "for them; --checkpoint-every SECONDS saves checkpoints less often")
        problems = find_nonfinite(flat, new_state, done, batch.exp.loop.tests_at)
        if problems:
            if ckpt is not None and progress.done > 0 and progress.saved != progress.done:
                # --checkpoint-every skipped the last good chunk's save: make it now, so the run can
                # resume from just before the bad chunk
                writes.submit(_writer(batch, progress, out, ckpt, w, None, done, 0, extra=out.extra(progress)))
                writes.wait()
            w.stage = "writing nonfinite_chunk.jsonl"
            paths = []
            for p, d in enumerate(out.dirs if out.writer else ()):
                paths.append(d / "nonfinite_chunk.jsonl")
                paths[-1].unlink(missing_ok=True)
                reporting.append_jsonl(paths[-1], reporting.step_records(batch.rows(flat, p), range(S)))
            reporter.end()
            _report_nonfinite(batch, out, problems, done, n, paths, ckpt)
            stop.stopped = (EXIT_NONFINITE, "non-finite values")
            return stop.stopped
        progress.state = new_state
        progress.history = extend_history(progress.history, flat)
        progress.done += n
        final = progress.done >= total
        stopping = not final and stop.check(progress.done) is not None
        save = ckpt is not None and (final or stopping or time.time() - last_save >= out.every)
        last_save = time.time() if save else last_save
        writes.submit(_writer(batch, progress, out, ckpt if save else None, w, flat, done, n, extra=out.extra(progress)))
        reporter.chunk(progress, n, flat)
        if stopping:
            writes.wait()  # a stopped run has its last chunk saved
            return stop.stopped
    return None


def _writer(batch, progress, out, ckpt, w, flat, done: int, n: int, extra: dict) -> Callable[[], None]:
    """The host writes of one chunk (run in the writer thread): each point's records (unless ``flat``
    is None), then (unless ``ckpt`` is None) the checkpoint of the state and history as they stand
    now (both immutable)."""
    from shed_jax import reporting

    S, state, history, step = batch.num_seeds, progress.state, progress.history, progress.done

    def write():
        t0 = time.time()
        for p, d in enumerate(out.dirs if out.writer and flat is not None else ()):
            w.stage = f"writing the records of budget steps {done}-{done + n - 1} to {d / 'metrics.jsonl'}"
            reporting.append_jsonl(d / "metrics.jsonl", reporting.step_records(batch.rows(flat, p), range(S)))
        if ckpt is not None:
            w.stage = f"saving checkpoint {step} in {ckpt.directory}"
            ckpt.save(step, state, history, out.config, extra=extra)
            ckpt.wait()
            progress.saved = step
        progress.write_s.append(time.time() - t0)

    return write


def _report_nonfinite(batch, out: Output, problems: list[str], done: int, n: int, paths: list, ckpt) -> None:
    where = f"{out.label}: " if out.label else ""
    last = ckpt.latest_step() if ckpt is not None else None
    print(f"[shed_jax] {where}non-finite values in budget steps {done}-{done + n - 1}; stopping without saving this chunk:",
          file=sys.stderr)
    for line in problems:
        print(f"  {line}", file=sys.stderr)
    if batch.num_points > 1:
        print(f"  (seed numbers above are rows of the batch: row = point x {batch.num_seeds} + seed; points: "
              + ", ".join(f"{p} {name}" for p, name in enumerate(out.names)) + ")", file=sys.stderr)
    metrics = str(paths[0]) if len(paths) == 1 else "nonfinite_chunk.jsonl in each point's directory"
    print(f"[shed_jax] this chunk's metrics: {metrics}; "
          + (f"the last good checkpoint is step {last} in {ckpt.directory}" if last is not None else "no checkpoint was saved"),
          file=sys.stderr)


def _close_quietly(ckpt) -> None:
    try:
        ckpt.close()
    except Exception:  # noqa: BLE001 - the failure that got here is what is reported
        pass


# ---------------------------------------------------------------------------------------------
# results: summary, plots, final evaluation, GIF
# ---------------------------------------------------------------------------------------------

def write_results(batch: Batch, progress: Progress, out: Output, w: Writes, *, wall: float, plots: bool = True,
                  final_sets=(), final_episodes: int = 10, extras: list | None = None,
                  early: "FinalEvalCompile | None" = None) -> list[dict]:
    """Each point's plots and final evaluations, then its ``summary.json`` (with ``extras[p]``); the summaries.
    ``early``: the final evaluation's programs compiled while training ran (one point only).

    A point with ``summary.json`` is finished: written last, so one cut off here gets them all again.
    """
    summaries = []
    where = lambda d: f" of {d}" if out.label else ""  # noqa: E731
    for p, d in enumerate(out.dirs):
        w.stage = f"writing the plots{where(d)}"
        hist = batch.rows(progress.history, p)
        summary = summarize(batch.exp, hist, wall, batch.num_seeds)
        summary.update(extras[p] if extras else {})
        if out.writer:
            if plots:
                make_plots(batch.exp, batch.env, hist, d)
            students = batch.rows(progress.state.student, p) if final_sets else None
            for resolved in final_sets:
                w.stage = f"writing the final evaluation on {resolved[2]!r}{where(d)}"
                final_eval(batch.exp, batch.env, batch.student, students, batch.num_seeds, resolved, d, progress.done,
                           final_episodes, early=early)
            w.stage = f"writing summary.json{where(d)}"
            rundir.write_atomic(d / "summary.json", json.dumps(summary, indent=2))
        summaries.append(summary)
    return summaries


def summarize(exp, hist: dict, wall: float, num_seeds: int) -> dict:
    """``summary.json`` of one run (``hist``: its flat metrics history [seeds, steps, ...])."""
    from shed_jax import reporting
    from shed_jax.runtime import source_commit

    T = exp.loop.steps_per_episode
    last = hist["test_return"][:, -1]
    m, se = reporting.mean_se(last)
    last_ep = hist["episode"][0] == hist["episode"][0, -1]
    train_steps = hist["info/env_steps_train"].astype(np.float64)
    return {
        "env": exp.env, "method": exp.method, "preset": exp.preset, "seeds": num_seeds,
        "budget_steps": int(hist["step"].shape[1]), "steps_per_episode": T,
        "final_test_return_mean": float(m), "final_test_return_se": float(se),
        "final_test_return_per_seed": [float(x) for x in last],
        "final_test_return_per_level": [float(x) for x in np.nanmean(hist["test_return_per_level"][:, -1], axis=0)],
        "student_env_steps_last_episode": float(train_steps[:, last_ep].sum(axis=1).mean()),
        "student_env_steps_total": float(train_steps.sum(axis=1).mean()),
        "eval_env_steps_total": float(hist["info/env_steps_eval"].astype(np.float64).sum(axis=1).mean()),
        "wall_time_s": wall,
        "wall_time_per_seed_s": wall / num_seeds,
        "commit": source_commit(),  # the code that finished the run (config.json names the one that started it)
    }


def make_plots(exp, env, hist: dict, out: pathlib.Path) -> None:
    """test_return.png, test_return_per_level.png, generated_levels.png and student_training.png of one run."""
    from shed_jax import reporting

    x, y = reporting.last_episode_curve(hist, "test_return")
    label = reporting.episode_label(exp.method, hist, exp.loop.num_episodes)
    reporting.plot_curves({label: (x, y)}, out / "test_return.png", xlabel="student env steps", ylabel="mean test return",
                          title=f"{exp.method} on {exp.env}: test return (mean ± SE over seeds)")
    x, per_level = reporting.last_episode_curve(hist, "test_return_per_level")  # [S, steps, L]
    # one small panel per level, shared axes (ten overlaid bands could not be told apart)
    reporting.plot_panels(x, per_level, out / "test_return_per_level.png", xlabel="student env steps",
                          ylabel="test return", title=f"{exp.method} on {exp.env}: per test level (mean ± SE over seeds)")
    levels = hist.get("info/levels")
    if levels is not None and levels.ndim == 4 and levels.shape[-1] == env.param_space.dim:
        xs = np.arange(levels.shape[1])
        reporting.plot_parameters(xs, levels, env.param_space.names, out / "generated_levels.png",
                                  title=f"{exp.method} on {exp.env}: generated level parameters per budget step")
    reporting.plot_student_training(hist, out / "student_training.png",
                                    title=f"{exp.method} on {exp.env}: the student's PPO updates per budget step "
                                          f"(mean ± SE over seeds; panel title: last value)")


def heartbeat_wait(thunk, what: str):
    """``thunk()`` in a worker with a "still <what>" line every HEARTBEAT_S seconds (``in_worker``): the
    ``wait`` of ``evaluation.evaluate_students``, whose compile and roll-outs can take minutes."""
    return in_worker(thunk, "eval", heartbeat=HEARTBEAT_S, what=what)


def final_eval(exp, env, student, student_state, num_seeds: int, resolved, out: pathlib.Path, step: int,
               episodes: int, early: "FinalEvalCompile | None" = None) -> None:
    """Evaluate the final students on one level set (as ``eval`` does) and write final_eval_<set>.json
    (with the device, command and date).

    The episode cap is the test set's (``LoopSpec.test_max_steps``). The run's results are already
    written, so a failure here is reported and does not fail the run. The JSON's ``wall_time_s`` is
    the evaluation's own time, compile included unless ``early`` compiled it while training ran
    (``FinalEvalCompile``; then any wait for that compile to end); the run's ``summary.json`` wall time
    stops before it.
    """
    from shed_jax.evaluation import evaluate_students

    t0 = time.time()
    levels = len(resolved[1])
    compiled = early.program(resolved[2]) if early is not None else None
    how = "compiled during training" if compiled is not None else "compiling first"
    print(f"[shed_jax] final evaluation on {resolved[2]!r}: {levels} level(s) x {num_seeds} seed(s) x {episodes} "
          f"episode(s) ({how})...", flush=True)
    try:
        body, text = evaluate_students(exp, env, student, student_state, num_seeds, resolved, episodes=episodes,
                                       max_steps=exp.loop.test_max_steps, wait=heartbeat_wait, compiled=compiled)
    except Exception as err:  # noqa: BLE001 - see the docstring
        print(f"[shed_jax] final evaluation on {resolved[2]!r} failed: {type(err).__name__}: {err}", file=sys.stderr)
        return
    path = out / f"final_eval_{body['levels']}.json"
    from shed_jax.runtime import provenance

    rundir.write_atomic(path, json.dumps({"run": str(out), "budget_step": step, "wall_time_s": time.time() - t0,
                                          **provenance("shed_jax"), **body}, indent=2))
    solved = f"solved: return > {body['solved_threshold']:g}" if body["solved_threshold"] is not None else "no solved threshold"
    print(f"[shed_jax] final students on {body['levels']!r} ({num_seeds} seed(s) x {episodes} episode(s) per level, {solved}):")
    print(text)
    print(f"[shed_jax] wrote {path}")


class FinalEvalCompile:
    """The final evaluation's programs (``evaluation.evaluation_program``, one per ``--final-eval`` level
    set) compiled in a worker thread while training runs, for ``students`` as the chunks leave them (so
    the final students' shapes and placement). On a GPU the host mostly waits for the device while a
    chunk runs, and a walker's evaluation compiles for minutes. ``program(name)`` waits for the worker
    (a heartbeat line while it takes long) and gives the compiled program, or None where that compile
    failed (a line naming the error when it fails, and again here): the final evaluation then compiles
    its own. A run that stops
    before its end (time limit, signal, non-finite guard) drops the worker: ``python -m shed_jax``
    then exits at once (``__main__._exit`` knows the thread's name); a caller of ``run`` from Python
    leaves it to finish or die with the process."""

    def __init__(self, batch: Batch, final_sets, students, episodes: int, max_steps: int | None,
                 say: Callable[[str], None] = _say):
        import jax

        from shed_jax.evaluation import evaluation_program
        from shed_jax.experiment import seed_keys

        self.programs: dict = {}
        self.errors: dict[str, str] = {}  # name -> "Type: message" of a compile that failed
        keys = seed_keys(0, batch.num_seeds)  # final_eval's seed
        # shapes, dtypes and placement only: the first chunk's students are not kept alive by the compile
        students = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), students)

        def work():
            for levels, _, name in final_sets:
                try:
                    program = evaluation_program(batch.student, levels, episodes, max_steps)
                    self.programs[name] = program.lower(students, keys).compile()
                except Exception as err:  # noqa: BLE001 - see the class docstring
                    self.programs[name] = None
                    self.errors[name] = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
                    # said now too (through ``say``, e.g. the progress bar's writer, so that the line is
                    # not glued to the bar): a run stopped by its time limit never reaches program()
                    say(f"the final evaluation's compile begun during training failed ({self.errors[name]}); "
                         "it compiles again after training")

        # named for __main__._exit: a run stopped by its time limit may exit while this still compiles
        self.thread = threading.Thread(target=work, name="shed_jax-final-eval-compile", daemon=True)
        self.thread.start()

    def program(self, name: str, say: Callable[[str], None] = _say):
        if self.thread.is_alive():  # the main thread waits in in_worker's loop: signals and heartbeat lines as ever
            in_worker(self.thread.join, "eval", heartbeat=HEARTBEAT_S,
                      what="compiling the final evaluation (begun during training)", say=say)
        if name in self.errors:
            say(f"the final evaluation's compile begun during training failed ({self.errors[name]}); compiling it again")
        return self.programs.get(name)


def gif(env, student, state, tests, out: pathlib.Path) -> None:
    """final_student.gif of seed 0's final student (its first, with several students) on a test level; any
    failure but a full disk is one line."""
    print("[shed_jax] rendering a GIF of seed 0's final student on a test level...", flush=True)
    try:
        from shed_jax.methods.parallel_students import StudentPool
        from shed_jax.visualize import student_gif

        if isinstance(student, StudentPool):  # several students per seed: the first one's GIF
            student, state = student.student, StudentPool.member(state.student, 0, axis=1)
        path = student_gif(env, student, state, tests, out / "final_student.gif")
        print(f"[shed_jax] wrote {path}")
    except ImportError as err:  # the visualisation module is optional
        print(f"[shed_jax] no GIF: shed_jax.visualize is not available ({err})")
    except NotImplementedError as err:  # an env without a renderer
        print(f"[shed_jax] no GIF: {err}")
    except OSError as err:
        if errors.is_disk_full(err):
            raise  # reported by the caller with what is safe on disk
        print(f"[shed_jax] no GIF: {type(err).__name__}: {err}")
    except Exception as err:  # noqa: BLE001 - the results are written; a GIF failure must not fail the run
        print(f"[shed_jax] no GIF: {type(err).__name__}: {err}")


# ---------------------------------------------------------------------------------------------
# python -m shed_jax run
# ---------------------------------------------------------------------------------------------

CompileWhen = Literal["auto", "early", "late"]


@dataclasses.dataclass
class RunOptions:
    """The run command's options (its flags; None: the preset's or the saved run's value)."""

    env: str | None = None
    method: str | None = None
    preset: str | None = None
    seeds: int | None = None
    seed: int | None = None
    episodes: int | None = None
    steps_per_episode: int | None = None
    test_episode_every: int | None = None
    chunk: int | None = None
    set: list = dataclasses.field(default_factory=list)
    ppo: list = dataclasses.field(default_factory=list)
    out: str | None = None
    no_gif: bool | None = None  # None: the resumed run's choice, else False (OUTPUT_DEFAULTS)
    final_eval: str | None = None  # None: the resumed run's choice, else the env's own (OUTPUT_DEFAULTS)
    final_eval_episodes: int | None = None  # None: the resumed run's, else 10
    resume: str | None = None
    from_step: int | None = None
    restart: bool = False
    keep: int | None = None  # None: the resumed run's, else 3
    no_checkpoint: bool = False
    checkpoint_every: float | None = None  # None: the resumed run's, else 0.0
    stop_after: int | None = None
    time_limit: float | None = None
    profile_chunk: int | None = None  # profile this process's K-th chunk (shed_jax.profiling)
    # when the final evaluation compiles: "early", in a worker thread from the first chunk on, while
    # training runs; "late", after training; "auto": early on a GPU (the host is idle meanwhile),
    # late elsewhere (on a CPU a compile would slow the training it overlaps)
    compile_final_eval: CompileWhen = "auto"

    #: the counts (argparse checks them too, for callers that build the options themselves)
    COUNTS = ("seeds", "episodes", "steps_per_episode", "test_episode_every", "chunk", "keep", "final_eval_episodes",
              "stop_after", "from_step", "profile_chunk")

    #: how a run keeps its outputs: saved with the run (config.json's ``output``), so ``--resume`` goes on
    #: as the run started unless the flag is given again (the last one given is saved in turn)
    OUTPUT_DEFAULTS = {"keep": 3, "checkpoint_every": 0.0, "no_gif": False, "final_eval": None, "final_eval_episodes": 10}

    @classmethod
    def from_args(cls, args) -> "RunOptions":
        return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)})

    def with_output(self, saved: dict | None) -> "RunOptions":
        """Each output setting not given: the ``saved`` run's (a resumed run), else its default."""
        saved = saved or {}
        return dataclasses.replace(self, **{k: saved.get(k, default) if getattr(self, k) is None else getattr(self, k)
                                            for k, default in self.OUTPUT_DEFAULTS.items()})

    def output(self) -> dict:
        """The output settings saved with the run."""
        return {k: getattr(self, k) for k in self.OUTPUT_DEFAULTS}

    def check(self) -> None:
        """UsageError for a count < 1, a bad time limit or flags that do not go together."""
        for name in self.COUNTS:
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise UsageError(f"--{name.replace('_', '-')} must be an integer >= 1, got {value!r}")
        if self.time_limit is not None and not 0 <= self.time_limit < math.inf:
            raise UsageError(f"--time-limit must be a finite number of seconds >= 0, got {self.time_limit!r}")
        if self.checkpoint_every is not None:
            check_checkpoint_every(self.checkpoint_every, self.no_checkpoint)
        if self.from_step is not None and not self.resume:
            raise UsageError("--from-step N chooses the checkpoint that --resume DIR continues from; give --resume DIR as well")
        if self.compile_final_eval not in get_args(CompileWhen):
            raise UsageError(f"--compile-final-eval must be one of {', '.join(get_args(CompileWhen))}, "
                             f"got {self.compile_final_eval!r}")
        if self.restart:
            if self.resume:
                raise UsageError("--restart starts the run in --out DIR over, --resume DIR continues it: give one of them")
            if self.out is None:
                raise UsageError("--restart clears the run directory given with --out DIR: give --out")


def check_checkpoint_every(seconds: float, no_checkpoint: bool) -> None:
    """UsageError unless ``--checkpoint-every`` is a finite number of seconds >= 0 that goes with the other flags."""
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 0 <= seconds < math.inf:
        raise UsageError(f"--checkpoint-every must be a finite number of seconds >= 0, got {seconds!r}")
    if seconds and no_checkpoint:
        raise UsageError("--checkpoint-every sets how often checkpoints are saved and --no-checkpoint saves none: give one of them")


def run(opts: RunOptions) -> int:
    """``python -m shed_jax run``: one UED method on one environment, seeds vmapped, end to end.

    Every option is checked before the run directory is made (UsageError; CheckpointError for a
    checkpoint that cannot be used). Returns the exit status: 0, EXIT_NONFINITE, EXIT_STOPPED or
    128 + signal; a failed write raises WriteFailedError.
    """
    import jax

    opts.check()
    backend = jax.default_backend()
    plan = None
    made: list = []  # what this process created before the first chunk (removed if start-up is interrupted)
    with StopRequest() as signals:
        try:
            plan = rundir.plan_resume(opts, backend) if opts.resume else rundir.plan_fresh(opts, backend)
            opts = opts.with_output(plan.config.get("output"))
            plan.config["output"] = opts.output()  # saved with every checkpoint from here on
            started = _start_run(opts, plan, made)
            if started is None:
                return 0
        except StartupInterrupted as sig:
            resuming = plan is not None and plan.resume_step is not None
            return startup_interrupted(sig.signum, rundir.resume_command(plan.out) if resuming else None, made)
        batch, placed, progress, compiled, final_sets = started
        count = None
        if opts.profile_chunk is not None:
            compiled, count = profiled(compiled, opts.profile_chunk, plan.out)
        stop = StopRules(signals, opts.stop_after, None if opts.time_limit is None else progress.t0 + opts.time_limit,
                         opts.time_limit)
        code = _train_run(opts, plan, batch, compiled, progress, final_sets, stop)
        if count is not None and not count.traced:
            _say(f"[shed_jax] --profile-chunk {count.call}: this process ran {count.n} chunk(s), so none was profiled")
        return code


def profiled(compiled: dict, chunk: int, out) -> tuple[dict, "profiling.TraceCount"]:
    """The compiled chunks with this process's ``chunk``-th call of them profiled (``shed_jax.profiling``),
    and their shared count: ``out/profile_chunkK.json`` says where that call's time went, with the walls
    of the calls up to the one after it (waited for one by one, so they can be compared)."""
    from shed_jax import profiling

    path = str(pathlib.Path(out) / f"profile_chunk{chunk}.json")
    count = profiling.TraceCount(chunk, path, say=_say)
    _say(f"[shed_jax] --profile-chunk {chunk}: this process's chunk {chunk} runs under jax.profiler; "
         f"its summary goes to {path}")
    return {n: profiling.TracedCompiled(c, count) for n, c in compiled.items()}, count


def _start_run(opts: RunOptions, plan: rundir.RunPlan, made: list):
    """Everything before the first chunk: build (checked), restore or create the run directory, compile.

    None for a finished run (said): its checkpoint is read back to check it, nothing is written.
    """
    import jax

    from shed_jax import sharding
    from shed_jax.evaluation import final_level_sets

    exp, out = plan.exp, plan.out
    fresh = plan.resume_step is None
    parts = xp.build_checked(exp, fresh)
    final_sets = final_level_sets(opts.final_eval, exp, parts[0], parts[3])
    batch = make_batch(exp, parts, [({}, {})], num_seeds=plan.num_seeds, root_seed=plan.root_seed, chunk=plan.chunk)
    placed = place(batch, sharding.batch_mesh(jax.devices()[:1]))  # a run: a mesh of one device
    total = batch.total
    progress = Progress(state=None)
    if not fresh:
        restored = rundir.restore(plan, state_target(batch, placed))
        progress = Progress(on_mesh(restored.state, placed), restored.step, restored.history,
                            float(restored.extra.get("wall_time_s", 0.0)), saved=restored.step)
        if plan.finished:
            print(f"[shed_jax] {out} holds a finished run (budget step {progress.done}/{total}, summary.json written, the last "
                  f"checkpoint intact): nothing to do; `python -m shed_jax eval --run {out}` evaluates its students")
            return None
        rundir.discard_newer(plan)
        print(f"[shed_jax] resuming {out} from budget step {progress.done}/{total}")
        if (note := rundir.commit_note(plan.config)) is not None:
            print(f"[shed_jax] note: {note}")
        print(f"[shed_jax] {rundir.reconcile_metrics_jsonl(out / 'metrics.jsonl', progress.history, progress.done, plan.num_seeds)}")
    else:
        rundir.create_run_dir(plan, made)
    print(f"[shed_jax] {exp.method} on {exp.env}: {exp.loop.num_episodes} episode(s) x {exp.loop.steps_per_episode} "
          f"budget steps, {plan.num_seeds} seed(s), ~{exp.env_steps_per_budget_step:,} student env steps per budget step -> {out}")
    progress.t0 = time.time()  # this session's wall clock, compile included (summary.json's wall_time_s)
    progress.state, compiled = compile_batch(batch, placed, progress.done, progress.state)
    return batch, placed, progress, compiled, final_sets


class _RunReporter(Reporter):
    """The run's progress bar (steps; created after the compile, so its rate and ETA count training only)
    and one line per chunk."""

    def __init__(self, exp, num_seeds: int, on_first_chunk: Callable[[Progress], None] | None = None):
        self.exp, self.num_seeds, self.bar = exp, num_seeds, None
        self.on_first_chunk = on_first_chunk  # called once, after the first chunk of this process

    def begin(self, progress, total):
        from tqdm import tqdm

        self.total = total
        self.bar = tqdm(total=total, initial=progress.done, unit="step", desc=f"{self.exp.method}/{self.exp.env}",
                        dynamic_ncols=True)

    def chunk(self, progress, steps, flat):
        from shed_jax import reporting

        if self.on_first_chunk is not None:
            first, self.on_first_chunk = self.on_first_chunk, None
            first(progress)
        self.bar.update(steps)
        steps_train = progress.history["info/env_steps_train"].astype(np.float64).sum(axis=1).mean()
        tr = flat["test_return"][:, -1]
        teacher_r = np.nanmean(flat["info/teacher_reward"]) if np.any(np.isfinite(flat["info/teacher_reward"])) else math.nan
        # the test set runs only in some teacher episodes (--test-episode-every): say so, not "nan"
        test = (f"test return {np.nanmean(tr):8.1f} ± {reporting.mean_se(tr)[1]:.1f}" if np.any(np.isfinite(tr))
                else "test return  (not run in this episode)")
        self.bar.write(f"step {progress.done:5d}/{self.total}  episode {int(flat['episode'][0, -1])}  "
                       f"student env steps/seed {steps_train:,.0f}  {test}  teacher reward {teacher_r:8.3f}  "
                       f"{steps_train * self.num_seeds / max(progress.wall(), 1e-9):,.0f} train steps/s")

    def note(self, text):
        self.bar.write(f"[shed_jax] {text}")

    def end(self):
        if self.bar is not None:
            self.bar.close()


def compile_early(when: str) -> bool:
    """``RunOptions.compile_final_eval`` resolved: "auto" is early on a GPU."""
    import jax

    return when == "early" or (when == "auto" and jax.default_backend() == "gpu")


def _train_run(opts, plan, batch, compiled, progress, final_sets, stop) -> int:
    """The chunks (checked, written, saved), then the summary, plots, final evaluation and GIF."""
    out, total = plan.out, batch.total
    checkpointing = not opts.no_checkpoint

    def safe() -> str:
        if progress.saved is not None:
            return (f"safe on disk: checkpoint {progress.saved} in {out / 'checkpoints'} (and metrics.jsonl up to it); "
                    f"after freeing space continue with: {rundir.resume_command(out)}")
        if checkpointing:
            return f"no checkpoint was saved yet; after freeing space start over with: python -m shed_jax run --out {out} --restart ..."
        return "nothing resumable (--no-checkpoint)"

    output = Output([out], [out.name], out if checkpointing else None, opts.keep, plan.config,
                    lambda p: {"wall_time_s": p.wall()}, every=opts.checkpoint_every)
    early: list = []  # the final evaluation's programs, compiling from the first chunk on (compile_early)

    def compile_final_eval(p: Progress) -> None:  # called by the reporter, while its bar is shown
        try:
            early.append(FinalEvalCompile(batch, final_sets, batch.rows(p.state.student, 0), opts.final_eval_episodes,
                                          batch.exp.loop.test_max_steps, say=reporter.note))
        except Exception as err:  # noqa: BLE001 - a head start only: the final evaluation compiles its own
            reporter.note(f"the final evaluation will compile after training ({type(err).__name__}: {err})")

    hook = compile_final_eval if final_sets and compile_early(opts.compile_final_eval) else None
    reporter = _RunReporter(batch.exp, batch.num_seeds, hook)
    stopped = train(batch, compiled, progress, output, stop, reporter, safe)
    if stopped is not None:
        code, reason = stopped
        if code != EXIT_NONFINITE:
            print(f"[shed_jax] {reason}: stopped at budget step {progress.done}/{total}")
            if checkpointing:
                print(f"[shed_jax] checkpoint saved in {out / 'checkpoints' / str(progress.done)}; resume with:\n"
                      f"  {rundir.resume_command(out)}")
            else:
                print("[shed_jax] no checkpoint was written (--no-checkpoint): this run cannot be resumed")
        return code
    wall = progress.wall()
    signals = stop.signals
    if signals is not None and progress.saved is not None:
        if signals.signum is not None:  # it came during the last chunk (which finished and is saved)
            return results_interrupted(signals.signum, "training the last budget step", out, progress.saved, not opts.no_gif)
        signals.results = True  # training is saved: a signal from here on stops at once
    elif signals is not None:  # --no-checkpoint: the results are all there is, so a first signal lets them be written
        signals.finishing = "writing the results first (no checkpoint was saved, so they cannot be written later)"
    with Writes(safe, "writing the plots") as w:
        try:
            print(f"[shed_jax] training done ({progress.done}/{total} budget steps); writing the plots and summary.json...",
                  flush=True)
            summary, = write_results(batch, progress, output, w, wall=wall, final_sets=final_sets,
                                     final_episodes=opts.final_eval_episodes,
                                     extras=[{"wall_time_per_chunk_s": progress.wall_per_chunk()}],
                                     early=early[0] if early else None)
            if not opts.no_gif:
                w.stage = "writing final_student.gif"
                gif(batch.env, batch.student, progress.state, batch.tests, out)
            if signals is not None:
                signals.results = False  # all is written: a signal now takes the ordinary path
        except ResultsInterrupted as sig:
            return results_interrupted(sig.signum, w.stage, out, progress.saved, not opts.no_gif)
    print(json.dumps({k: summary[k] for k in ("final_test_return_mean", "final_test_return_se", "wall_time_s")}, indent=2))
    print(f"[shed_jax] results in {out}")
    return 0
