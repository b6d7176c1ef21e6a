"""Range checks of dynamic hyperparameters: one rule for the student's and the teacher's pytrees."""
from __future__ import annotations

import numpy as np


def check_ranges(obj, ranges: dict) -> None:
    """ValueError naming ``<Class>.<field>`` for a concrete value outside ``ranges[field]``.

    ``ranges``: field -> (low, high, low_inclusive, high_inclusive). Traced values are skipped
    (nothing to check at trace time).
    """
    for name, (lo, hi, lo_inc, hi_inc) in ranges.items():
        value = getattr(obj, name)
        try:
            v = np.asarray(value, dtype=np.float64)
        except Exception:  # a tracer
            continue
        ok = (v >= lo if lo_inc else v > lo) & (v <= hi if hi_inc else v < hi) & np.isfinite(v)
        if not np.all(ok):
            interval = f"{'[' if lo_inc else '('}{lo}, {hi}{']' if hi_inc else ')'}"
            raise ValueError(f"{type(obj).__name__}.{name} must be a finite value in {interval}, got {value}")
