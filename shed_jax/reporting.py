"""Host-side reporting of a run: per-step records, mean and standard error over seeds, plots.

Everything here runs between compiled chunks, on numpy arrays that came back from the device.
Metrics arrive as a pytree whose leaves have shape ``[seeds, steps, ...]``.
"""
from __future__ import annotations

import json
import math
import pathlib
from typing import Any, Iterable

import numpy as np


def mean_se(x: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error (sd / sqrt(n), ddof 1) over ``axis``, ignoring NaN.

    With a single sample the standard error is 0 (not NaN), so plots still draw a line.
    """
    x = np.asarray(x, np.float64)
    n = np.sum(~np.isnan(x), axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nanmean(x, axis=axis) if x.size else np.zeros(0)
        if x.shape[axis] > 1:
            sd = np.nanstd(x, axis=axis, ddof=1)
            se = np.where(n > 1, sd / np.sqrt(np.maximum(n, 1)), 0.0)
        else:
            se = np.zeros_like(mean)
    return mean, se


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


def _jsonable(x: np.ndarray):
    x = np.asarray(x)
    if x.ndim == 0:
        v = x.item()
        if isinstance(v, float) and not math.isfinite(v):
            return None
        return v
    return [_jsonable(v) for v in x]


def step_records(metrics: dict[str, np.ndarray], seed_ids: Iterable[int]) -> list[dict]:
    """One JSON-able record per (seed, step) from flattened ``[seeds, steps, ...]`` arrays."""
    seed_ids = list(seed_ids)
    records = []
    num_steps = next(iter(metrics.values())).shape[1]
    for t in range(num_steps):
        for i, seed in enumerate(seed_ids):
            rec = {"seed": seed}
            for k, v in metrics.items():
                rec[k] = _jsonable(v[i, t])
            records.append(rec)
    return records


def append_jsonl(path: pathlib.Path, records: list[dict]) -> None:
    with open(path, "a") as f:
        for r in records:
            f.write(json.dumps(r) + "\n")


def read_jsonl(path: pathlib.Path) -> list[dict]:
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def plot_curves(curves: dict[str, tuple[np.ndarray, np.ndarray]], path: pathlib.Path, *, xlabel: str,
                ylabel: str, title: str, references: dict[str, float] | None = None) -> None:
    """Mean +- SE curves. ``curves[label] = (x [steps], y [seeds, steps])``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=120)
    for label, (x, y) in curves.items():
        m, se = mean_se(np.asarray(y), axis=0)
        n = np.asarray(y).shape[0]
        line, = ax.plot(x, m, label=f"{label} (n={n})")
        ax.fill_between(x, m - se, m + se, color=line.get_color(), alpha=0.25, linewidth=0)
    for label, value in (references or {}).items():
        ax.axhline(value, linestyle="--", linewidth=1, color="grey")
        ax.annotate(label, (ax.get_xlim()[0], value), fontsize=7, color="grey", va="bottom")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_parameters(x: np.ndarray, levels: np.ndarray, names: tuple[str, ...], path: pathlib.Path, title: str) -> None:
    """The parameters a teacher generated over the run: ``levels [seeds, steps, L, d]``.

    One panel per parameter: the mean over seeds and levels per step, with the 10-90 % band.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = np.asarray(levels, np.float64)
    d = levels.shape[-1]
    cols = min(d, 4)
    rows = math.ceil(d / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), dpi=110, squeeze=False)
    flat = levels.transpose(1, 0, 2, 3).reshape(levels.shape[1], -1, d)  # [steps, seeds*L, d]
    for j in range(rows * cols):
        ax = axes[j // cols][j % cols]
        if j >= d:
            ax.axis("off")
            continue
        v = flat[..., j]
        ax.plot(x, v.mean(axis=1), color="C0")
        ax.fill_between(x, np.percentile(v, 10, axis=1), np.percentile(v, 90, axis=1), color="C0", alpha=0.25)
        ax.set_title(names[j], fontsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
