"""Host-side reporting of a run: per-step records, mean and standard error over seeds, tables, plots.

Everything here runs between compiled chunks (or after a run), on numpy arrays that came back from
the device. Metrics arrive as a pytree whose leaves have shape ``[seeds, steps, ...]``;
``flatten_tree`` turns it into ``{"info/levels": array, ...}``, ``step_records`` into one JSON record
per (step, seed) for ``metrics.jsonl``, and ``records_to_arrays`` reads those records back into the
same ``[seeds, steps, ...]`` arrays.

Plots (matplotlib, Agg backend, one PNG each):

* ``plot_curves``      mean ± SE over seeds of several methods on one axis (optionally with the
                       paper's digitised curves as dashed references);
* ``plot_panels``      small multiples, mean ± SE over seeds: one panel per test level, or per
                       training statistic of the student (``plot_student_training``);
* ``plot_parameters``  the teacher's generated parameters per budget step, one panel per parameter;
* ``plot_eval_vector`` SHED/h-MDP's performance vector over budget steps (heatmap + its mean);
* ``plot_level_bars``  final returns on named levels, one bar per method per level, ± SE, with a
                       solved threshold and reference markers (e.g. DCD's published numbers).
"""
from __future__ import annotations

import json
import math
import pathlib
import warnings
from typing import Any, Iterable, Sequence

import numpy as np
import orjson

# --------------------------------------------------------------------------------------------
# statistics
# --------------------------------------------------------------------------------------------


def mean_se(x: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error (sd / sqrt(n), ddof 1) over ``axis``, ignoring NaN.

    With a single sample the standard error is 0 (not NaN), so plots still draw a line.
    """
    x = np.asarray(x, np.float64)
    n = np.sum(~np.isnan(x), axis=axis)
    # numpy warns of all-NaN columns and of columns with one value; both are answered below (NaN, SE 0)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(x, axis=axis) if x.size else np.zeros(0)
        if x.shape[axis] > 1:
            sd = np.nanstd(x, axis=axis, ddof=1)
            se = np.where(n > 1, sd / np.sqrt(np.maximum(n, 1)), 0.0)
        else:
            se = np.zeros_like(mean)
    return mean, se


# --------------------------------------------------------------------------------------------
# records: metrics pytree <-> metrics.jsonl
# --------------------------------------------------------------------------------------------


def flatten_tree(tree: Any, prefix: str = "") -> dict[str, np.ndarray]:
    """Nested dicts / flax dataclasses -> {'a/b/c': array}."""
    out: dict[str, np.ndarray] = {}
    if hasattr(tree, "__dataclass_fields__"):
        tree = {f: getattr(tree, f) for f in tree.__dataclass_fields__}
    if isinstance(tree, dict):
        for k, v in tree.items():
            out.update(flatten_tree(v, f"{prefix}{k}/"))
    else:
        out[prefix[:-1]] = np.asarray(tree)
    return out


def _serialisable(x: np.ndarray) -> np.ndarray:
    """``x`` as orjson takes it: C-contiguous, native byte order, floats as float32 or float64
    (bfloat16 and float16, which orjson lacks, become float32). Each value is written with the
    shortest digits that read back to it in its own precision: ``0.1`` for float32 0.1, not
    ``0.10000000149011612``. This is lossless for the float32 metrics and halves ``metrics.jsonl``
    (a walker step records up to 64 levels x 8 parameters per seed). Small exponents are spelt out:
    ``0.00001``, not ``1e-05``."""
    x = np.asarray(x)
    if x.dtype.kind not in "iub" and x.dtype not in (np.float32, np.float64):
        x = x.astype(np.float32)
    return np.ascontiguousarray(x.astype(x.dtype.newbyteorder("="), copy=False))


def step_records(metrics: dict[str, np.ndarray], seed_ids: Iterable[int]) -> list[dict]:
    """One record per (seed, step) from flattened ``[seeds, steps, ...]`` arrays, step-major.

    The values are numpy scalars and array views, written by :func:`append_jsonl` (orjson):
    non-finite floats become ``null`` (JSON has no NaN; ``records_to_arrays`` turns them back into
    NaN), and each float the shortest decimal that reads back to it in its own precision. A sweep
    of 1,024 seeds writes its records while the next chunk runs, so this must take less time than
    a chunk: orjson writes these arrays about 10x faster than ``json`` writes Python lists.
    """
    seed_ids = list(seed_ids)
    arrays = {k: _serialisable(v) for k, v in metrics.items()}
    num_steps = next(iter(arrays.values())).shape[1]
    return [{"seed": int(seed), **{k: v[i, t] for k, v in arrays.items()}}
            for t in range(num_steps) for i, seed in enumerate(seed_ids)]


def jsonl_bytes(records: list[dict]) -> bytes:
    """The JSON Lines text of ``records`` (values: Python scalars, numpy scalars and arrays of one
    dimension or more; NaN/Inf -> null)."""
    return b"".join(orjson.dumps(r, option=orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_APPEND_NEWLINE) for r in records)


def append_jsonl(path: pathlib.Path, records: list[dict]) -> None:
    with open(path, "ab") as f:
        f.write(jsonl_bytes(records))


def read_jsonl(path: pathlib.Path) -> list[dict]:
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def _to_array(values: list) -> np.ndarray:
    """A nested list from JSON -> array; ``None`` (a non-finite float) -> NaN."""
    arr = np.asarray(values)
    if arr.dtype == object:
        try:
            arr = np.asarray(values, np.float64)
        except (TypeError, ValueError) as err:
            raise ValueError(f"records hold ragged or non-numeric values: {err}") from None
    return arr


def records_to_arrays(records: list[dict]) -> dict[str, np.ndarray]:
    """The inverse of ``step_records``: records -> ``{key: [seeds, steps, ...]}``, seeds sorted by id.

    Records of one seed are taken in file order (that is, step order). Every seed must have the
    same number of records. A key only some records hold (a run resumed by a version that logs a
    metric its checkpoint's version did not) is NaN in the others, with the shape it has where held.
    """
    if not records:
        raise ValueError("records_to_arrays: no records")
    keys: dict[str, Any] = {}  # key -> its first value (the shape of a missing one), in first-seen order
    by_seed: dict[Any, list[dict]] = {}
    for n, r in enumerate(records):
        if "seed" not in r:
            raise ValueError(f"record {n} has no 'seed' field")
        for k, v in r.items():
            if k != "seed" and k not in keys:
                keys[k] = v
        by_seed.setdefault(r["seed"], []).append(r)
    lengths = {s: len(v) for s, v in by_seed.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"seeds have different numbers of records (a partial write?): {lengths}")
    seeds = sorted(by_seed)
    out = {"seed": np.asarray([[s] * lengths[s] for s in seeds])}
    for k, first in keys.items():
        missing = np.full(np.shape(_to_array(first)), np.nan).tolist()
        out[k] = _to_array([[r.get(k, missing) for r in by_seed[s]] for s in seeds])
    return out


# --------------------------------------------------------------------------------------------
# curves
# --------------------------------------------------------------------------------------------


def last_tested_episode(hist: dict[str, np.ndarray], key: str = "test_return") -> int:
    """The last teacher episode in which any seed has a finite ``hist[key]``; the last episode when
    none has. A finished run tests its last episode; a partial one (stopped by ``--time-limit``, or
    resumed mid-way) may not have yet, and then reports the last episode that was tested."""
    episode = np.asarray(hist["episode"])[0]
    y = np.asarray(hist[key], np.float64)
    tested = np.any(np.isfinite(y.reshape(y.shape[0], y.shape[1], -1)), axis=(0, 2))
    return int(episode[tested][-1]) if tested.any() else int(episode[-1])


def last_episode_curve(hist: dict[str, np.ndarray], key: str = "test_return") -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of the last tested teacher episode (``last_tested_episode``): x = cumulative student
    env steps of seed 0 within it ``[n]``, y = ``hist[key]`` over those steps ``[seeds, n, ...]``.

    For methods with one episode this is the whole run. Steps where every seed has NaN (no
    test-set evaluation at that step, ``LoopSpec.test_every > 1``) are dropped.
    """
    episode = np.asarray(hist["episode"])[0]
    last = episode == last_tested_episode(hist, key)
    x = np.cumsum(np.asarray(hist["info/env_steps_train"])[0, last].astype(np.float64))
    y = np.asarray(hist[key])[:, last].astype(np.float64)
    keep = ~np.all(np.isnan(y.reshape(y.shape[0], y.shape[1], -1)), axis=(0, 2))
    return x[keep], y[:, keep]


def episode_label(name: str, hist: dict[str, np.ndarray], num_episodes: int) -> str:
    """``name``, with the teacher episode (counted from 1) its curve shows when the run has several."""
    if num_episodes <= 1:
        return name
    return f"{name} (teacher episode {last_tested_episode(hist) + 1})"


def final_value(y: np.ndarray) -> tuple[float, float, int]:
    """Mean, SE and index of the last step where any seed of ``y [seeds, steps]`` is finite."""
    y = np.asarray(y, np.float64)
    finite = np.where(np.any(np.isfinite(y), axis=0))[0]
    if finite.size == 0:
        return math.nan, math.nan, -1
    t = int(finite[-1])
    m, se = mean_se(y[:, t])
    return float(m), float(se), t


# --------------------------------------------------------------------------------------------
# text formatting
# --------------------------------------------------------------------------------------------


def format_mean_se(mean: float, se: float, digits: int = 1) -> str:
    """``-100.0 ± 3.2``; ``n/a`` for a NaN mean."""
    if mean is None or not math.isfinite(float(mean)):
        return "n/a"
    if se is None or not math.isfinite(float(se)):
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {se:.{digits}f}"


def format_count(n: float) -> str:
    """Compact counts: 950, 12.8k, 1.02M, 2.05G (three significant digits)."""
    if n is None or not math.isfinite(float(n)):
        return "n/a"
    n = float(n)
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(n) >= scale:
            v = n / scale
            return f"{v:.3g}{unit}" if abs(v) < 1000 else f"{v:.0f}{unit}"
    return f"{n:.0f}"


def format_duration(seconds: float) -> str:
    """``42 s``, ``12.5 min``, ``3.20 h``."""
    if seconds is None or not math.isfinite(float(seconds)):
        return "n/a"
    s = float(seconds)
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.2f} h"


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], align: str | None = None) -> str:
    """A GitHub markdown table; ``align`` is one of l/r/c per column (default: left). Pipes in
    cells are escaped."""
    if align is None:
        align = "l" * len(headers)
    if len(align) != len(headers):
        raise ValueError(f"markdown_table: align {align!r} has {len(align)} entries for {len(headers)} columns")
    marks = {"l": "---", "r": "---:", "c": ":---:"}
    if set(align) - set(marks):
        raise ValueError(f"markdown_table: align must use only l, r, c; got {align!r}")

    def cell(v) -> str:
        return str(v).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(cell(h) for h in headers) + " |", "|" + "|".join(marks[a] for a in align) + "|"]
    for n, row in enumerate(rows):
        if len(row) != len(headers):
            raise ValueError(f"markdown_table: row {n} has {len(row)} cells for {len(headers)} columns")
        lines.append("| " + " | ".join(cell(v) for v in row) + " |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# plots
# --------------------------------------------------------------------------------------------


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finite_columns(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop steps where every seed is NaN, so lines do not break at unevaluated steps."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if y.ndim == 1:
        y = y[None]
    if y.shape[-1] != x.shape[0]:
        raise ValueError(f"curve has {x.shape[0]} x values but y of shape {y.shape} (expected [seeds, {x.shape[0]}])")
    keep = ~np.all(np.isnan(y), axis=0)
    return x[keep], y[:, keep]


def _cut(x: np.ndarray, y: np.ndarray, x_max: float) -> tuple[np.ndarray, np.ndarray]:
    """The part of a curve with x <= x_max, ending with the interpolated point at x_max."""
    if not np.isfinite(x_max) or x.size == 0 or x[-1] <= x_max:
        return x, y
    keep = x <= x_max
    if keep.any() and x_max > x[keep][-1]:
        return np.append(x[keep], x_max), np.append(y[keep], np.interp(x_max, x, y))
    return x[keep], y[keep]


def _episode_lines(ax, episode_starts) -> None:
    for s in episode_starts if episode_starts is not None else ():
        ax.axvline(s, color="grey", linewidth=0.6, alpha=0.5, linestyle=":")


def plot_curves(curves: dict[str, tuple[np.ndarray, np.ndarray]], path: pathlib.Path, *, xlabel: str,
                ylabel: str, title: str, references: dict[str, float] | None = None,
                reference_curves: dict[str, tuple] | None = None, logx: bool = False) -> None:
    """Mean ± SE curves of several methods on one axis. ``curves[label] = (x [steps], y [seeds, steps])``.

    ``references[label] = value`` draws a grey horizontal line. ``reference_curves[label] = (x, y)`` or
    ``(x, y, curve_label)`` draws a dashed line with markers (e.g. a paper's digitised curve), in the
    colour of ``curves[curve_label]`` when given; the x axis ends at the curves' last step, so a
    reference longer than the runs is cut there. Steps where every seed is NaN are skipped.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5), dpi=120)
    colors: dict[str, str] = {}
    x_max = -np.inf
    for label, (x, y) in curves.items():
        x, y = _finite_columns(x, y)
        x_max = max(x_max, float(np.max(x))) if x.size else x_max
        m, se = mean_se(y, axis=0)
        line, = ax.plot(x, m, label=f"{label} (n={y.shape[0]})", linewidth=1.6)
        colors[label] = line.get_color()
        ax.fill_between(x, m - se, m + se, color=line.get_color(), alpha=0.22, linewidth=0)
    for label, ref in (reference_curves or {}).items():
        rx, ry = _cut(np.asarray(ref[0], np.float64), np.asarray(ref[1], np.float64), x_max)
        color = colors.get(ref[2]) if len(ref) > 2 and ref[2] is not None else None
        ax.plot(rx, ry, linestyle="--", marker="o", markersize=3, linewidth=1.0, alpha=0.8,
                color=color or "grey", label=label)
    for label, value in (references or {}).items():
        ax.axhline(value, linestyle="--", linewidth=1, color="grey")
        ax.annotate(label, (ax.get_xlim()[0], value), fontsize=7, color="grey", va="bottom")
    if logx:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_panels(x: np.ndarray, series: np.ndarray, path: pathlib.Path, *, title: str,
                names: Sequence[str] | None = None, xlabel: str = "student env steps", ylabel: str = "test return",
                sharey: bool = True, digits: int = 0, episode_starts: Sequence[float] | None = None) -> None:
    """Small multiples: one panel per series, mean ± SE over seeds. ``series [seeds, steps, K]``.

    Two uses: one panel per test level (``sharey``: levels compare at a glance), and one panel per
    training statistic (``sharey=False``: each has its own scale). Each panel title carries its final
    mean with ``digits`` decimals; ``episode_starts`` draws dotted lines between teacher episodes.
    """
    plt = _pyplot()
    series = np.asarray(series, np.float64)
    if series.ndim != 3:
        raise ValueError(f"plot_panels: series must be [seeds, steps, panels], got shape {series.shape}")
    K = series.shape[-1]
    names = list(names) if names is not None else [f"level {j}" for j in range(K)]
    if len(names) != K:
        raise ValueError(f"plot_panels: {len(names)} names for {K} panels")
    cols = min(K, 5 if sharey else 3)  # own scales need room for their tick labels
    rows = math.ceil(K / cols)
    fig, axes = plt.subplots(rows, cols, figsize=((2.8 if sharey else 3.6) * cols, 2.3 * rows + 0.4), dpi=110,
                             squeeze=False, sharex=sharey, sharey=sharey)
    for j in range(rows * cols):
        ax = axes[j // cols][j % cols]
        if j >= K:
            ax.axis("off")
            continue
        xj, yj = _finite_columns(x, series[..., j])
        m, se = mean_se(yj, axis=0)
        ax.plot(xj, m, color="C0", linewidth=1.3)
        ax.fill_between(xj, m - se, m + se, color="C0", alpha=0.25, linewidth=0)
        _episode_lines(ax, episode_starts)
        final = f"{m[-1]:.{digits}f}" if m.size and np.isfinite(m[-1]) else "n/a"
        ax.set_title(f"{names[j]}: {final}", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        if j // cols == rows - 1 or not sharey:
            ax.set_xlabel(xlabel, fontsize=7)
        if j % cols == 0:
            ax.set_ylabel(ylabel, fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


# The student's PPO statistics of ``plot_student_training``, as (metric under info/extras/ppo/, panel
# title): how a stalled student shows, e.g. a Gaussian policy whose entropy keeps falling while the
# clipped fraction and KL per update rise.
STUDENT_PANELS = (("episode_return", "training episode return"), ("episode_length", "training episode length"),
                  ("entropy", "policy entropy"), ("approx_kl", "approx. KL per update"),
                  ("clip_frac", "clipped fraction"), ("grad_norm", "gradient norm"))


def plot_student_training(hist: dict[str, np.ndarray], path: pathlib.Path, *, title: str) -> bool:
    """The student's PPO statistics per budget step over the whole run (every teacher episode, dotted
    lines between them), one panel each with its own scale; False (nothing drawn) when the history
    holds none of them."""
    panels = [(f"info/extras/ppo/{k}", name) for k, name in STUDENT_PANELS if f"info/extras/ppo/{k}" in hist]
    if not panels:
        return False
    stats = np.stack([np.asarray(hist[k], np.float64) for k, _ in panels], axis=-1)  # [S, steps, K]
    episode = np.asarray(hist["episode"])[0]
    plot_panels(np.arange(stats.shape[1]), stats, path, names=[name for _, name in panels], xlabel="budget step",
                ylabel="", sharey=False, digits=3, episode_starts=np.where(np.diff(episode) != 0)[0] + 0.5,
                title=title)
    return True


def plot_parameters(x: np.ndarray, levels: np.ndarray, names: tuple[str, ...], path: pathlib.Path, title: str, *,
                    low: Sequence[float] | None = None, high: Sequence[float] | None = None,
                    episode_starts: Sequence[float] | None = None, xlabel: str = "budget step") -> None:
    """The parameters a teacher generated over the run: ``levels [seeds, steps, L, d]`` (env units).

    One panel per parameter. The line is the mean over seeds of each seed's mean over its L
    generated levels, with a band of ± SE over seeds; the light grey band is the 10-90 % range of
    all generated levels of the step (how diverse the teacher's levels are). ``low``/``high`` draw
    the parameter box as dotted lines; ``episode_starts`` marks teacher-episode boundaries.
    """
    plt = _pyplot()
    levels = np.asarray(levels, np.float64)
    if levels.ndim != 4:
        raise ValueError(f"plot_parameters: levels must be [seeds, steps, L, d], got shape {levels.shape}")
    S, T, L, d = levels.shape
    if len(names) != d:
        raise ValueError(f"plot_parameters: {len(names)} names for {d} parameters")
    x = np.asarray(x, np.float64)
    if x.shape != (T,):
        raise ValueError(f"plot_parameters: x has shape {x.shape}, expected ({T},)")
    cols = min(d, 4)
    rows = math.ceil(d / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 2.7 * rows + 0.4), dpi=110, squeeze=False, sharex=True)
    per_seed = np.nanmean(levels, axis=2)  # [S, T, d]
    pooled = levels.transpose(1, 0, 2, 3).reshape(T, S * L, d)  # [T, S*L, d]
    for j in range(rows * cols):
        ax = axes[j // cols][j % cols]
        if j >= d:
            ax.axis("off")
            continue
        v = pooled[..., j]
        ax.fill_between(x, np.nanpercentile(v, 10, axis=1), np.nanpercentile(v, 90, axis=1), color="grey",
                        alpha=0.18, linewidth=0, label="10-90 % of levels")
        m, se = mean_se(per_seed[..., j], axis=0)
        ax.plot(x, m, color="C0", linewidth=1.3, label=f"mean (n={S} seeds)")
        ax.fill_between(x, m - se, m + se, color="C0", alpha=0.3, linewidth=0, label="± SE over seeds")
        for bound in (low, high):
            if bound is not None:
                ax.axhline(float(bound[j]), color="black", linewidth=0.7, linestyle=":")
        _episode_lines(ax, episode_starts)
        ax.set_title(names[j], fontsize=9)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        if j // cols == rows - 1 or j + cols >= d:
            ax.set_xlabel(xlabel, fontsize=8)
        if j == 0:
            ax.legend(fontsize=6, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_eval_vector(x: np.ndarray, vectors: np.ndarray, path: pathlib.Path, *, title: str,
                     level_labels: Sequence[str] | None = None, episode_starts: Sequence[float] | None = None,
                     xlabel: str = "budget step") -> None:
    """SHED/h-MDP's performance vector (the teacher's state: mean return per evaluation level) over time.

    ``vectors [seeds, steps, m]`` (``hist["info/extras/teacher_state"]``). Top: heatmap of the mean
    over seeds, one row per evaluation level. Bottom: the mean over the m levels, ± SE over seeds.
    """
    plt = _pyplot()
    vectors = np.asarray(vectors, np.float64)
    if vectors.ndim != 3:
        raise ValueError(f"plot_eval_vector: vectors must be [seeds, steps, m], got shape {vectors.shape}")
    S, T, m = vectors.shape
    x = np.asarray(x, np.float64)
    if x.shape != (T,):
        raise ValueError(f"plot_eval_vector: x has shape {x.shape}, expected ({T},)")
    labels = list(level_labels) if level_labels is not None else [f"eval {i}" for i in range(m)]
    if len(labels) != m:
        raise ValueError(f"plot_eval_vector: {len(labels)} labels for {m} evaluation levels")
    mean = np.nanmean(vectors, axis=0)  # [T, m]
    fig, (ax_h, ax_l) = plt.subplots(2, 1, figsize=(8, 2.2 + 0.22 * m + 2.4), dpi=110, sharex=True,
                                     gridspec_kw={"height_ratios": [max(m * 0.22, 1.5), 2.0]})
    if T > 1:
        half = np.diff(x).mean() / 2
        extent = (x[0] - half, x[-1] + half, m - 0.5, -0.5)
    else:
        extent = (x[0] - 0.5, x[0] + 0.5, m - 0.5, -0.5)
    im = ax_h.imshow(mean.T, aspect="auto", cmap="viridis", extent=extent, interpolation="nearest")
    ax_h.set_yticks(range(m))
    ax_h.set_yticklabels(labels, fontsize=6)
    cbar = fig.colorbar(im, ax=[ax_h, ax_l], pad=0.01, fraction=0.04)  # both panels keep one width
    cbar.ax.tick_params(labelsize=7)
    cbar.set_label("mean return", fontsize=7)
    ax_h.set_title(title, fontsize=10)
    avg, se = mean_se(np.nanmean(vectors, axis=2), axis=0)
    ax_l.plot(x, avg, color="C1", linewidth=1.3, label=f"mean over {m} eval levels (n={S} seeds)")
    ax_l.fill_between(x, avg - se, avg + se, color="C1", alpha=0.3, linewidth=0)
    _episode_lines(ax_l, episode_starts)
    _episode_lines(ax_h, episode_starts)
    ax_l.set_xlabel(xlabel)
    ax_l.set_ylabel("mean return", fontsize=8)
    ax_l.grid(alpha=0.3)
    ax_l.legend(fontsize=7)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def plot_level_bars(levels: Sequence[str], bars: dict[str, tuple[Sequence[float], Sequence[float]]],
                    path: pathlib.Path, *, title: str, ylabel: str = "return", threshold: float | None = None,
                    references: dict[str, Sequence[float]] | None = None) -> None:
    """Grouped bars: for each level, one bar per method with its SE as an error bar.

    ``bars[label] = (mean [L], se [L])`` in the order of ``levels``. ``threshold`` draws a dashed
    line (e.g. the solved return); ``references[label] = values [L]`` draws one marker per level and
    reference (e.g. a paper's table), so published numbers sit next to ours without being bars.
    """
    plt = _pyplot()
    L = len(levels)
    if not bars:
        raise ValueError("plot_level_bars: no bars to draw")
    for label, (mean, se) in bars.items():
        if len(mean) != L or len(se) != L:
            raise ValueError(f"plot_level_bars: {label!r} has {len(mean)} means and {len(se)} SEs for {L} levels")
    for label, values in (references or {}).items():
        if len(values) != L:
            raise ValueError(f"plot_level_bars: reference {label!r} has {len(values)} values for {L} levels")
    n = len(bars)
    width = 0.8 / n
    x = np.arange(L, dtype=np.float64)
    fig, ax = plt.subplots(figsize=(max(7.0, 1.3 * L + 2.0), 4.2), dpi=120)
    for i, (label, (mean, se)) in enumerate(bars.items()):
        ax.bar(x - 0.4 + width * (i + 0.5), np.asarray(mean, np.float64), width, yerr=np.asarray(se, np.float64),
               capsize=2, label=label, alpha=0.85)
    markers = "D^sv<>po"
    for j, (label, values) in enumerate((references or {}).items()):
        ax.scatter(x, np.asarray(values, np.float64), marker=markers[j % len(markers)], s=28, color="black",
                   facecolors="none" if j % 2 else "black", zorder=3, label=label)
    if threshold is not None:
        ax.axhline(threshold, linestyle="--", linewidth=1, color="grey")
        ax.annotate(f"solved > {threshold:g}", (x[-1] + 0.4, threshold), fontsize=7, color="grey", ha="right",
                    va="bottom")
    ax.axhline(0.0, color="black", linewidth=0.6)
    ax.set_xticks(x)
    ax.set_xticklabels(levels, fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
