"""``python -m shed_jax sweep``: seeds x hyperparameter grid x methods, one compile per shape group.

    python -m shed_jax sweep --env lander --methods shed,hmdp --preset quick --seeds 2 \\
        --grid eta=0,10 --grid actor_lr=1e-3,3e-4 --out runs/sweep-eta-lr

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
keys ``python -m shed_jax run`` uses, so a point with the preset's values starts from that run's
keys (on a GPU a program of another batch width may round differently; docs/sweeps.md). The
batch of a group is laid out point-major (row = point * seeds + seed) and split over all visible
devices (``shed_jax.sharding``; padded when it does not divide, or ``--no-pad`` to refuse).

Output, per point ``OUT/<method>/<point>/``: ``config.json``, ``metrics.jsonl`` and
``summary.json`` in the format of ``cli/run.py`` (its ``summarize``/``make_plots`` and
``shed_jax.reporting``), plus the point's values; and for the sweep ``OUT/sweep.json`` and
``OUT/sweep.md``: the table point -> final test return mean +- SE over seeds.

Checkpoints: after every chunk the group in progress saves its whole batched state and metrics
history (``shed_jax.checkpoint.RunCheckpointer``, the last one kept) under
``OUT/checkpoints/<group>/``, and ``OUT/sweep_args.json`` holds the command's arguments.
``--resume OUT`` re-plans from those arguments, keeps the groups whose points all have a
``summary.json``, restores the group in progress (its configuration must match), cuts its points'
``metrics.jsonl`` back to the checkpoint's step and continues; a group with no checkpoint starts
over. The continued metrics equal those of an uninterrupted sweep (tests/test_sweep.py).
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import math
import pathlib
import re
import time
from typing import Any, Callable

import numpy as np

from shed_jax.cli.errors import UsageError

KINDS = ("method_hparam", "student_hparam", "method_config", "student_config")
STUDENT_PREFIX = "ppo."


def add_arguments(p) -> None:
    from shed_jax.cli.errors import non_negative_float, positive_int
    from shed_jax.cli.run import ENVS
    from shed_jax.presets import PRESETS

    count = positive_int
    p.add_argument("--env", default="lander", choices=ENVS, help=" | ".join(ENVS))
    p.add_argument("--methods", default="shed", help="comma-separated: shed,hmdp,dr,paired,accel,accel-norevisit,plr")
    p.add_argument("--preset", default="auto", choices=("auto",) + PRESETS,
                   help="auto: 'paper' on a GPU, 'quick' on a CPU (the choice is printed)")
    p.add_argument("--seeds", type=count, default=None, help="seeds per grid point (default: quick 2, paper 5)")
    p.add_argument("--seed", type=int, default=0, help="root seed; seed i uses fold_in(root, i) at every point")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="a grid axis (repeatable); values are JSON or strings, e.g. --grid eta=0,10 --grid ppo.lr=1e-4,3e-4")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="fix a key for every point (repeatable), e.g. --set num_eval_levels=20")
    p.add_argument("--episodes", type=count, default=None, help="override the number of teacher episodes N_ep")
    p.add_argument("--steps-per-episode", type=count, default=None, help="override the budget steps per episode T")
    p.add_argument("--test-episode-every", type=count, default=None, metavar="K",
                   help="as for run: the test set runs only in teacher episodes 0, K, 2K, ... and the last "
                        "(default: paper preset 10 for shed/hmdp, else 1 = every episode)")
    p.add_argument("--chunk", type=count, default=None, help="budget steps per compiled call (default: T)")
    p.add_argument("--devices", type=count, default=None, help="use the first N visible devices (default: all)")
    p.add_argument("--no-pad", action="store_true",
                   help="refuse (error) when a group's seeds x points does not divide by the device count, instead of padding")
    p.add_argument("--no-plots", action="store_true", help="skip the per-point plots")
    p.add_argument("--final-eval", default=None, metavar="LEVELS",
                   help="as for run: after the last budget step, evaluate every point's final students on level sets "
                        "(test | named | FILE.json, comma-separated, or none) into <point>/final_eval_<set>.json; "
                        "default: walker named, other envs none")
    p.add_argument("--final-eval-episodes", type=count, default=10, metavar="N",
                   help="episodes per level and seed of --final-eval (default 10)")
    p.add_argument("--out", default=None, help="sweep directory (default runs/sweep-<env>-<preset>-<time>)")
    p.add_argument("--resume", default=None, metavar="DIR",
                   help="continue the sweep in DIR with its saved arguments: finished groups are kept, the "
                        "group in progress continues from its last checkpoint (other arguments are ignored)")
    p.add_argument("--time-limit", type=non_negative_float, default=None, metavar="SECONDS",
                   help="after the chunk in which this many seconds have passed, save and stop (exit code 75); "
                        "continue with --resume")
    p.add_argument("--no-checkpoint", action="store_true",
                   help="do not checkpoint the group in progress after each chunk (the sweep cannot be resumed)")


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
    """``--set KEY=VALUE`` items (cli/run.py's parser)."""
    from shed_jax.cli.run import _parse_overrides

    return _parse_overrides(items)


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


# ---------------------------------------------------------------------------------------------
# building and running groups
# ---------------------------------------------------------------------------------------------

@dataclasses.dataclass
class BuiltGroup:
    group: Group
    exp: Any  # presets.Experiment of the group (static values applied)
    env: Any
    student: Any
    method: Any
    tests: Any  # test levels
    method_hparams: Any  # stacked SHEDHyperparams [P] or None
    student_hparams: Any  # stacked PPOHyperparams [P]


def build_group(group: Group, make_experiment: Callable, build: Callable) -> BuiltGroup:
    """The group's Experiment and parts; every static and dynamic value is validated here (before compiling)."""
    from shed_jax.student.config import PPOHyperparams

    exp = make_experiment(group.method, dict(group.method_config), dict(group.student_config))
    env, student, method, tests = build(exp)
    shp = PPOHyperparams.stack([exp.ppo.hparams.replace(**_floats(p.student_hparams, group.method, STUDENT_PREFIX))
                                for p in group.points])
    mhp = None
    if hasattr(method, "default_hparams"):
        base = method.default_hparams
        mhp = type(base).stack([base.replace(**_floats(p.method_hparams, group.method)) for p in group.points])
    elif any(p.method_hparams for p in group.points):
        raise ValueError(f"method {group.method!r} has no dynamic hyperparameters")
    return BuiltGroup(group, exp, env, student, method, tests, mhp, shp)


def _floats(values: dict, method: str, prefix: str = "") -> dict:
    out = {}
    for k, v in values.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"method {method!r}: hyperparameter {prefix}{k} needs a number, got {v!r}")
        out[k] = float(v)
    return out


def group_init(init: Callable, method) -> Callable:
    """``(key, student_hparams, method_hparams) -> RunState``: the loop's init, then the method's hparams."""

    def init_point(key, student_hp, method_hp):
        state = init(key, student_hp)
        if method_hp is not None:
            state = state.replace(method=method.with_hparams(state.method, method_hp))
        return state

    return init_point


def batch_inputs(built: BuiltGroup, num_seeds: int, root_seed: int):
    """Host arrays (keys [B, 2], student hparams [B], method hparams [B] or None), row = point * S + seed."""
    import jax

    from shed_jax.cli.run import seed_keys

    P = len(built.group.points)
    keys = np.tile(np.asarray(seed_keys(root_seed, num_seeds)), (P, 1))  # the run CLI's keys, at every point
    rep = lambda tree: None if tree is None else jax.tree_util.tree_map(lambda x: np.repeat(np.asarray(x), num_seeds, axis=0), tree)
    return keys, rep(built.student_hparams), rep(built.method_hparams)


def _point_rows(flat: dict, p: int, num_seeds: int) -> dict:
    return {k: v[p * num_seeds:(p + 1) * num_seeds] for k, v in flat.items()}


#: configuration keys a resumed group must share with its checkpoint
GROUP_KEYS = ("group", "points", "experiment", "seeds", "root_seed", "chunk", "batch")


def group_checkpoint_dir(out: pathlib.Path, group) -> pathlib.Path:
    return out / "checkpoints" / dir_name(group.label)


def point_dir(out: pathlib.Path, group, point) -> pathlib.Path:
    """``OUT/<method>/<point>/``: where one point's run files go."""
    return out / group.method / dir_name(point.name)


def _num_chunks(built: BuiltGroup, chunk: int | None) -> int:
    return math.ceil(built.exp.loop.total_steps / (chunk or built.exp.loop.steps_per_episode))


def run_group(built: BuiltGroup, *, out: pathlib.Path, num_seeds: int, root_seed: int, chunk: int | None, mesh,
              pad: bool = True, plots: bool = True, bar=None, log: Callable = print, final_sets=(),
              final_episodes: int = 10, checkpoint: bool = True, resume: bool = False,
              deadline: float | None = None) -> list[dict] | None:
    """Run one group (all its points x seeds in one vmapped, sharded program); write each point's files.

    ``final_sets``: level sets resolved by ``cli.eval.resolve_levels``; each point's final students
    are evaluated on them as ``run --final-eval`` does (seed i with ``fold_in(PRNGKey(0), i)``).
    ``checkpoint``: save the state and history after every chunk (``group_checkpoint_dir``);
    ``resume``: continue from the latest such checkpoint if there is one. ``deadline`` (a
    ``time.time()`` value): stop after the chunk that passes it and return None (not finished).
    """
    import jax

    from shed_jax import reporting, sharding
    from shed_jax.checkpoint import RunCheckpointer
    from shed_jax.cli.run import final_eval, make_plots, reconcile_metrics_jsonl, summarize
    from shed_jax.loop import make_run

    exp, group = built.exp, built.group
    P = len(group.points)
    init, run = make_run(built.student, built.method, built.tests, exp.loop)
    total = exp.loop.total_steps
    chunk = chunk or exp.loop.steps_per_episode
    dirs = [point_dir(out, group, p) for p in group.points]
    writer = jax.process_index() == 0  # several hosts: every process computes, process 0 writes
    for d, p in zip(dirs, group.points):
        if not writer:
            break
        d.mkdir(parents=True, exist_ok=True)
        config = {"experiment": exp.to_dict(), "seeds": num_seeds, "root_seed": root_seed, "backend": jax.default_backend(),
                  "devices": [str(x) for x in mesh.devices.flat], "chunk": chunk, "jax": jax.__version__,
                  "sweep_point": {"name": p.name, "values": p.values, "group": group.label,
                                  "method_hparams": p.method_hparams, "student_hparams": p.student_hparams}}
        (d / "config.json").write_text(json.dumps(config, indent=2, default=str))

    inputs = batch_inputs(built, num_seeds, root_seed)
    inputs, n = sharding.pad_batch(inputs, mesh.size, pad=pad)
    t0 = time.time()
    state = sharding.sharded_init(group_init(init, built.method), mesh)(*sharding.put_batch(inputs, mesh))
    run_chunk = sharding.sharded_run(run, mesh)
    history: dict[str, list[np.ndarray]] = {}
    done = 0
    first_chunk_s = None
    previous_wall = 0.0
    group_config = {"group": group.label, "points": [p.name for p in group.points], "experiment": exp.to_dict(),
                    "seeds": num_seeds, "root_seed": root_seed, "chunk": chunk, "batch": sharding.batch_size(inputs)}
    ckpt = None
    if checkpoint or resume:
        if jax.process_count() > 1:
            raise ValueError("sweep checkpoints are written by one host only; pass --no-checkpoint on several hosts")
        ckpt = RunCheckpointer(group_checkpoint_dir(out, group), keep=1, create=True)
    try:
        if resume and ckpt.latest_step() is not None:
            restored = ckpt.restore(state, config=group_config, keys=GROUP_KEYS)
            state = jax.device_put(restored.state, sharding.batch_sharding(mesh))
            done = restored.step
            history = {k: [v] for k, v in restored.history.items()}
            previous_wall = float(restored.extra.get("wall_time_s", 0.0))
            first_chunk_s = restored.extra.get("first_chunk_s")
            (bar.write if bar is not None else log)(f"[shed_jax] {group.label}: resumed at budget step {done}/{total}")
            if bar is not None:
                bar.update(math.ceil(done / chunk))
        if resume:  # records after the checkpoint (or all of them, without one) are run again
            saved = {k: np.concatenate(v, axis=1) for k, v in history.items()}
            for p, d in enumerate(dirs if writer else ()):
                note = reconcile_metrics_jsonl(d / "metrics.jsonl", _point_rows(saved, p, num_seeds), done, num_seeds)
                (bar.write if bar is not None else log)(f"[shed_jax] {group.label} {group.points[p].name}: {note}")
        while done < total:
            steps = min(chunk, total - done)
            state, metrics = run_chunk(state, steps, done)
            flat = reporting.flatten_tree(sharding.unpad(sharding.to_host(metrics), n))
            if first_chunk_s is None:
                first_chunk_s = time.time() - t0
            for k, v in flat.items():
                history.setdefault(k, []).append(v)
            for p, d in enumerate(dirs if writer else ()):
                reporting.append_jsonl(d / "metrics.jsonl", reporting.step_records(_point_rows(flat, p, num_seeds), range(num_seeds)))
            done += steps
            if bar is not None:
                bar.update(1)
            tr = flat["test_return"][:, -1].reshape(P, num_seeds)
            means = np.nanmean(tr, axis=1) if np.any(np.isfinite(tr)) else np.full(P, math.nan)
            msg = (f"{group.label}: step {done}/{total}  test return per point "
                   + " ".join(f"{m:.1f}" for m in means))
            (bar.write if bar is not None else log)(msg)
            if checkpoint:
                ckpt.save(done, state, {k: np.concatenate(v, axis=1) for k, v in history.items()}, group_config,
                          extra={"wall_time_s": previous_wall + time.time() - t0, "first_chunk_s": first_chunk_s})
            if deadline is not None and done < total and time.time() >= deadline:
                where = f"checkpoint at budget step {done}" if checkpoint else "no checkpoint (--no-checkpoint)"
                (bar.write if bar is not None else log)(f"[shed_jax] {group.label}: stopped at the time limit; {where}")
                return None
    finally:
        if ckpt is not None:
            ckpt.close()
    wall = previous_wall + time.time() - t0
    hist = {k: np.concatenate(v, axis=1) for k, v in history.items()}
    rows = []
    for p, (point, d) in enumerate(zip(group.points, dirs)):
        h = _point_rows(hist, p, num_seeds)
        summary = summarize(exp, h, wall, num_seeds)
        # the group's runs shared the wall time: per run, divide by all of them
        summary.update(wall_time_per_seed_s=wall / (P * num_seeds), runs_in_group=P * num_seeds, group=group.label,
                       first_chunk_s=first_chunk_s, point=point.name, values=point.values)
        if writer:
            (d / "summary.json").write_text(json.dumps(summary, indent=2))
            if plots:
                make_plots(exp, built.env, h, d)
            if final_sets:
                # the point's rows of the batch (point-major, padding at the end)
                students = jax.tree_util.tree_map(lambda x: x[p * num_seeds:(p + 1) * num_seeds], state.student)
                for resolved in final_sets:
                    final_eval(exp, built.env, built.student, students, num_seeds, resolved, d, done, final_episodes)
        rows.append(_row(out, group, point, summary, num_seeds))
    return rows


def _row(out: pathlib.Path, group, point, summary: dict, num_seeds: int) -> dict:
    """The sweep table's row of one point, from its summary."""
    return {"method": group.method, "group": group.label, "point": point.name, "values": point.values,
            "final_test_return_mean": summary["final_test_return_mean"],
            "final_test_return_se": summary["final_test_return_se"], "seeds": num_seeds,
            "dir": str(point_dir(out, group, point).relative_to(out)),
            "group_wall_time_s": summary["wall_time_s"]}  # the group's, over every process that ran it


def _row_from_summary(out: pathlib.Path, group, point, num_seeds: int) -> dict:
    summary = json.loads((point_dir(out, group, point) / "summary.json").read_text())
    return _row(out, group, point, summary, num_seeds)


def table(rows: list[dict]) -> str:
    """A markdown table: method | point | final test return mean +- SE (n)."""
    lines = ["| method | point | final test return (mean ± SE) | seeds |", "|---|---|---|---|"]
    for r in rows:
        m, se = r["final_test_return_mean"], r["final_test_return_se"]
        lines.append(f"| {r['group']} | {r['point']} | {m:.2f} ± {se:.2f} | {r['seeds']} |")
    return "\n".join(lines)


def prepare_sweep(groups: list[Group], *, out: pathlib.Path, make_experiment: Callable, build: Callable,
                  num_seeds: int, chunk: int | None = None, final_eval: str | None = "none",
                  final_eval_episodes: int = 10, resume: bool = False) -> tuple[list, list]:
    """Build every group and resolve its ``--final-eval`` level sets, checking every value (ValueError)
    before anything is compiled or written. Returns ``(built groups, their level sets)`` for ``run_sweep``."""
    import jax

    from shed_jax.cli import eval as eval_cli
    from shed_jax.cli.run import final_eval_specs

    if num_seeds < 1:
        raise ValueError("--seeds must be >= 1")
    if chunk is not None and chunk < 1:
        raise ValueError("--chunk must be >= 1")
    if final_eval_episodes < 1:
        raise ValueError("--final-eval-episodes must be >= 1")
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a directory; choose another --out")
    built = [build_group(g, make_experiment, build) for g in groups]
    finals = []  # per group: its resolved --final-eval level sets, so that a bad one fails before any compile
    for b in built:
        try:
            finals.append([eval_cli.resolve_levels(spec, b.env, b.exp, b.tests) for spec in final_eval_specs(final_eval, b.exp.env)])
        except eval_cli.LevelFileError as err:
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
              time_limit: float | None = None, prepared: tuple | None = None) -> list[dict] | None:
    """Build every group first (all values validated before any compile), run them, write the sweep table.

    ``final_eval``: level sets as for ``run --final-eval`` (None: the env's default there).
    ``checkpoint``/``resume``: see the module docstring. ``time_limit`` (seconds): stop after the chunk
    that passes it; returns None when the sweep stopped before its end. ``prepared``: what
    ``prepare_sweep`` returned for the same arguments (else it is called here).
    """
    import jax
    from tqdm import tqdm

    from shed_jax import sharding

    mesh = mesh or sharding.batch_mesh()
    if prepared is None:
        prepared = prepare_sweep(groups, out=out, make_experiment=make_experiment, build=build, num_seeds=num_seeds,
                                 chunk=chunk, final_eval=final_eval, final_eval_episodes=final_eval_episodes, resume=resume)
    built, finals = prepared
    finished = [all((point_dir(out, b.group, p) / "summary.json").exists() for p in b.group.points) for b in built]
    n_chunks = sum(_num_chunks(b, chunk) for b in built)
    bar = tqdm(total=n_chunks, unit="chunk", desc="sweep", dynamic_ncols=True, disable=not progress)
    rows = []
    t0 = time.time()
    deadline = None if time_limit is None else t0 + time_limit
    try:
        for b, final_sets, done in zip(built, finals, finished):
            if resume and done:  # finished before: its rows come from the points' summaries
                rows += [_row_from_summary(out, b.group, p, num_seeds) for p in b.group.points]
                bar.update(_num_chunks(b, chunk))
                bar.write(f"[shed_jax] {b.group.label}: finished before, kept")
                continue
            B = len(b.group.points) * num_seeds
            bar.write(f"[shed_jax] {b.group.label}: {len(b.group.points)} point(s) x {num_seeds} seed(s) = {B} runs "
                      f"in one program over {mesh.size} device(s)"
                      + (f" (+{sharding.padded_size(B, mesh.size) - B} padding)" if B % mesh.size else ""))
            group_rows = run_group(b, out=out, num_seeds=num_seeds, root_seed=root_seed, chunk=chunk, mesh=mesh, pad=pad,
                                   plots=plots, bar=bar, final_sets=final_sets, final_episodes=final_eval_episodes,
                                   checkpoint=checkpoint, resume=resume, deadline=deadline)
            if group_rows is None:
                return None
            rows += group_rows
    finally:
        bar.close()
    group_walls = {r["group"]: r["group_wall_time_s"] for r in rows}
    result = {"rows": rows, "groups": [b.group.label for b in built], "seeds": num_seeds, "root_seed": root_seed,
              "devices": mesh.size,
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


#: the arguments saved in OUT/sweep_args.json and read back by --resume
SAVED_ARGS = ("env", "methods", "preset", "seeds", "seed", "grid", "set", "episodes", "steps_per_episode",
              "test_episode_every", "chunk", "devices", "no_pad", "no_plots", "final_eval", "final_eval_episodes",
              "no_checkpoint")
ARGS_FILE = "sweep_args.json"


def resumed_args(args):
    """``args`` with the saved arguments of the sweep in ``args.resume`` (its ``--time-limit`` kept)."""
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


def main(args) -> int:
    """The sweep command. Every value is checked (UsageError, one line, exit 2) before OUT is written."""
    import jax

    from shed_jax import sharding
    from shed_jax.checkpoint import CheckpointError
    from shed_jax.cli.run import EXIT_STOPPED, build
    from shed_jax.methods.registry import METHODS

    resume = getattr(args, "resume", None) is not None
    if resume:
        args = resumed_args(args)

    backend = jax.default_backend()
    preset = args.preset
    if preset == "auto":
        preset = "paper" if backend == "gpu" else "quick"
        print(f"[shed_jax] backend={backend}: using the '{preset}' preset")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not methods:
        raise UsageError(f"--methods needs at least one method of {', '.join(METHODS)}")
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise UsageError(f"--methods: unknown method(s) {', '.join(map(repr, unknown))}; known: {', '.join(METHODS)}")
    if len(set(methods)) != len(methods):
        raise UsageError(f"--methods lists a method twice: {args.methods}")
    num_seeds = args.seeds or (5 if preset == "paper" else 2)
    devices = jax.devices()
    if args.devices is not None:
        if not 1 <= args.devices <= len(devices):
            raise UsageError(f"--devices must lie in [1, {len(devices)}] (visible devices), got {args.devices}")
        devices = devices[: args.devices]
    make_experiment = preset_experiment(args.env, preset, args.episodes, args.steps_per_episode,
                                        args.test_episode_every)
    out = pathlib.Path(args.out or f"runs/sweep-{args.env}-{preset}-{time.strftime('%Y%m%d-%H%M%S')}")
    if not resume and (out / ARGS_FILE).exists():
        raise UsageError(f"{out} already holds a sweep; continue it with --resume {out} or choose another --out")
    try:
        grid, fixed = parse_grid(args.grid), parse_fixed(args.set)
        groups = []
        for name in methods:
            exp = make_experiment(name, {}, {})
            _, student, method, _ = build(exp)
            gs, notes = plan(key_space(name, method, exp.ppo), grid, fixed)
            for note in notes:
                print(f"[shed_jax] note: {note}")
            groups += gs
        prepared = prepare_sweep(groups, out=out, make_experiment=make_experiment, build=build, num_seeds=num_seeds,
                                 chunk=args.chunk, final_eval=args.final_eval,
                                 final_eval_episodes=args.final_eval_episodes, resume=resume)
    except (ValueError, TypeError) as err:
        raise UsageError(f"sweep: {err}") from err
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"--out {out}: cannot create it ({err.strerror or err})") from err
    if not resume and jax.process_index() == 0:
        saved = {k: getattr(args, k) for k in SAVED_ARGS}
        saved["preset"] = preset  # 'auto' resolved: a resumed sweep keeps the preset it started with
        (out / ARGS_FILE).write_text(json.dumps(saved, indent=2))
    mesh = sharding.batch_mesh(devices)
    runs = sum(len(g.points) for g in groups) * num_seeds
    print(f"[shed_jax] sweep on {args.env} ({preset}): {len(groups)} compiled group(s), {runs} runs, "
          f"{mesh.size} device(s) -> {out}")
    try:
        rows = run_sweep(groups, out=out, make_experiment=make_experiment, build=build, num_seeds=num_seeds,
                         root_seed=args.seed, chunk=args.chunk, mesh=mesh, pad=not args.no_pad, plots=not args.no_plots,
                         final_eval=args.final_eval, final_eval_episodes=args.final_eval_episodes,
                         checkpoint=not args.no_checkpoint, resume=resume, time_limit=args.time_limit,
                         prepared=prepared)
    except (ValueError, CheckpointError) as err:
        raise UsageError(f"sweep: {err}") from err
    if rows is None:
        print(f"[shed_jax] stopped at --time-limit {args.time_limit:g}s; continue with:\n"
              f"  python -m shed_jax sweep --resume {out}")
        return EXIT_STOPPED
    print(table(rows))
    print(f"[shed_jax] results in {out} (sweep.json, sweep.md, <method>/<point>/)")
    return 0
