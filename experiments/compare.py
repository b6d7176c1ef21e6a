"""Compare finished runs of ``python -m shed_jax run``: one markdown table and plots for docs/results.md.

    python -m experiments.compare runs/lander-shed-paper-* runs/lander-dr-paper-* --out docs/results/lander --paper lander

Each RUN_DIR holds what ``python -m shed_jax run`` (``shed_jax/driver.py``) writes: ``config.json``
(the experiment, seeds, backend), ``metrics.jsonl`` (one record per budget step and seed) and
``summary.json`` (final numbers; missing if the run did not finish, in which case the table uses
the last step in ``metrics.jsonl`` and marks the row "partial").

Writes to OUT:

* ``results.md``: the table (method, env, preset, seeds, final mean test return ± SE over seeds,
  student env steps of the reported student and of the whole run, wall time per seed and, with
  ``--paper``, the paper's digitised final number from docs/design.md §12.1); for runs with several teacher
  episodes (SHED, h-MDP) a second table of the test return at the end of each tested episode;
  then links to the plots;
* ``curves_<env>.png``: mean test return ± SE vs student env steps, all methods of that env on one
  axis; for episodic methods (shed, hmdp: several teacher episodes) the last teacher episode, as
  ``make_plots`` in shed_jax/driver.py does. With ``--paper`` the paper's digitised curves are drawn
  dashed, with x = update x env steps per paper update (see ``PAPER_STEPS_PER_UPDATE``);
* ``per_level_<env>_<label>.png``: one panel per test level (the reported student, as the curves);
* ``params_<env>_<label>.png``: the parameters each method's teacher generated, per budget step;
* ``student_<env>_<label>.png``: the student's PPO statistics per budget step (as the run's
  ``student_training.png``);
* ``eval_vector_<env>_<label>.png``: SHED/h-MDP's performance vector (teacher state) per budget step;
* ``results.csv``: the raw numbers behind them, one row per (run, seed, budget step) where the test
  set ran: label, env, seed, teacher episode, step in it, the student env steps so far in that
  episode, the teacher reward, the test return and its per-level means.

Walker runs whose directory holds ``final_eval_named.json`` (``run``'s default final evaluation)
also get a table of DCD's six test levels: return ± SE over seeds with the solved rate (return > 230)
in parentheses, and the mean over all named levels; with ``--paper walker`` DCD's own table (docs/design.md §12.2,
Box2D at about 66x our budget) follows as reference rows. ``named_levels.png`` shows the same six
levels as bars, with DCD's means as markers under ``--paper walker``.

``--until-step N`` compares budget steps 0 to N-1 only, e.g. a stopped run against a finished one
at the same budget; a run cut there is partial, and its final files are left out.

Runs given the same ``--labels`` entry are pooled into one row: their seeds side by side (numbered
in the order of the RUN_DIRs), e.g. two 5-seed runs with root seeds 0 and 1 as one 10-seed row. They
must share the whole experiment config and differ in root seed, else the tool stops with an error.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import pathlib
import re
import sys

import numpy as np

from shed_jax import eval_sets

# The paper's digitised mean test-return curves, docs/design.md §12.1 (digitised from the
# paper's figures: mean line only, about ±10-20; x = student update 0-1000; y = mean return over the
# 10 test levels). A (low, high) pair is a range read off the figure. Keys are our method names:
# the lander "ACCEL" row is the official code's linear-ramp ACCEL (docs/design.md §11.2); the lander
# PAIRED row is from the paper's v1. Methods absent here (plr, accel-norevisit) have no number in the paper.
PAPER_UPDATES = (0, 200, 400, 600, 800, 1000)
PAPER = {
    "lander": {
        "shed": (-415, -259, -168, -120, -113, -100),
        "hmdp": (-491, -244, -214, -237, -185, -143),
        "accel": (-580, -249, -194, -442, -554, -254),
        "dr": (-632, -656, -639, -811, -661, -257),
        "paired": (-608, -435, -448, -723, -831, -377),
    },
    "walker": {
        "shed": (-110, 22, 51, 60, 51, (62, 65)),
        "accel": (-107, (9, 11), 41, (50, 56), 31, (54, 57)),
        "hmdp": (-108, 4, 29, 23, 17, 33),
        "dr": (-110, -4, (3, 7), (6, 9), -5, 18),
        "paired": (-112, -21, -11, -19, -22, -10),
    },
}
# Student env steps per plotted paper update, to overlay the paper's curves on our x axis: lander,
# the paper's 1e6 steps over 1000 updates (docs/design.md §10.3); walker, 1e7 env steps over 1000 (docs/design.md §12.1,
# "one plotted step ≈ 1e4 env steps (inferred)").
PAPER_STEPS_PER_UPDATE = {"lander": 1e3, "walker": 1e4}

# DCD's six standard BipedalWalker test levels (docs/design.md §9.2, §13.2), in the column order of DCD's table, and
# DCD's results on them (docs/design.md §12.2, from DCD's results files: 20k updates, about 6.6e8 Box2D steps,
# 10 seeds): (mean return, SE, solved rate) per level. An ordering reference, not a parity target.
NAMED_SET_A = eval_sets.DCD_TEST_LEVELS
DCD_SOLVED_THRESHOLD = 230.0  # an episode is solved when its return is above this (docs/design.md §9.3)
DCD_NAMED = {
    "ACCEL": ((317.9, 0.9, .998), (210.8, 10.7, .629), (91.6, 9.7, .206), (112.0, 24.0, .310), (165.8, 14.0, .491),
              (253.3, 13.1, .764)),
    "PLR⊥": ((304.8, 2.3, .992), (84.8, 12.8, .158), (51.0, 4.8, .045), (43.3, 11.3, .040), (6.5, 5.5, .006),
             (129.7, 13.3, .244)),
    "DR": ((266.8, 13.3, .836), (14.2, 3.9, .014), (18.6, 3.9, .007), (12.4, 3.7, .002), (-10.4, 3.9, .000),
           (51.8, 6.3, .033)),
}


def paper_env(env: str) -> str:
    """'lander-continuous' -> 'lander'; the paper's figures are per base environment."""
    return "lander" if env.startswith("lander") else env


def _point(v) -> float:
    return float(np.mean(v)) if isinstance(v, tuple) else float(v)


def format_paper(v) -> str:
    """A digitised value as printed in docs/design.md §12.1: ``≈ -100`` or ``≈ 62–65``."""
    if isinstance(v, tuple):
        return f"≈ {v[0]:g}–{v[1]:g}"
    return f"≈ {v:g}"


@dataclasses.dataclass
class Run:
    """One run directory, loaded."""

    path: pathlib.Path
    config: dict
    summary: dict | None
    hist: dict  # {key: [seeds, steps, ...]} from metrics.jsonl
    label: str = ""
    parts: list[Run] = dataclasses.field(default_factory=list)  # the runs pooled into this one, if any
    cut: bool = False  # budget steps past ``--until-step`` were left out: its final files are not read

    @property
    def experiment(self) -> dict:
        return self.config["experiment"]

    @property
    def env(self) -> str:
        return self.experiment["env"]

    @property
    def method(self) -> str:
        return self.experiment["method"]

    @property
    def preset(self) -> str:
        return self.experiment.get("preset", "?")

    @property
    def seeds(self) -> int:
        return int(self.hist["test_return"].shape[0])

    @property
    def num_episodes(self) -> int:
        return int(np.asarray(self.hist["episode"])[0, -1]) + 1

    @property
    def partial(self) -> bool:
        return self.summary is None


def load_run(path, until_step: int | None = None) -> Run:
    """Read config.json, metrics.jsonl and (if present) summary.json of one run directory; with
    ``until_step``, its budget steps before that one only (a run that went further is then partial:
    its summary and final evaluation describe later students)."""
    from shed_jax import reporting

    path = pathlib.Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"{path} is not a directory")
    for name in ("config.json", "metrics.jsonl"):
        if not (path / name).exists():
            raise FileNotFoundError(f"{path} has no {name}: is it a run directory of `python -m shed_jax run`?")
    config = json.loads((path / "config.json").read_text())
    if "experiment" not in config or not {"env", "method"} <= set(config["experiment"]):
        raise ValueError(f"{path / 'config.json'} has no experiment env/method")
    summary = json.loads((path / "summary.json").read_text()) if (path / "summary.json").exists() else None
    records = reporting.read_jsonl(path / "metrics.jsonl")
    if not records:
        raise ValueError(f"{path / 'metrics.jsonl'} is empty")
    cut = False
    if until_step is not None:
        kept = [r for r in records if r["step"] < until_step]
        if not kept:
            raise ValueError(f"{path / 'metrics.jsonl'} has no budget step before {until_step}")
        cut, records = len(kept) < len(records), kept
    hist = reporting.records_to_arrays(records)
    missing = {"test_return", "episode", "info/env_steps_train"} - set(hist)
    if missing:
        raise ValueError(f"{path / 'metrics.jsonl'} lacks {sorted(missing)}")
    return Run(path, config, None if cut else summary, hist, cut=cut)


def assign_labels(runs: list[Run]) -> None:
    """Label = method; where two runs share (env, method), add the preset, then the directory name."""
    for r in runs:
        r.label = r.method
    for extra in (lambda r: f"{r.method} ({r.preset})", lambda r: f"{r.method} ({r.path.name})"):
        seen: dict[tuple, int] = {}
        for r in runs:
            seen[(r.env, r.label)] = seen.get((r.env, r.label), 0) + 1
        for r in runs:
            if seen[(r.env, r.label)] > 1:
                r.label = extra(r)


def pool_runs(runs: list[Run], labels: list[str]) -> list[Run]:
    """Label the runs; runs sharing a label become one run with their seeds side by side.

    A pooled run keeps the first run's path and config; its summary (final return, wall time) is
    recomputed over all seeds, or None when a part has none (it did not finish). Raises
    ``ValueError`` when the runs of one label differ in their experiment or in the steps their
    metrics hold, or share a root seed (the same root seed gives the same seeds)."""
    from shed_jax import reporting

    groups: dict[str, list[Run]] = {}
    for r, label in zip(runs, labels, strict=True):
        r.label = label
        groups.setdefault(label, []).append(r)
    pooled = []
    for label, group in groups.items():
        if len(group) == 1:
            pooled.append(group[0])
            continue
        first = group[0]
        # metrics a newer version logs (a run resumed by it) are left out unless every run has them
        shared = [k for k in first.hist if all(k in r.hist for r in group)]
        for r in group[1:]:
            differ = sorted(k for k in set(r.experiment) | set(first.experiment)
                            if r.experiment.get(k) != first.experiment.get(k))
            if differ:
                raise ValueError(f"cannot pool {r.path} with {first.path} as {label!r}: their experiments "
                                 f"differ in {differ}")
            if any(r.hist[k].shape[1:] != first.hist[k].shape[1:] for k in shared):
                raise ValueError(f"cannot pool {r.path} with {first.path} as {label!r}: their metrics.jsonl "
                                 "differ in budget steps (did one stop early?)")
        roots = [r.config.get("root_seed") for r in group]
        if None in roots or len(set(roots)) != len(roots):
            raise ValueError(f"cannot pool the runs labelled {label!r}: their root seeds {roots} must be known "
                             "and distinct (the same root seed gives the same seeds)")
        hist = {k: np.concatenate([r.hist[k] for r in group], axis=0) for k in shared}
        summary = None
        if all(r.summary is not None for r in group):
            m, se = reporting.mean_se(np.asarray(hist["test_return"], np.float64)[:, -1])
            wall = sum(float(r.summary["wall_time_s"]) for r in group)
            summary = {"final_test_return_mean": float(m), "final_test_return_se": float(se), "wall_time_s": wall,
                       "wall_time_per_seed_s": wall / hist["test_return"].shape[0]}
        pooled.append(Run(first.path, first.config, summary, hist, label, parts=list(group)))
    return pooled


def pooled_note(runs: list[Run]) -> str | None:
    """One line naming the runs behind each pooled row (directory, root seed, seeds), or None."""
    notes = []
    for r in runs:
        if r.parts:
            parts = ", ".join(f"{p.path.name} (root seed {p.config['root_seed']}, {p.seeds} seeds)" for p in r.parts)
            notes.append(f"**{r.label}** = {parts}")
    return ("Pooled rows, seeds numbered in this order: " + "; ".join(notes) + ".") if notes else None


def final_return(run: Run) -> tuple[float, float]:
    """Final mean test return ± SE over seeds: summary.json's, else the last evaluated step's."""
    from shed_jax import reporting

    if run.summary is not None:
        return float(run.summary["final_test_return_mean"]), float(run.summary["final_test_return_se"])
    m, se, _ = reporting.final_value(run.hist["test_return"])
    return m, se


def env_steps(run: Run) -> tuple[float, float]:
    """Student env steps (mean over seeds) of the reported student (its teacher episode) and of the run."""
    train = np.asarray(run.hist["info/env_steps_train"], np.float64)
    episode = np.asarray(run.hist["episode"])[0]
    last = episode == episode[-1]
    return float(train[:, last].sum(axis=1).mean()), float(train.sum(axis=1).mean())


def table(runs: list[Run], paper: str | None = None) -> str:
    """The markdown comparison table, one row per run (sorted by env, then final return, best first)."""
    from shed_jax import reporting

    headers = ["method", "env", "preset", "seeds", "final test return (mean ± SE)", "student env steps",
               "all teacher episodes", "wall time / seed"]
    align = "lllrrrrr"
    if paper is not None:
        headers.append(f"paper, update 1000 (docs/design.md §12.1, {paper})")
        align += "r"
    rows = []
    order = sorted(runs, key=lambda r: (r.env, -np.nan_to_num(final_return(r)[0], nan=-np.inf)))
    for r in order:
        m, se = final_return(r)
        last, total = env_steps(r)
        wall = r.summary.get("wall_time_per_seed_s") if r.summary else None
        ret = reporting.format_mean_se(m, se) + (" (partial)" if r.partial else "")
        all_eps = reporting.format_count(total) + (f" ({r.num_episodes} ep.)" if r.num_episodes > 1 else "")
        row = [r.label, r.env, r.preset, r.seeds, ret, reporting.format_count(last), all_eps,
               reporting.format_duration(wall) if wall is not None else "n/a"]
        if paper is not None:
            ref = PAPER[paper].get(r.method) if paper_env(r.env) == paper else None
            row.append(format_paper(ref[-1]) if ref is not None else "—")
        rows.append(row)
    return reporting.markdown_table(headers, rows, align)


def curve(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """(x student env steps [n], y test return [seeds, n]) of the reported student."""
    from shed_jax import reporting

    return reporting.last_episode_curve(run.hist, "test_return")


def _safe(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", label).strip("_")


def param_space(env_name: str, dim: int):
    """The env's ParamSpace (names, low, high) if it matches ``dim`` parameters, else None."""
    import envs

    space = envs.make(env_name).param_space
    return space if space.dim == dim else None


def write_plots(runs: list[Run], out: pathlib.Path, paper: str | None = None) -> list[pathlib.Path]:
    """curves_<env>.png and per run per_level_/params_/student_/eval_vector_<env>_<label>.png; returns the paths."""
    from shed_jax import reporting

    written = []
    for env in sorted({r.env for r in runs}):
        group = [r for r in runs if r.env == env]
        curves = {}
        for r in group:
            label = reporting.episode_label(r.label, r.hist, r.num_episodes)
            curves[label] = curve(r)
        refs = {}
        if paper is not None and paper_env(env) == paper:
            scale = PAPER_STEPS_PER_UPDATE[paper]
            labels = {r.method: lab for r, lab in zip(group, curves)}
            for method, values in PAPER[paper].items():
                if method in labels:
                    refs[f"paper {method} (docs/design.md §12.1)"] = (np.asarray(PAPER_UPDATES, np.float64) * scale,
                                                          np.asarray([_point(v) for v in values]), labels[method])
        path = out / f"curves_{_safe(env)}.png"
        reporting.plot_curves(curves, path, xlabel="student env steps", ylabel="mean test return",
                              title=f"{env}: test return (mean ± SE over seeds)", reference_curves=refs)
        written.append(path)
    for r in runs:
        episode = np.asarray(r.hist["episode"])[0]
        starts = np.where(np.diff(episode) != 0)[0] + 0.5  # between the last and first step of two episodes
        per_level = r.hist.get("test_return_per_level")
        if per_level is not None and per_level.ndim == 3:
            x, y = reporting.last_episode_curve(r.hist, "test_return_per_level")
            path = out / f"per_level_{_safe(r.env)}_{_safe(r.label)}.png"
            reporting.plot_panels(x, y, path, title=f"{r.label} on {r.env}: return per test level "
                                  f"(mean ± SE over seeds; panel title: final mean)")
            written.append(path)
        levels = r.hist.get("info/levels")
        if levels is not None and levels.ndim == 4:
            space = param_space(r.env, levels.shape[-1])
            names = space.names if space is not None else tuple(f"p{j}" for j in range(levels.shape[-1]))
            path = out / f"params_{_safe(r.env)}_{_safe(r.label)}.png"
            reporting.plot_parameters(np.arange(levels.shape[1]), levels, names, path,
                                      f"{r.label} on {r.env}: generated level parameters per budget step",
                                      low=space.low if space is not None else None,
                                      high=space.high if space is not None else None, episode_starts=starts)
            written.append(path)
        path = out / f"student_{_safe(r.env)}_{_safe(r.label)}.png"
        if reporting.plot_student_training(r.hist, path, title=f"{r.label} on {r.env}: the student's PPO updates per "
                                           f"budget step (mean ± SE over seeds; panel title: last value)"):
            written.append(path)
        vec = r.hist.get("info/extras/teacher_state")
        if vec is not None and vec.ndim == 3:
            path = out / f"eval_vector_{_safe(r.env)}_{_safe(r.label)}.png"
            reporting.plot_eval_vector(np.arange(vec.shape[1]), vec, path, episode_starts=starts,
                                       title=f"{r.label} on {r.env}: performance vector (teacher state)")
            written.append(path)
    return written


def episode_table(runs: list[Run]) -> str | None:
    """Test return at the end of each tested teacher episode (mean ± SE over seeds), one row per
    run with more than one teacher episode (SHED, h-MDP); None if there is no such run."""
    from shed_jax import reporting

    rows, columns = {}, set()
    for r in runs:
        if r.num_episodes < 2:
            continue
        episode = np.asarray(r.hist["episode"])[0]
        ret = np.asarray(r.hist["test_return"], np.float64)
        cells = {}
        for e in np.unique(episode):
            last = np.nonzero(episode == e)[0][-1]  # the episode's final budget step
            if np.any(np.isfinite(ret[:, last])):
                m, se = reporting.mean_se(ret[:, last])
                cells[int(e)] = reporting.format_mean_se(float(m), float(se))
        rows[r.label] = cells
        columns |= set(cells)
    if not rows:
        return None
    columns = sorted(columns)
    return reporting.markdown_table(["teacher episode"] + [str(e) for e in columns],
                                    [[label] + [cells.get(e, "—") for e in columns] for label, cells in rows.items()],
                                    "l" + "r" * len(columns))


def format_level_cell(mean: float, se: float, solved: float | None) -> str:
    """``-17.3 ± 21.9 (.540)``: return ± SE with the solved rate as DCD prints it."""
    from shed_jax import reporting

    text = reporting.format_mean_se(mean, se)
    if solved is not None and np.isfinite(solved):
        text += " (" + f"{solved:.3f}".lstrip("0") + ")"
    return text


def named_results(runs: list[Run]) -> list[tuple[Run, dict]]:
    """(run, its ``final_eval_named.json``) for each run that has one, checked: DCD's six levels
    present (looked up by label, not position) and DCD's solved threshold (230)."""
    found = []
    for r in runs:
        ev = _named_eval(r)
        if ev is None:
            continue
        path = r.path / "final_eval_named.json"
        labels = {lv["label"] for lv in ev["per_level"]}
        missing = [name for name in NAMED_SET_A if name not in labels]
        if missing:
            raise ValueError(f"{path} lacks the named levels {missing}")
        threshold = ev.get("solved_threshold", DCD_SOLVED_THRESHOLD)
        if threshold != DCD_SOLVED_THRESHOLD:
            raise ValueError(f"{path} counts returns above {threshold} as solved; DCD's table uses "
                             f"{DCD_SOLVED_THRESHOLD:g}")
        found.append((r, ev))
    return found


def _named_eval(r: Run) -> dict | None:
    """The run's ``final_eval_named.json`` (None without one). For a pooled run, its parts' files
    with the returns of all seeds side by side and the statistics recomputed over them."""
    from shed_jax import evaluation

    def read(run):
        path = run.path / "final_eval_named.json"
        return json.loads(path.read_text()) if path.exists() and not run.cut else None

    if not r.parts:
        return read(r)
    evs = [read(p) for p in r.parts]
    if all(ev is None for ev in evs):
        return None
    same = ("labels", "episodes", "max_steps", "deterministic", "solved_threshold")
    for p, ev in zip(r.parts, evs):
        if ev is None:
            raise ValueError(f"{p.path} has no final_eval_named.json, but the runs pooled with it as {r.label!r} do")
        if any(ev.get(k) != evs[0].get(k) for k in same):
            raise ValueError(f"{p.path / 'final_eval_named.json'} differs from {r.parts[0].path / 'final_eval_named.json'} "
                             f"in one of {list(same)}: their named evaluations cannot be pooled")
    returns = np.concatenate([np.asarray(ev["returns"], np.float64) for ev in evs], axis=0)
    table = evaluation.level_table(returns, evs[0].get("solved_threshold"), evs[0].get("cvar_alpha", evaluation.CVAR_ALPHA))
    return {**evs[0], "seeds": int(returns.shape[0]), "returns": returns.tolist(),
            **evaluation.table_json(evs[0]["labels"], table)}


def _set_a(ev: dict, field: str) -> list[float]:
    by_label = {lv["label"]: lv for lv in ev["per_level"]}
    return [by_label[name][field] for name in NAMED_SET_A]


def named_table(runs: list[Run], paper: str | None = None) -> str | None:
    """DCD's six walker test levels from each run's ``final_eval_named.json`` (one row per run that
    has one; the last column pools every named level, DCD's six and the harder ones), with DCD's
    reference rows when ``paper == "walker"``; None if no run has a named-level evaluation.

    Runs whose named sets differ in size (an older level list) say so in their pooled cell, since
    those pools are not comparable."""
    from shed_jax import reporting

    found = named_results(runs)
    if not found:
        return None
    rows, sizes = [], []
    for r, ev in found:
        cells = [format_level_cell(*c) for c in zip(_set_a(ev, "mean"), _set_a(ev, "se"), _set_a(ev, "solved_rate"))]
        o = ev["overall"]
        rows.append([r.label, str(ev["seeds"])] + cells + [format_level_cell(o["mean"], o["se"], o["solved_rate"])])
        sizes.append(len(ev["per_level"]))
    pooled = f"all {sizes[0]} named levels"
    if len(set(sizes)) > 1:
        pooled = "all named levels"
        for row, n in zip(rows, sizes):
            row[-1] += f" [{n} levels]"
    if paper == "walker":
        for name, cells in DCD_NAMED.items():
            rows.append([f"DCD {name} (docs/design.md §12.2)", "10"] + [format_level_cell(*c) for c in cells] + ["—"])
    return reporting.markdown_table(["method", "seeds", *NAMED_SET_A, pooled], rows, "lr" + "r" * 7)


def plot_named(runs: list[Run], out: pathlib.Path, paper: str | None = None) -> pathlib.Path | None:
    """named_levels.png: the runs' returns on DCD's six levels as bars (± SE over seeds), the solved
    line, and DCD's numbers as markers under ``--paper walker``; None without named evaluations."""
    from shed_jax import reporting

    found = named_results(runs)
    if not found:
        return None
    refs = {f"DCD {name}": [c[0] for c in cells] for name, cells in DCD_NAMED.items()} if paper == "walker" else None
    path = out / "named_levels.png"
    reporting.plot_level_bars(NAMED_SET_A, {r.label: (_set_a(ev, "mean"), _set_a(ev, "se")) for r, ev in found}, path,
                              title="DCD's test levels: final return (mean ± SE over seeds)",
                              threshold=DCD_SOLVED_THRESHOLD, references=refs)
    return path


def write_csv(runs: list[Run], path: pathlib.Path) -> int:
    """One row per (run, seed, budget step) with a test-set result; returns the number of rows."""
    levels = max((r.hist["test_return_per_level"].shape[-1] for r in runs if "test_return_per_level" in r.hist),
                 default=0)
    header = ["method", "env", "seed", "episode", "step_in_episode", "student_env_steps_in_episode",
              "teacher_reward", "test_return"] + [f"test_level_{j + 1}" for j in range(levels)]
    n = 0
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for r in runs:
            h = r.hist
            episode = np.asarray(h["episode"])
            train = np.asarray(h["info/env_steps_train"], np.float64)
            in_episode = np.zeros_like(train)  # cumulative student env steps within each teacher episode
            for e in np.unique(episode[0]):
                sel = episode[0] == e
                in_episode[:, sel] = np.cumsum(train[:, sel], axis=1)
            step_in = np.asarray(h.get("step_in_episode", np.broadcast_to(np.arange(train.shape[1]), train.shape)))
            reward = np.asarray(h.get("info/teacher_reward", np.full(train.shape, np.nan)), np.float64)
            ret = np.asarray(h["test_return"], np.float64)
            per_level = np.asarray(h.get("test_return_per_level", np.full(ret.shape + (0,), np.nan)), np.float64)
            for s in range(ret.shape[0]):
                for t in np.nonzero(np.isfinite(ret[s]))[0]:
                    cells = [reward[s, t], ret[s, t], *per_level[s, t], *([np.nan] * (levels - per_level.shape[-1]))]
                    w.writerow([r.label, r.env, s, int(episode[s, t]), int(step_in[s, t]), int(in_episode[s, t])]
                               + ["" if not np.isfinite(v) else f"{v:.2f}" for v in cells])
                    n += 1
    return n


def markdown(runs: list[Run], plots: list[pathlib.Path], out: pathlib.Path, paper: str | None) -> str:
    lines = [table(runs, paper), ""]
    note = pooled_note(runs)
    if note is not None:
        lines += [note, ""]
    episodes = episode_table(runs)
    if episodes is not None:
        lines += ["Test return at the end of each tested teacher episode (mean ± SE over seeds):", "", episodes, ""]
    named = named_table(runs, paper)
    if named is not None:
        lines += ["DCD's test levels after the last budget step (`final_eval_named.json`): return, mean ± SE over "
                  "seeds, and in parentheses the solved rate, the share of all episodes with return > 230:", "",
                  named, ""]
    lines.append("Final test return: mean over the test levels of the per-level mean return at the last budget "
                 "step, mean ± SE over seeds (SE = sd/√n, ddof 1). Student env steps: those of the reported "
                 "student (for SHED/h-MDP its last teacher episode); \"all teacher episodes\" counts every "
                 "student the teacher trained.")
    if paper is not None:
        lines.append("Paper: the mean line digitised from the paper's figure at update ≈ 1000 (docs/design.md §12.1), "
                     "±10–20 from digitising, over an unknown number of seeds.")
    lines.append("")
    for p in plots:
        lines.append(f"![{p.stem}]({p.relative_to(out).as_posix()})")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.compare", description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories written by `python -m shed_jax run`")
    p.add_argument("--out", required=True, help="output directory (results.md, results.csv and PNGs)")
    p.add_argument("--labels", default=None,
                   help="comma-separated labels, one per RUN_DIR, for the table and the plots "
                        "(default: the method, disambiguated by preset, then directory name); RUN_DIRs "
                        "with the same label are pooled into one row (same experiment, other root seeds)")
    p.add_argument("--paper", choices=sorted(PAPER), default=None,
                   help="add the paper's digitised numbers (docs/design.md §12.1) for this environment")
    p.add_argument("--until-step", type=int, default=None, metavar="N",
                   help="compare budget steps 0 to N-1 only: runs of different lengths at one budget (a run cut "
                        "short is partial, its final evaluation left out)")
    args = p.parse_args(argv)
    if args.until_step is not None and args.until_step < 1:
        p.error(f"--until-step must be at least 1, got {args.until_step}")
    try:
        runs = [load_run(d, args.until_step) for d in args.runs]
    except (OSError, ValueError) as err:
        p.error(str(err))
    assign_labels(runs)
    if args.labels is not None:
        labels = [x.strip() for x in args.labels.split(",")]
        if len(labels) != len(runs) or not all(labels):
            p.error(f"--labels needs {len(runs)} non-empty labels (one per RUN_DIR), got {args.labels!r}")
        try:
            runs = pool_runs(runs, labels)
        except ValueError as err:
            p.error(str(err))
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plots = write_plots(runs, out, args.paper)
    named = plot_named(runs, out, args.paper)
    if named is not None:
        plots.append(named)
    rows = write_csv(runs, out / "results.csv")
    text = markdown(runs, plots, out, args.paper)
    (out / "results.md").write_text(text)
    print(text)
    print(f"[compare] wrote {out / 'results.md'}, {len(plots)} plot(s) and {out / 'results.csv'} ({rows} rows)",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
