"""Sweeps: seeds x hyperparameter grid x methods, one compiled program per shape group.

Every method runs the cartesian product of the ``--grid`` axes, each point with ``--seeds`` seeds.
A grid key is resolved per method (``classify``):

* a dynamic hyperparameter -- the method's (SHED/h-MDP: ``eta``, ``psi`` (SHED), ``actor_lr``,
  ``critic_lr``, ``explore_sigma``) or the student's (``ppo.lr``, ``ppo.ent_coef``, ... the fields of
  ``PPOHyperparams``): points that differ only in these share one program; the whole group
  (points x seeds) is one vmapped call, compiled once;
* a static field -- of the method's config (``num_eval_levels``, ``updates_per_step``, ...) or of
  ``PPOConfig`` (``ppo.num_envs``, ...): it changes shapes or program structure, so each value forms
  its own *shape group*, compiled once.

Any other key is an error that names the method and the keys it knows. ``--set KEY=VALUE`` fixes a
key for every point (resolved the same way, not part of point names).

Seeds are common random numbers: seed i of every point uses ``fold_in(PRNGKey(--seed), i)``, the
keys ``python -m shed_jax run`` uses. Each group is one :class:`shed_jax.driver.Batch` (row = point
* seeds + seed) split over all visible devices (padded when it does not divide, or ``--no-pad`` to
refuse), trained, checked, saved and reported by ``shed_jax.driver`` exactly as a run is.

Output, per point ``OUT/<method>/<point>/``: a run's ``config.json`` (plus the point),
``metrics.jsonl``, plots, final evaluations and ``summary.json`` (plus the point's values); for the
sweep ``OUT/sweep.json`` and ``OUT/sweep.md``: the table point -> final test return mean +- SE over
seeds. After every chunk (or at most every ``--checkpoint-every`` seconds) the group in progress
saves its whole batch under ``OUT/checkpoints/<group>/`` (the last one kept), and
``OUT/sweep_args.json`` holds the command's arguments: ``--resume OUT`` re-plans from those, keeps
the groups whose points all have a
``summary.json``, restores the group in progress (its configuration must match), cuts its points'
``metrics.jsonl`` back to the checkpoint's step and continues (docs/sweeps.md).
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import math
import pathlib
import re
import sys
import time
from typing import Any, Callable

import numpy as np

from shed_jax import driver, rundir
from shed_jax.errors import EXIT_NONFINITE, EXIT_STOPPED, UsageError

KINDS = ("method_hparam", "student_hparam", "method_config", "student_config")
STUDENT_PREFIX = "ppo."


# ---------------------------------------------------------------------------------------------
# grid parsing and planning: pure functions
# ---------------------------------------------------------------------------------------------

def split_top_level(text: str) -> list[str]:
    """Split on commas outside brackets/braces/quotes: ``'0,[1,2],"a,b"'`` -> 3 items."""
    items, depth, quote, cur = [], 0, None, []
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{(":
            depth += 1
        elif ch in "]})":
            depth -= 1
        elif ch == "," and depth == 0:
            items.append("".join(cur))
            cur = []
            continue
        cur.append(ch)
    items.append("".join(cur))
    return [s.strip() for s in items]


def parse_value(text: str) -> Any:
    """JSON if it parses (numbers, true/false/null, lists), else the string itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_grid(items: list[str]) -> dict[str, list]:
    """``['eta=0,10', 'psi=0.25,0.5']`` -> ``{'eta': [0, 10], 'psi': [0.25, 0.5]}`` (order kept)."""
    grid: dict[str, list] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--grid expects KEY=V1,V2,..., got {item!r}")
        key, text = (s.strip() for s in item.split("=", 1))
        if not key:
            raise ValueError(f"--grid {item!r}: empty key")
        if key in grid:
            raise ValueError(f"--grid key {key!r} given twice; list all its values in one --grid")
        parts = split_top_level(text)
        if any(not p for p in parts):
            raise ValueError(f"--grid {item!r}: empty value (KEY=V1,V2,...)")
        values = [parse_value(p) for p in parts]
        seen = []
        for v in values:
            if v in seen:
                raise ValueError(f"--grid key {key!r} lists {v!r} twice")
            seen.append(v)
        grid[key] = values
    return grid


def parse_fixed(items: list[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` items (parsed as the run's ``--set``)."""
    from shed_jax.experiment import parse_overrides

    return parse_overrides(items)


@dataclasses.dataclass(frozen=True)
class KeySpace:
    """The keys one method accepts: dynamic hyperparameters and static config fields, its and the student's."""

    method: str
    method_hparams: tuple = ()
    student_hparams: tuple = ()
    method_config: tuple = ()
    student_config: tuple = ()

    def known(self) -> list[str]:
        own = sorted(set(self.method_hparams) | set(self.method_config))
        return own + [STUDENT_PREFIX + k for k in sorted(set(self.student_hparams) | set(self.student_config))]


def key_space(method_name: str, method, ppo_config) -> KeySpace:
    """The KeySpace of a built method object and the student's PPOConfig."""
    from shed_jax.student.config import PPOHyperparams

    return KeySpace(
        method=method_name,
        method_hparams=tuple(getattr(method, "hparam_names", ())),
        student_hparams=tuple(f.name for f in dataclasses.fields(PPOHyperparams)),
        method_config=tuple(f.name for f in dataclasses.fields(method.config)),
        student_config=tuple(f.name for f in dataclasses.fields(ppo_config) if f.name != "hparams"),
    )


def classify(key: str, space: KeySpace) -> tuple[str, str]:
    """``(kind, field)`` of a grid key for one method; ValueError naming the method otherwise.

    Unprefixed keys belong to the method (dynamic, then static); ``ppo.``-prefixed
    keys to the student (dynamic ``PPOHyperparams``, then static ``PPOConfig``).
    """
    if key.startswith(STUDENT_PREFIX):
        field = key[len(STUDENT_PREFIX):]
        if field in space.student_hparams:
            return "student_hparam", field
        if field in space.student_config:
            return "student_config", field
        raise ValueError(f"method {space.method!r}: the student has no hyperparameter or config field {field!r} "
                         f"(key {key!r}); known keys: {', '.join(space.known())}")
    if key in space.method_hparams:
        return "method_hparam", key
    if key in space.method_config:
        return "method_config", key
    hint = ""
    if key in space.student_hparams or key in space.student_config:
        hint = f" (a student key: write {STUDENT_PREFIX}{key})"
    raise ValueError(f"method {space.method!r} has no hyperparameter or config field {key!r}{hint}; "
                     f"known keys: {', '.join(space.known())}")


def expand_grid(grid: dict[str, list]) -> list[dict]:
    """The cartesian product, first key slowest: ``{'a': [1, 2], 'b': [3]}`` -> ``[{a:1,b:3}, {a:2,b:3}]``."""
    keys = list(grid)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(grid[k] for k in keys))]


def _fmt(v: Any) -> str:
    return v if isinstance(v, str) else json.dumps(v)


def point_name(values: dict) -> str:
    """``{'eta': 0, 'psi': 0.25}`` -> ``'eta=0,psi=0.25'``; no grid keys -> ``'default'``."""
    return ",".join(f"{k}={_fmt(v)}" for k, v in values.items()) or "default"


def dir_name(name: str) -> str:
    """A file-system-safe form of a point name."""
    return re.sub(r"[^A-Za-z0-9._=,+-]", "_", name)


@dataclasses.dataclass(frozen=True)
class Point:
    name: str
    values: dict  # the point's grid values
    method_hparams: dict  # field -> value overrides of the method's hyperparameters
    student_hparams: dict  # field -> value overrides of PPOHyperparams


@dataclasses.dataclass(frozen=True)
class Group:
    """Points of one method that share every static value: one program, one vmapped call."""

    method: str
    method_config: dict  # static overrides of the method's config (on top of the preset)
    student_config: dict  # static overrides of PPOConfig
    points: tuple  # of Point

    @property
    def label(self) -> str:
        statics = {**self.method_config, **{STUDENT_PREFIX + k: v for k, v in self.student_config.items()}}
        return f"{self.method}[{point_name(statics)}]" if statics else self.method


def plan(space: KeySpace, grid: dict[str, list], fixed: dict | None = None) -> tuple[list[Group], list[str]]:
    """Split one method's grid into shape groups. Returns ``(groups, notes)``.

    ``fixed`` (``--set``) applies to every point.
    """
    fixed = dict(fixed or {})
    notes = []
    kinds = {k: classify(k, space) for k in list(grid) + list(fixed)}
    base = {kind: {} for kind in KINDS}
    for k, v in fixed.items():
        kind, field = kinds[k]
        base[kind][field] = v
    groups: dict[str, dict] = {}
    for values in expand_grid(grid):
        parts = {kind: dict(base[kind]) for kind in KINDS}
        for k, v in values.items():
            kind, field = kinds[k]
            parts[kind][field] = v
        name = point_name(values)
        static = (json.dumps(parts["method_config"], sort_keys=True), json.dumps(parts["student_config"], sort_keys=True))
        g = groups.setdefault(static[0] + "|" + static[1], {"method_config": parts["method_config"],
                                                           "student_config": parts["student_config"], "points": []})
        g["points"].append(Point(name, values, parts["method_hparam"], parts["student_hparam"]))
    out = [Group(space.method, g["method_config"], g["student_config"], tuple(g["points"])) for g in groups.values()]
    return out, notes


def plan_groups(methods: list[str], grid: dict, fixed: dict, make_experiment: Callable, build: Callable) -> list[Group]:
    """Every method's shape groups (each method built once for its keys; notes printed)."""
    groups = []
    for name in methods:
        exp = make_experiment(name, {}, {})
        _, _, method, _ = build(exp)
        gs, notes = plan(key_space(name, method, exp.ppo), grid, fixed)
        for note in notes:
            print(f"[shed_jax] note: {note}")
        groups += gs
    return groups


# ---------------------------------------------------------------------------------------------
# building and running groups
# ---------------------------------------------------------------------------------------------

@dataclasses.dataclass
class BuiltGroup:
    group: Group
    batch: driver.Batch  # the group's points x seeds (static values applied, every value validated)

    @property
    def exp(self):
        return self.batch.exp


def build_group(group: Group, make_experiment: Callable, build: Callable, *, num_seeds: int, root_seed: int = 0,
                chunk: int | None = None) -> BuiltGroup:
    """The group's Experiment, parts and batch; every static and dynamic value is validated here (before compiling)."""
    exp = make_experiment(group.method, dict(group.method_config), dict(group.student_config))
    batch = driver.make_batch(exp, build(exp), [(p.student_hparams, p.method_hparams) for p in group.points],
                              num_seeds=num_seeds, root_seed=root_seed, chunk=chunk)
    return BuiltGroup(group, batch)


#: configuration keys a resumed group must share with its checkpoint
GROUP_KEYS = ("group", "points", "experiment", "seeds", "root_seed", "chunk", "batch")


def group_checkpoint_dir(out: pathlib.Path, group) -> pathlib.Path:
    return out / "checkpoints" / dir_name(group.label)


def point_dir(out: pathlib.Path, group, point) -> pathlib.Path:
    """``OUT/<method>/<point>/``: where one point's run files go."""
    return out / group.method / dir_name(point.name)


def _num_chunks(built: BuiltGroup) -> int:
    return math.ceil(built.batch.total / built.batch.chunk)


class _GroupReporter(driver.Reporter):
    """The sweep's bar (chunks of every group) and one line per chunk: the mean test return of each point."""

    def __init__(self, say: Callable, bar, label: str, points: int, seeds: int):
        self.say, self.bar, self.label, self.points, self.seeds = say, bar, label, points, seeds

    def begin(self, progress, total):
        self.total = total

    def note(self, text):
        self.say(f"[shed_jax] {text}")

    def chunk(self, progress, steps, flat):
        if self.bar is not None:
            self.bar.update(1)
        tr = flat["test_return"][:, -1].reshape(self.points, self.seeds)
        means = np.nanmean(tr, axis=1) if np.any(np.isfinite(tr)) else np.full(self.points, math.nan)
        self.say(f"{self.label}: step {progress.done}/{self.total}  test return per point " + " ".join(f"{m:.1f}" for m in means))


def run_group(built: BuiltGroup, *, out: pathlib.Path, mesh, pad: bool = True, plots: bool = True, bar=None,
              log: Callable = print, final_sets=(), final_episodes: int = 10, checkpoint: bool = True,
              resume: bool = False, stop: driver.StopRules | None = None, made: list | None = None,
              checkpoint_every: float = 0.0) -> list[dict] | None:
    """Run one group (all its points x seeds in one vmapped, sharded program); write each point's files.

    ``final_sets``: level sets resolved by ``evaluation.resolve_levels``; each point's final students
    are evaluated on them as ``run --final-eval`` does (seed i with ``fold_in(PRNGKey(0), i)``).
    ``checkpoint``: save the state and history after every chunk, or at most every ``checkpoint_every``
    seconds (``group_checkpoint_dir``);
    ``resume``: continue from the latest such checkpoint if there is one. ``stop``: when to stop at a
    chunk boundary (returns None, not finished; ``stop.stopped`` says why). ``made`` collects the
    directories and files made before training starts (removed if start-up is interrupted).
    """
    import jax

    from shed_jax.checkpoint import RunCheckpointer, complete_steps
    from shed_jax.rundir import reconcile_metrics_jsonl

    stop = stop or driver.StopRules()
    exp, group, batch = built.exp, built.group, built.batch
    P, S, total = len(group.points), batch.num_seeds, batch.total

    def say(text: str) -> None:
        (bar.write if bar is not None else log)(text)
        sys.stdout.flush()  # a compile may follow: the line must not wait in a pipe's buffer

    if stop.signalled():
        return None
    t0 = time.time()
    dirs = [point_dir(out, group, p) for p in group.points]
    writer = jax.process_index() == 0  # several hosts: every process computes, process 0 writes
    placed = driver.place(batch, mesh, pad)
    for d, p in zip(dirs, group.points):
        if not writer:
            break
        for path in (d.parent, d):
            if not path.exists():
                path.mkdir(parents=True)
                made is not None and made.append(path)
        config = {**rundir.run_config(exp, S, batch.root_seed, jax.default_backend(), mesh.devices.flat, batch.chunk),
                  "sweep_point": {"name": p.name, "values": p.values, "group": group.label,
                                  "method_hparams": p.method_hparams, "student_hparams": p.student_hparams}}
        (d / "config.json").write_text(rundir.config_json(config))
        made is not None and made.append(d / "config.json")
    group_config = {"group": group.label, "points": [p.name for p in group.points], "experiment": exp.to_dict(),
                    "seeds": S, "root_seed": batch.root_seed, "chunk": batch.chunk, "batch": placed.size}
    if (checkpoint or resume) and jax.process_count() > 1:
        raise ValueError("sweep checkpoints are written by one host only; pass --no-checkpoint on several hosts")
    ckpt_dir = group_checkpoint_dir(out, group)
    progress = driver.Progress(state=None, t0=t0)
    if resume:
        if complete_steps(ckpt_dir):
            with RunCheckpointer(ckpt_dir, create=False) as reader:
                restored = reader.restore(driver.state_target(batch, placed), config=group_config, keys=GROUP_KEYS)
            progress = driver.Progress(driver.on_mesh(restored.state, placed), restored.step, restored.history,
                                       float(restored.extra.get("wall_time_s", 0.0)), t0,
                                       restored.extra.get("first_chunk_s"), saved=restored.step)
            say(f"[shed_jax] {group.label}: resumed at budget step {progress.done}/{total}")
            if bar is not None:
                bar.update(math.ceil(progress.done / batch.chunk))
        for p, d in enumerate(dirs if writer else ()):  # records after the checkpoint (or all of them, without one) run again
            note = reconcile_metrics_jsonl(d / "metrics.jsonl", batch.rows(progress.history, p), progress.done, S)
            say(f"[shed_jax] {group.label} {group.points[p].name}: {note}")
    progress.state, compiled = driver.compile_batch(batch, placed, progress.done, progress.state, say=say)
    if stop.signalled():  # a signal while this (not the first) group compiled: nothing of it to save
        return None

    def safe() -> str:
        resume_with = f"after freeing space continue with: python -m shed_jax sweep --resume {out}"
        if progress.saved is not None:
            return (f"safe on disk: checkpoint {progress.saved} of {group.label} in {ckpt_dir / 'checkpoints'} (and its "
                    f"points' metrics.jsonl up to it), and the groups finished before; {resume_with}")
        if checkpoint:
            return f"no checkpoint of {group.label} was saved yet (the groups finished before are kept); {resume_with}"
        return "nothing resumable (--no-checkpoint)"

    output = driver.Output(dirs, [p.name for p in group.points], ckpt_dir if checkpoint else None, 1, group_config,
                           lambda pr: {"wall_time_s": pr.wall(), "first_chunk_s": pr.first_chunk_s},
                           label=group.label, writer=writer, every=checkpoint_every)
    stopped = driver.train(batch, compiled, progress, output, stop, _GroupReporter(say, bar, group.label, P, S), safe)
    if stopped is not None:
        if stopped[0] != EXIT_NONFINITE:
            where = f"checkpoint at budget step {progress.done}" if checkpoint else "no checkpoint (--no-checkpoint)"
            why = "at the time limit" if stopped[0] == EXIT_STOPPED else f"({stopped[1]})"
            say(f"[shed_jax] {group.label}: stopped {why}; {where}")
        return None
    wall = progress.wall()
    # the group's runs shared the wall time: per run, divide by all of them
    extras = [dict(wall_time_per_seed_s=wall / (P * S), runs_in_group=P * S, group=group.label,
                   first_chunk_s=progress.first_chunk_s, wall_time_per_chunk_s=progress.wall_per_chunk(),
                   devices=mesh.size, point=p.name, values=p.values) for p in group.points]
    signals, finishing = stop.signals, getattr(stop.signals, "finishing", None)
    if signals is not None:  # the group is trained: a first signal lets its results be written, then the sweep stops
        signals.finishing = f"writing the results of {group.label}, then stopping before the next group"
    try:
        with driver.Writes(safe) as w:
            summaries = driver.write_results(batch, progress, output, w, wall=wall, plots=plots, final_sets=final_sets,
                                             final_episodes=final_episodes, extras=extras)
    finally:
        if signals is not None:
            signals.finishing = finishing
    return [_row(out, group, point, summary, S) for point, summary in zip(group.points, summaries)]


def fixed_values(point) -> dict:
    """The dynamic values a point runs with that neither its group label (static keys) nor its name
    (grid values) shows: those of ``--set``, as the user spelt the keys."""
    dynamic = {**point.method_hparams, **{STUDENT_PREFIX + k: v for k, v in point.student_hparams.items()}}
    return {k: v for k, v in dynamic.items() if k not in point.values}


def _row(out: pathlib.Path, group, point, summary: dict, num_seeds: int) -> dict:
    """The sweep table's row of one point, from its summary."""
    return {"method": group.method, "group": group.label, "point": point.name, "values": point.values,
            "set": fixed_values(point),
            "final_test_return_mean": summary["final_test_return_mean"],
            "final_test_return_se": summary["final_test_return_se"], "seeds": num_seeds,
            "dir": str(point_dir(out, group, point).relative_to(out)),
            "group_wall_time_s": summary["wall_time_s"]}  # the group's, over every process that ran it


def _row_from_summary(out: pathlib.Path, group, point, num_seeds: int) -> dict:
    summary = json.loads((point_dir(out, group, point) / "summary.json").read_text())
    return _row(out, group, point, summary, num_seeds)


def table(rows: list[dict]) -> str:
    """A markdown table: method | point | final test return mean +- SE (n), and a column of the
    ``--set`` values the labels do not show when there are any."""
    fixed = any(r.get("set") for r in rows)
    lines = ["| method | point | final test return (mean ± SE) | seeds |" + (" also set |" if fixed else ""),
             "|---|---|---|---|" + ("---|" if fixed else "")]
    for r in rows:
        m, se = r["final_test_return_mean"], r["final_test_return_se"]
        extra = f" {point_name(r['set']) if r.get('set') else ''} |" if fixed else ""
        lines.append(f"| {r['group']} | {r['point']} | {m:.2f} ± {se:.2f} | {r['seeds']} |" + extra)
    return "\n".join(lines)


def prepare_sweep(groups: list[Group], *, out: pathlib.Path, make_experiment: Callable, build: Callable,
                  num_seeds: int, root_seed: int = 0, chunk: int | None = None, final_eval: str | None = "none",
                  final_eval_episodes: int = 10, resume: bool = False) -> tuple[list, list]:
    """Build every group and resolve its ``--final-eval`` level sets, checking every value (ValueError)
    before anything is compiled or written. Returns ``(built groups, their level sets)`` for ``run_sweep``."""
    import jax

    from shed_jax.evaluation import LevelFileError, final_eval_specs, resolve_levels

    if num_seeds < 1:
        raise ValueError("--seeds must be >= 1")
    if chunk is not None and chunk < 1:
        raise ValueError("--chunk must be >= 1")
    if final_eval_episodes < 1:
        raise ValueError("--final-eval-episodes must be >= 1")
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a directory; choose another --out")
    built = [build_group(g, make_experiment, build, num_seeds=num_seeds, root_seed=root_seed, chunk=chunk) for g in groups]
    finals = []  # per group: its resolved --final-eval level sets, so that a bad one fails before any compile
    for b in built:
        try:
            finals.append([resolve_levels(spec, b.batch.env, b.exp, b.batch.tests)
                           for spec in final_eval_specs(final_eval, b.batch.env.ued.final_eval)])
        except LevelFileError as err:
            raise ValueError(f"--final-eval: {err}") from err
    if any(finals) and jax.process_count() > 1:
        raise ValueError("--final-eval runs on one host only (the students of a multi-host batch are not all addressable here)")
    for b in built if not resume else ():
        for p in b.group.points:
            if (point_dir(out, b.group, p) / "metrics.jsonl").exists():
                raise ValueError(f"{point_dir(out, b.group, p)} already holds a run (metrics.jsonl); "
                                 f"continue it with --resume {out} or choose another --out")
    return built, finals


def run_sweep(groups: list[Group], *, out: pathlib.Path, make_experiment: Callable,
              build: Callable, num_seeds: int, root_seed: int = 0, chunk: int | None = None, mesh=None,
              pad: bool = True, plots: bool = True, progress: bool = True, final_eval: str | None = "none",
              final_eval_episodes: int = 10, checkpoint: bool = True, resume: bool = False,
              time_limit: float | None = None, prepared: tuple | None = None, stop: driver.StopRules | None = None,
              made: list | None = None, checkpoint_every: float = 0.0) -> list[dict] | None:
    """Build every group first (all values validated before any compile), run them, write the sweep table.

    ``final_eval``: level sets as for ``run --final-eval`` (None: the env's default there).
    ``checkpoint``/``resume``: see the module docstring; ``checkpoint_every``: seconds between a group's
    checkpoints (0: every chunk). ``time_limit`` (seconds): stop after the chunk
    that passes it; returns None when the sweep stopped before its end (``stop.stopped`` says why).
    ``prepared``: what ``prepare_sweep`` returned for the same arguments (else it is called here).
    """
    import jax
    from tqdm import tqdm

    from shed_jax import sharding

    mesh = mesh or sharding.batch_mesh()
    if prepared is None:
        prepared = prepare_sweep(groups, out=out, make_experiment=make_experiment, build=build, num_seeds=num_seeds,
                                 root_seed=root_seed, chunk=chunk, final_eval=final_eval,
                                 final_eval_episodes=final_eval_episodes, resume=resume)
    built, finals = prepared
    finished = [all((point_dir(out, b.group, p) / "summary.json").exists() for p in b.group.points) for b in built]
    bar = tqdm(total=sum(_num_chunks(b) for b in built), unit="chunk", desc="sweep", dynamic_ncols=True,
               disable=not progress)
    rows = []
    t0 = time.time()
    stop = stop or driver.StopRules()
    if time_limit is not None:
        stop.deadline, stop.time_limit = t0 + time_limit, time_limit
    try:
        for b, final_sets, done in zip(built, finals, finished):
            if resume and done:  # finished before: its rows come from the points' summaries
                rows += [_row_from_summary(out, b.group, p, num_seeds) for p in b.group.points]
                bar.update(_num_chunks(b))
                bar.write(f"[shed_jax] {b.group.label}: finished before, kept")
                continue
            B = len(b.group.points) * num_seeds
            bar.write(f"[shed_jax] {b.group.label}: {len(b.group.points)} point(s) x {num_seeds} seed(s) = {B} runs "
                      f"in one program over {mesh.size} device(s)"
                      + (f" (+{sharding.padded_size(B, mesh.size) - B} padding)" if B % mesh.size else ""))
            group_rows = run_group(b, out=out, mesh=mesh, pad=pad, plots=plots, bar=bar, final_sets=final_sets,
                                   final_episodes=final_eval_episodes, checkpoint=checkpoint, resume=resume, stop=stop,
                                   made=made, checkpoint_every=checkpoint_every)
            if group_rows is None:
                return None
            rows += group_rows
    finally:
        bar.close()
    group_walls = {r["group"]: r["group_wall_time_s"] for r in rows}
    from shed_jax.runtime import provenance

    result = {**provenance("shed_jax"), "rows": rows, "groups": [b.group.label for b in built], "seeds": num_seeds,
              "root_seed": root_seed, "devices": mesh.size,
              "wall_time_s": time.time() - t0,  # this process only (a resumed sweep's earlier ones are not in it)
              "groups_wall_time_s": sum(group_walls.values())}  # every group's run, earlier processes included
    if jax.process_index() == 0:
        (out / "sweep.json").write_text(json.dumps(result, indent=2))
        (out / "sweep.md").write_text(table(rows) + "\n")
    return rows


def preset_experiment(env: str, preset: str, episodes=None, steps_per_episode=None,
                      test_episode_every=None) -> Callable:
    """``make_experiment(method, method_overrides, ppo_overrides)`` from the named preset."""
    from shed_jax.presets import build_experiment

    def make(method: str, method_overrides: dict, ppo_overrides: dict):
        exp = build_experiment(env, method, preset, episodes=episodes, steps_per_episode=steps_per_episode,
                               test_episode_every=test_episode_every, method_overrides=method_overrides)
        if ppo_overrides:
            exp = dataclasses.replace(exp, ppo=exp.ppo.replace(**ppo_overrides))
        return exp

    return make


# ---------------------------------------------------------------------------------------------
# python -m shed_jax sweep
# ---------------------------------------------------------------------------------------------

#: the arguments saved in OUT/sweep_args.json and read back by --resume
SAVED_ARGS = ("env", "methods", "preset", "seeds", "seed", "grid", "set", "episodes", "steps_per_episode",
              "test_episode_every", "chunk", "devices", "no_pad", "no_plots", "final_eval", "final_eval_episodes",
              "no_checkpoint")
ARGS_FILE = "sweep_args.json"


@dataclasses.dataclass
class SweepOptions:
    """The sweep command's options (its flags)."""

    env: str = "lander"
    methods: str = "shed"
    preset: str = "auto"
    seeds: int | None = None
    seed: int = 0
    grid: list = dataclasses.field(default_factory=list)
    set: list = dataclasses.field(default_factory=list)
    episodes: int | None = None
    steps_per_episode: int | None = None
    test_episode_every: int | None = None
    chunk: int | None = None
    devices: int | None = None
    no_pad: bool = False
    no_plots: bool = False
    final_eval: str | None = None
    final_eval_episodes: int = 10
    out: str | None = None
    resume: str | None = None
    time_limit: float | None = None
    no_checkpoint: bool = False
    checkpoint_every: float = 0.0

    @classmethod
    def from_args(cls, args) -> "SweepOptions":
        return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)})


def resumed_args(args):
    """``args`` with the saved arguments of the sweep in ``args.resume`` (its ``--time-limit`` and
    ``--checkpoint-every`` kept)."""
    out = pathlib.Path(args.resume)
    path = out / ARGS_FILE
    if not path.is_file():
        raise UsageError(f"--resume {out}: no {ARGS_FILE} there (not a sweep directory, or one from before sweeps "
                         "could be resumed)")
    saved = json.loads(path.read_text())
    if saved.get("no_checkpoint"):
        raise UsageError(f"--resume {out}: that sweep ran with --no-checkpoint")
    if args.out is not None and pathlib.Path(args.out) != out:
        raise UsageError(f"--resume continues the sweep in its own directory {out}; drop --out {args.out}")
    merged = dict(vars(args))
    merged.update({k: saved[k] for k in SAVED_ARGS if k in saved})
    merged["out"] = str(out)
    return type(args)(**merged)


def sweep(opts: SweepOptions) -> int:
    """``python -m shed_jax sweep``. Every value is checked (UsageError, one line, exit 2) before OUT is written.

    Returns the exit status: 0, EXIT_NONFINITE, EXIT_STOPPED or 128 + signal; a failed write raises
    WriteFailedError. A signal during start-up (before the first chunk) stops at once and removes
    what this process made.
    """
    import jax

    from shed_jax import sharding
    from shed_jax.checkpoint import CheckpointError
    from shed_jax.experiment import build, preset_default_seeds
    from shed_jax.methods.registry import METHODS

    resume = opts.resume is not None
    if resume:
        opts = resumed_args(opts)
    driver.check_checkpoint_every(opts.checkpoint_every, opts.no_checkpoint)
    backend = jax.default_backend()
    preset = opts.preset
    if preset == "auto":
        preset = "paper" if backend == "gpu" else "quick"
        print(f"[shed_jax] backend={backend}: using the '{preset}' preset")
    methods = [m.strip() for m in opts.methods.split(",") if m.strip()]
    if not methods:
        raise UsageError(f"--methods needs at least one method of {', '.join(METHODS)}")
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise UsageError(f"--methods: unknown method(s) {', '.join(map(repr, unknown))}; known: {', '.join(METHODS)}")
    if len(set(methods)) != len(methods):
        raise UsageError(f"--methods lists a method twice: {opts.methods}")
    num_seeds = opts.seeds or preset_default_seeds(preset)
    devices = jax.devices()
    if opts.devices is not None:
        if not 1 <= opts.devices <= len(devices):
            raise UsageError(f"--devices must lie in [1, {len(devices)}] (visible devices), got {opts.devices}")
        devices = devices[: opts.devices]
    make_experiment = preset_experiment(opts.env, preset, opts.episodes, opts.steps_per_episode, opts.test_episode_every)
    out = pathlib.Path(opts.out or f"runs/sweep-{opts.env}-{preset}-{time.strftime('%Y%m%d-%H%M%S')}")
    if not resume and (out / ARGS_FILE).exists():
        raise UsageError(f"{out} already holds a sweep; continue it with --resume {out} or choose another --out")
    resume_command = f"python -m shed_jax sweep --resume {out}"
    made: list = []  # what this process created before the first chunk (removed if start-up is interrupted)
    with driver.StopRequest() as signals:
        stop = driver.StopRules(signals)
        try:
            try:
                groups = plan_groups(methods, parse_grid(opts.grid), parse_fixed(opts.set), make_experiment, build)
                prepared = prepare_sweep(groups, out=out, make_experiment=make_experiment, build=build,
                                         num_seeds=num_seeds, root_seed=opts.seed, chunk=opts.chunk,
                                         final_eval=opts.final_eval, final_eval_episodes=opts.final_eval_episodes,
                                         resume=resume)
            except (ValueError, TypeError) as err:
                raise UsageError(f"sweep: {err}") from err
            try:
                if not out.exists():
                    out.mkdir(parents=True)
                    made.append(out)
            except OSError as err:
                raise UsageError(f"--out {out}: cannot create it ({err.strerror or err})") from err
            if not resume and jax.process_index() == 0:
                saved = {k: getattr(opts, k) for k in SAVED_ARGS}
                saved["preset"] = preset  # 'auto' resolved: a resumed sweep keeps the preset it started with
                (out / ARGS_FILE).write_text(json.dumps(saved, indent=2))
                made.append(out / ARGS_FILE)
            mesh = sharding.batch_mesh(devices)
            runs = sum(len(g.points) for g in groups) * num_seeds
            print(f"[shed_jax] sweep on {opts.env} ({preset}): {len(groups)} compiled group(s), {runs} runs, "
                  f"{mesh.size} device(s) -> {out}")
            try:
                rows = run_sweep(groups, out=out, make_experiment=make_experiment, build=build, num_seeds=num_seeds,
                                 root_seed=opts.seed, chunk=opts.chunk, mesh=mesh, pad=not opts.no_pad,
                                 plots=not opts.no_plots, final_eval=opts.final_eval,
                                 final_eval_episodes=opts.final_eval_episodes, checkpoint=not opts.no_checkpoint,
                                 resume=resume, time_limit=opts.time_limit, prepared=prepared, stop=stop, made=made,
                                 checkpoint_every=opts.checkpoint_every)
            except (ValueError, CheckpointError) as err:
                raise UsageError(f"sweep: {err}") from err
        except driver.StartupInterrupted as sig:
            return driver.startup_interrupted(sig.signum, resume_command if resume else None, made)
    if rows is None:
        code, reason = stop.stopped
        if code == EXIT_STOPPED:
            print(f"[shed_jax] stopped at --time-limit {opts.time_limit:g}s; continue with:\n  {resume_command}")
        elif code != EXIT_NONFINITE:
            print(f"[shed_jax] {reason}; " + (f"continue with:\n  {resume_command}" if not opts.no_checkpoint
                                              else "it ran with --no-checkpoint and cannot be resumed"))
        return code
    print(table(rows))
    print(f"[shed_jax] results in {out} (sweep.json, sweep.md, <method>/<point>/)")
    return 0
