"""How often the 2-D walker's time-of-impact search finds a candidate, per search and per batch-step.

A step runs Box2D's time of impact (``toi.earliest_impact`` per leg polygon, ``toi_events`` times)
for every walker, and after each search the manifolds at the impact pose, the position and velocity
passes: about half of a step's kernel launches at 200 walkers (docs/bipedal.md, "Where the launches
are"). Skipping all of it in a step where no walker of the batch has a candidate (the search's time
below 1) would pay only if such steps were common. This counts them: it wraps ``toi.earliest_impact``
with a host callback that records each search's "candidate" flags over the batch, per place in the
program (the step's search and the auto-reset's: both run for every walker), runs batches as
``experiments.manifold_census`` does (random actions on FULL levels; Gymnasium's scripted gait on the
flat and Hardcore levels), and reports the share of searches with a candidate and the share of
batch-steps in which any search of the batch had one.

    python -m experiments.toi_census --worlds 200 --steps 100 --out FILE.json

The same count in a teacher's evaluation of a saved run's students: ``experiments/eval_length.py RUN_DIR
--toi-census`` (which imports ``record_searches`` and ``summarise`` from here; this module imports
nothing of the project at its top, so that it also runs beside a carried run's own, older sources).

Measurement only (CPU is fine: the search's arithmetic is the GPU's); the callback costs time, not results.
"""
from __future__ import annotations

import argparse
import datetime
import itertools
import json
import platform
import sys

import jax
import jax.numpy as jnp
import numpy as np

_RECORDS: list = []  # (call site, the search's candidate flags over the batch) per search run
_SITES = itertools.count()  # a number per traced call of the search: one per place in the program


def _recording(search):
    def wrapped(*args, **kwargs):
        out = search(*args, **kwargs)
        site = next(_SITES)

        def record(hit):  # under vmap: the whole batch's flags at once (vmap_method="expand_dims")
            _RECORDS.append((site, np.asarray(hit, bool)))
            return np.zeros(np.shape(hit), np.float32)

        zero = jax.pure_callback(record, jax.ShapeDtypeStruct((), jnp.float32), out[0] < 1.0, vmap_method="expand_dims")
        return (out[0] + zero, *out[1:])  # used, so the callback stays in the program; the time is unchanged
    return wrapped


SITE_NAMES = ("first reset", "step", "auto-reset")  # the order in which slots_on traces them


def record_searches() -> list:
    """Wrap ``toi.earliest_impact`` (of the ``envs`` on the path) so that every search run from now on
    appends its (site, candidate flags) to the returned list; a site is a traced call of the search, so
    a program must be traced after this. Clears the list and the site count."""
    global _SITES
    from envs.physics2d import toi
    if not getattr(toi.earliest_impact, "_recording", False):
        toi.earliest_impact = _recording(toi.earliest_impact)
        toi.earliest_impact._recording = True
    _RECORDS.clear()
    _SITES = itertools.count()
    return _RECORDS


def summarise(records: list, names=SITE_NAMES) -> dict:
    """``records``: (site, flags) per search run, each flags array one batch-step's searches at that
    site (walkers x polygons, with any leading batch axes). Per site (named by ``names`` in trace order,
    else "site N"): how many ran, the share of searches with a candidate, the share of batch-steps with
    any, and the fewest candidates in one batch-step."""
    out = {}
    for site in sorted({s for s, _ in records}):
        runs = [np.asarray(f, bool) for s, f in records if s == site]
        name = names[site] if site < len(names) else f"site {site}"
        out[name] = {"batch_steps": len(runs), "searches_per_batch_step": int(runs[0].size),
                     "candidate_share": round(float(np.mean([f.mean() for f in runs])), 4),
                     "batch_steps_with_any": round(float(np.mean([f.any() for f in runs])), 4),
                     "fewest_candidates_in_a_batch_step": int(min(f.sum() for f in runs))}
    return out


def census(env, mode: str, worlds: int, steps: int, seed: int) -> dict:
    """``summarise`` of one batch of ``worlds`` walkers run for ``steps`` steps in ``mode``."""
    from experiments import manifold_census
    records = record_searches()
    manifold_census.slots_on(env, mode, worlds, steps, seed)
    return summarise(records)


def main(argv=None) -> int:
    import envs
    from experiments import manifold_census
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--worlds", type=int, default=200)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--modes", default=",".join(manifold_census.MODES),
                   help="comma-separated, of " + ", ".join(manifold_census.MODES))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    modes = [m for m in a.modes.split(",") if m]
    bad = [m for m in modes if m not in manifold_census.MODES]
    if bad or a.worlds < 1 or a.steps < 1:
        p.error(f"modes must be among {', '.join(manifold_census.MODES)} (got {', '.join(bad)})" if bad
                else "worlds and steps must be >= 1")
    env = envs.make("bipedal")
    rec = {"device": f"{jax.devices()[0].device_kind} ({platform.processor() or platform.machine()})",
           "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
           "command": "python -m experiments.toi_census " + " ".join(sys.argv[1:] if argv is None else argv),
           "worlds": a.worlds, "steps": a.steps, "modes": {}}
    for mode in modes:
        rec["modes"][mode] = r = census(env, mode, a.worlds, a.steps, a.seed)
        for site, c in r.items():
            print(f"{mode}, {site}: {c['candidate_share']:.1%} of the searches found a candidate; "
                  f"{c['batch_steps_with_any']:.1%} of {c['batch_steps']} batch-steps of {c['searches_per_batch_step']} "
                  f"searches had one (at least {c['fewest_candidates_in_a_batch_step']} in each)", flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump(rec, f, indent=1)
            f.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
