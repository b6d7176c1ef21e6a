"""Evaluating trained students on level sets: the per-level table, level sets by name or file.

``evaluate_students`` runs every seed's student (seeds vmapped, one compile) on a level set for a
number of episodes per level and returns one row per level: the mean return (mean over seeds of
each seed's mean), its standard error over seeds, the solved rate (fraction of all episodes with
return > the solved threshold, by default the env's ``ued.solved_threshold``: lander 200, walker 230) and the CVaR at 10 % (mean of the
worst ceil(0.1 n) of the n = seeds x episodes returns). ``python -m shed_jax eval`` and
``run --final-eval`` both use it, so the same state, levels and arguments give the same returns.

Level sets (``resolve_levels``; ``eval --levels``, ``run --final-eval``):

* ``test``: the run's own test set (lander: the 10 official test landers; walker: its test set);
* ``named``: the environment's named levels (``env.ued.named_levels``). Walker: every level of
  ``envs.walker.levels.LEVELS`` (fixed terrains, seeds 1000 + i); lander: the official 10 evaluation
  landers then the 10 test landers (``shed_jax.eval_sets``); cartpole: its ``LEVELS``;
* ``FILE.json``: a list of levels, each a parameter vector in ``env.param_space`` order or an object
  of params fields by name (missing fields take the env's defaults; an optional ``"label"``), or
  ``{"levels": [...]}``. Values are checked against the env's physical bounds, not clipped.
"""
from __future__ import annotations

import importlib
import json
import math
import pathlib
import re

import numpy as np

from shed_jax.errors import UsageError

CVAR_ALPHA = 0.1


class LevelFileError(ValueError):
    """A --levels FILE that cannot be turned into levels (the message names the entry and field)."""


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



def _json_num(x):
    x = float(x)
    return x if math.isfinite(x) else None


def evaluation_program(student, levels, episodes: int, max_steps: int | None = None, deterministic: bool = False):
    """The jitted, seed-vmapped ``(student states, keys) -> returns [seeds, levels, episodes]`` that
    ``evaluate_students`` compiles; ``experiment.seed_keys`` gives its keys."""
    import jax

    return jax.jit(jax.vmap(lambda s, k: student.evaluate(s, k, levels, episodes, max_steps, deterministic)))


def evaluate_students(exp, env, student, student_state, num_seeds: int, resolved, *, episodes: int = 10,
                      max_steps: int | None = None, deterministic: bool = False, seed: int = 0,
                      solved_threshold: float | None = None, wait=None, compiled=None) -> tuple[dict, str]:
    """Evaluate every seed's student (vmapped, one compile) on a resolved level set.

    ``resolved`` is what ``resolve_levels`` returns. Seed i of the run uses ``fold_in(PRNGKey(seed), i)``,
    so the same state, levels and arguments give the same returns from ``eval`` and from ``run
    --final-eval``. ``wait(thunk, what)`` runs the two long stages, ``what`` = "compiling" then
    "evaluating", and returns the thunk's value (the CLI's ``driver.in_worker`` with a heartbeat line,
    so a long evaluation is never silent); None calls them directly. ``compiled``: the program of
    ``evaluation_program`` for these arguments, compiled earlier (``run`` compiles it while training);
    where it does not take these arrays (another sharding) it is compiled again. Returns the
    JSON-ready result (levels, returns, per-level table) and the printed table.
    """
    from shed_jax.experiment import seed_keys
    from shed_jax.levels import ued

    levels, labels, name = resolved
    threshold = solved_threshold if solved_threshold is not None else ued(env).solved_threshold
    keys = seed_keys(seed, num_seeds)
    wait = wait or (lambda thunk, what: thunk())
    returns = None
    if compiled is not None:
        try:  # JAX checks the arguments' avals (TypeError) and sharding (ValueError) as the call is dispatched
            out = compiled(student_state, keys)
        except (TypeError, ValueError) as err:
            print(f"[shed_jax] the evaluation program compiled earlier does not take these students "
                  f"({type(err).__name__}: {str(err).splitlines()[0]}); compiling it again", flush=True)
        else:
            returns = wait(lambda: np.asarray(out), "evaluating")
    if returns is None:
        evaluate = evaluation_program(student, levels, episodes, max_steps, deterministic)
        try:
            program = wait(lambda: evaluate.lower(student_state, keys).compile(), "compiling")
        except ValueError as err:  # e.g. levels longer than the env's default limit without --max-steps
            raise LevelFileError(str(err)) from err
        returns = wait(lambda: np.asarray(program(student_state, keys)), "evaluating")  # [seeds, levels, episodes]
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




def find_levels(env) -> dict | None:
    """The LEVELS dict of the env's module or package (name -> params, or builder -> params)."""
    module = type(env).__module__
    candidates = [module, module.rsplit(".", 1)[0], module.rsplit(".", 1)[0] + ".levels"]
    for name in candidates:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError:
            continue
        if isinstance(getattr(mod, "LEVELS", None), dict):
            return mod.LEVELS
    return None


def final_eval_specs(arg: str | None, default: str = "none") -> list[str]:
    """``--final-eval`` -> the level-set specs to evaluate after the run (``eval --levels`` values);
    ``default`` (the env's ``ued.final_eval``) when the flag was not given."""
    text = default if arg is None else arg
    specs = [t.strip() for t in text.split(",") if t.strip()]
    if "none" in specs:
        if len(specs) > 1:
            raise UsageError(f"--final-eval: 'none' cannot be combined with level sets, got {arg!r}")
        return []
    if len(set(specs)) != len(specs):
        raise UsageError(f"--final-eval names a level set twice: {arg!r}")
    return specs


def final_level_sets(arg: str | None, exp, env, tests) -> list:
    """``--final-eval`` resolved for one experiment (UsageError for a bad set), before anything compiles."""
    try:
        return [resolve_levels(spec, env, exp, tests) for spec in final_eval_specs(arg, env.ued.final_eval)]
    except LevelFileError as err:
        raise UsageError(f"--final-eval: {err}") from err


def restore_students(run_dir, step: int | None = None):
    """A saved run's experiment, parts and final students: ``(exp, env, student, tests, seeds, step, students)``.

    Reads checkpoint ``step`` (default: the latest) without its metrics history; CheckpointError if
    it cannot be used.
    """
    import jax

    from shed_jax.checkpoint import RunCheckpointer
    from shed_jax.experiment import build, experiment_from_dict, seed_keys
    from shed_jax.loop import make_run

    with RunCheckpointer(pathlib.Path(run_dir), create=False) as reader:
        config = reader.read_config(step)
        exp = experiment_from_dict(config["experiment"])
        num_seeds, root_seed = int(config["seeds"]), int(config["root_seed"])
        env, student, method, tests = build(exp)
        init, _ = make_run(student, method, tests, exp.loop)
        target = jax.eval_shape(jax.vmap(init), seed_keys(root_seed, num_seeds))
        restored = reader.restore(target, step=step, with_history=False)
    return exp, env, student, tests, num_seeds, restored.step, restored.state.student
