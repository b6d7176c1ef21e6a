"""``python -m shed_jax eval``: evaluate the students of a saved run on a level set.

    python -m shed_jax eval --run runs/lander-shed-paper-20250101-120000 --levels test --episodes 100

Loads the run's latest checkpoint (or ``--step``), rebuilds its experiment from the configuration
saved with it, evaluates every seed's student (seeds vmapped, one compile) for ``--episodes``
episodes per level and prints one row per level: the mean return (mean over seeds of each seed's
mean), its standard error over seeds, the solved rate (fraction of all episodes with return
> ``--solved-threshold``, by default the env's ``ued.solved_threshold``: lander 200, walker 230)
and the CVaR at 10 % (mean of the worst ceil(0.1 n) of the n = seeds x episodes returns). Writes
``DIR/eval_<levels>.json``.

Level sets (``--levels``):

* ``test``: the run's own test set (lander: the 10 official test landers; walker: its test set);
* ``named``: the environment's named levels (``env.ued.named_levels``). Walker: every level of
  ``envs.walker.levels.LEVELS`` (fixed terrains, seeds 1000 + i); lander: the official 10 evaluation
  landers then the 10 test landers (``shed_jax.eval_sets``); cartpole: its ``LEVELS``;
* ``FILE.json``: a list of levels, each a parameter vector in ``env.param_space`` order or an object
  of params fields by name (missing fields take the env's defaults; an optional ``"label"``), or
  ``{"levels": [...]}``. Values are checked against the env's physical bounds, not clipped.
"""
from __future__ import annotations

import json
import math
import pathlib
import re

import numpy as np

CVAR_ALPHA = 0.1
EXIT_BAD_INPUT = 2


class LevelFileError(ValueError):
    """A --levels FILE that cannot be turned into levels (the message names the entry and field)."""


def add_arguments(p) -> None:
    p.add_argument("--run", required=True, metavar="DIR", help="run directory (with checkpoints/)")
    p.add_argument("--levels", default="test", metavar="test|named|FILE",
                   help="level set: the run's test set, the env's named levels, or a JSON file (default test)")
    p.add_argument("--episodes", type=int, default=10, help="episodes per level and seed (default 10)")
    p.add_argument("--max-steps", type=int, default=None, help="episode cap (default: each level's own time limit)")
    p.add_argument("--deterministic", action="store_true", help="greedy actions (default: sample the policy)")
    p.add_argument("--seed", type=int, default=0, help="evaluation key; seed i of the run uses fold_in(seed, i)")
    p.add_argument("--solved-threshold", type=float, default=None,
                   help="return above which an episode counts as solved (default: the env's; lander 200, walker 230)")
    p.add_argument("--step", type=int, default=None, help="checkpoint step to load (default: the latest)")
    p.add_argument("--out", default=None, help="output JSON (default DIR/eval_<levels>.json)")


# --------------------------------------------------------------------------------------------
# the table (pure numpy)
# --------------------------------------------------------------------------------------------


def cvar(x, alpha: float = CVAR_ALPHA) -> float:
    """Conditional value at risk: the mean of the worst ``ceil(alpha * n)`` values (at least one)."""
    x = np.sort(np.asarray(x, np.float64).ravel())
    if x.size == 0:
        return math.nan
    if not 0.0 < alpha <= 1.0:
        raise ValueError(f"cvar: alpha must lie in (0, 1], got {alpha}")
    k = max(1, math.ceil(alpha * x.size - 1e-9))
    return float(x[:k].mean())


def table_json(labels: list[str], table: dict) -> dict:
    """``per_level`` (one record per label) and ``overall`` of a ``level_table``, as the JSON of
    ``eval`` and ``run --final-eval`` holds them (NaN as null)."""
    return {
        "per_level": [
            {"label": lab, "mean": _json_num(table["mean"][j]), "se": _json_num(table["se"][j]),
             "solved_rate": _json_num(table["solved_rate"][j]), "cvar": _json_num(table["cvar"][j])}
            for j, lab in enumerate(labels)
        ],
        "overall": {k: _json_num(v) for k, v in table["overall"].items()},
    }


def level_table(returns, threshold: float | None, alpha: float = CVAR_ALPHA) -> dict:
    """Per-level and overall statistics of ``returns [seeds, levels, episodes]``.

    mean: mean over seeds of each seed's mean return; se: standard error of those seed means
    (0 with one seed); solved_rate: fraction of all the level's episodes with return > threshold
    (NaN without a threshold); cvar: ``cvar`` of the level's seeds x episodes returns. ``overall``
    pools the levels the same way (a seed's overall mean is its mean over levels and episodes).
    """
    from shed_jax import reporting

    r = np.asarray(returns, np.float64)
    if r.ndim != 3 or 0 in r.shape:
        raise ValueError(f"level_table: returns must be [seeds, levels, episodes], got shape {r.shape}")
    mean, se = reporting.mean_se(r.mean(axis=2), axis=0)
    all_mean, all_se = reporting.mean_se(r.mean(axis=(1, 2)), axis=0)
    if threshold is None:
        solved = np.full(r.shape[1], np.nan)
        all_solved = math.nan
    else:
        solved = (r > threshold).mean(axis=(0, 2))
        all_solved = float((r > threshold).mean())
    return {
        "mean": np.asarray(mean, np.float64),
        "se": np.asarray(se, np.float64),
        "solved_rate": solved,
        "cvar": np.asarray([cvar(r[:, j], alpha) for j in range(r.shape[1])]),
        "overall": {"mean": float(all_mean), "se": float(all_se), "solved_rate": all_solved, "cvar": cvar(r, alpha)},
    }


def format_table(labels, table: dict, alpha: float = CVAR_ALPHA) -> str:
    from shed_jax import reporting

    def pct(x):
        return "n/a" if not math.isfinite(x) else f"{100 * x:.0f} %"

    rows = [
        [lab, reporting.format_mean_se(table["mean"][j], table["se"][j]), pct(table["solved_rate"][j]), f"{table['cvar'][j]:.1f}"]
        for j, lab in enumerate(labels)
    ]
    o = table["overall"]
    rows.append(["all levels", reporting.format_mean_se(o["mean"], o["se"]), pct(o["solved_rate"]), f"{o['cvar']:.1f}"])
    return reporting.markdown_table(["level", "return (mean ± SE over seeds)", "solved", f"CVaR {100 * alpha:g} %"], rows, "lrrr")


# --------------------------------------------------------------------------------------------
# level sets
# --------------------------------------------------------------------------------------------


def _scalar_fields(base) -> list[str]:
    return [f for f in base.__dataclass_fields__ if np.ndim(getattr(base, f)) == 0]


def load_level_file(path, env):
    """Levels from a JSON file (see the module doc) -> (params with a leading axis, labels)."""
    from shed_jax.eval_sets import LevelSet

    path = pathlib.Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as err:
        raise LevelFileError(f"{path}: cannot read: {err}") from err
    except json.JSONDecodeError as err:
        raise LevelFileError(f"{path}: not valid JSON: {err}") from err
    if isinstance(data, dict) and "levels" in data:
        data = data["levels"]
    if not isinstance(data, list) or not data:
        raise LevelFileError(f"{path}: expected a non-empty JSON list of levels (parameter vectors or objects), got {type(data).__name__}")
    space, base = env.param_space, env.default_params
    fields = _scalar_fields(base)

    def number(v, where):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise LevelFileError(f"{path}: {where} must be a finite number, got {v!r}")
        return v

    if all(isinstance(x, list) for x in data):
        for i, v in enumerate(data):
            if len(v) != space.dim:
                raise LevelFileError(f"{path}: level {i} has {len(v)} values; {env.name} levels are vectors of "
                                     f"{space.dim} ({', '.join(space.names)})")
            for j, x in enumerate(v):
                number(x, f"level {i}, {space.names[j]}")
        columns = {n: np.asarray([v[j] for v in data], np.float64) for j, n in enumerate(space.names)}
        labels = [f"level-{i}" for i in range(len(data))]
    elif all(isinstance(x, dict) for x in data):
        used = sorted({k for d in data for k in d} - {"label"})
        unknown = [k for k in used if k not in fields]
        if unknown:
            raise LevelFileError(f"{path}: unknown {env.name} parameter(s) {unknown}; known: {', '.join(fields)}")
        columns = {}
        for k in used:
            default = np.asarray(getattr(base, k)).item()
            vals = []
            for i, d in enumerate(data):
                v = d.get(k, default)
                if isinstance(default, bool):
                    if not isinstance(v, bool):
                        raise LevelFileError(f"{path}: level {i}, {k} must be true or false, got {v!r}")
                else:
                    number(v, f"level {i}, {k}")
                    if isinstance(default, int) and float(v) != int(v):
                        raise LevelFileError(f"{path}: level {i}, {k} must be an integer, got {v!r}")
                vals.append(v)
            columns[k] = np.asarray(vals)
        labels = [str(d.get("label", f"level-{i}")) for i, d in enumerate(data)]
    else:
        raise LevelFileError(f"{path}: levels must be all vectors (lists) or all objects, got a mix")
    levels = LevelSet(columns).to_params(base)
    try:
        env.check_params(levels)
    except ValueError as err:
        raise LevelFileError(f"{path}: {err}") from err
    return levels, labels


def resolve_levels(spec: str, env, exp, tests):
    """``--levels`` -> (params with a leading axis, labels, short name for the output file)."""
    from shed_jax import levels as L

    if spec == "test":
        if exp.test_set in dict(L.ued(env).test_sets):  # the env's set: its own labels
            labels = L.test_set(env, exp.test_set)[1]
        else:  # a test set handed in from elsewhere (e.g. a test's own levels)
            labels = [f"test-{i}" for i in range(int(np.shape(np.asarray(tests.max_steps))[0]))]
        return tests, labels, "test"
    if spec == "named":
        named = L.named_levels(env)
        if named is None:
            raise LevelFileError(f"{env.name} has no named levels; use --levels test or a FILE")
        return named[0], named[1], "named"
    path = pathlib.Path(spec)
    if not path.exists():
        raise LevelFileError(f"--levels must be 'test', 'named' or an existing JSON file; {spec!r} is none of these")
    levels, labels = load_level_file(path, env)
    return levels, labels, re.sub(r"[^A-Za-z0-9_.-]+", "_", path.stem)


# --------------------------------------------------------------------------------------------
# command
# --------------------------------------------------------------------------------------------


def _json_num(x):
    x = float(x)
    return x if math.isfinite(x) else None


def main(args) -> int:
    from shed_jax.checkpoint import CheckpointError

    from shed_jax.cli import errors

    if args.episodes < 1:
        raise errors.UsageError(f"--episodes must be an integer >= 1, got {args.episodes}")
    if args.max_steps is not None and args.max_steps < 1:
        raise errors.UsageError(f"--max-steps must be an integer >= 1, got {args.max_steps}")
    try:
        return _main(args)
    except CheckpointError as err:
        errors.report(err, args)
        return EXIT_BAD_INPUT
    except LevelFileError as err:
        errors.report(err, args, prefix=f"{errors.PREFIX} --levels:")
        return EXIT_BAD_INPUT


def evaluate_students(exp, env, student, student_state, num_seeds: int, resolved, *, episodes: int = 10,
                      max_steps: int | None = None, deterministic: bool = False, seed: int = 0,
                      solved_threshold: float | None = None) -> tuple[dict, str]:
    """Evaluate every seed's student (vmapped, one compile) on a resolved level set.

    ``resolved`` is what ``resolve_levels`` returns. Seed i of the run uses ``fold_in(PRNGKey(seed), i)``,
    so the same state, levels and arguments give the same returns from ``eval`` and from ``run
    --final-eval``. Returns the JSON-ready result (levels, returns, per-level table) and the
    printed table.
    """
    import jax

    from shed_jax.levels import ued

    levels, labels, name = resolved
    threshold = solved_threshold if solved_threshold is not None else ued(env).solved_threshold
    root = jax.random.PRNGKey(seed)
    keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(np.arange(num_seeds))
    evaluate = jax.jit(jax.vmap(lambda s, k: student.evaluate(s, k, levels, episodes, max_steps, deterministic)))
    try:
        returns = np.asarray(evaluate(student_state, keys))  # [seeds, levels, episodes]
    except ValueError as err:  # e.g. levels longer than the env's default limit without --max-steps
        raise LevelFileError(str(err)) from err
    table = level_table(returns, threshold)
    vectors = np.asarray(env.param_space.to_vector(levels))
    result = {
        "env": exp.env,
        "method": exp.method,
        "preset": exp.preset,
        "levels": name,
        "labels": labels,
        "level_params": {n: vectors[:, j].tolist() for j, n in enumerate(env.param_space.names)},
        "seeds": num_seeds,
        "episodes": episodes,
        "max_steps": max_steps,
        "deterministic": bool(deterministic),
        "seed": seed,
        "solved_threshold": threshold,
        "cvar_alpha": CVAR_ALPHA,
        "returns": returns.tolist(),
        **table_json(labels, table),
    }
    return result, format_table(labels, table)


def _main(args) -> int:
    import jax

    from shed_jax.checkpoint import RunCheckpointer
    from shed_jax.cli import run as run_cli
    from shed_jax.loop import make_run

    run_dir = pathlib.Path(args.run)
    with RunCheckpointer(run_dir, create=False) as reader:
        config = reader.read_config(args.step)
        exp = run_cli.experiment_from_dict(config["experiment"])
        num_seeds, root_seed = int(config["seeds"]), int(config["root_seed"])
        env, student, method, tests = run_cli.build(exp)
        init, _ = make_run(student, method, tests, exp.loop)
        target = jax.eval_shape(jax.vmap(init), run_cli.seed_keys(root_seed, num_seeds))
        restored = reader.restore(target, step=args.step, with_history=False)
    resolved = resolve_levels(args.levels, env, exp, tests)
    body, text = evaluate_students(exp, env, student, restored.state.student, num_seeds, resolved,
                                   episodes=args.episodes, max_steps=args.max_steps, deterministic=args.deterministic,
                                   seed=args.seed, solved_threshold=args.solved_threshold)
    threshold = body["solved_threshold"]
    print(f"[shed_jax] {exp.method} on {exp.env}, {run_dir} at budget step {restored.step}: {num_seeds} seed(s) x "
          f"{args.episodes} episode(s) per level, {'deterministic' if args.deterministic else 'stochastic'} policy, "
          f"levels {args.levels!r}" + ("" if threshold is not None else " (no solved threshold for this env: pass --solved-threshold)"))
    print(text)
    result = {"run": str(run_dir), "checkpoint_step": restored.step, **body, "levels_arg": args.levels}
    out = pathlib.Path(args.out) if args.out else run_dir / f"eval_{body['levels']}.json"
    out.write_text(json.dumps(result, indent=2))
    print(f"[shed_jax] wrote {out}")
    return 0
