"""The learning teacher's runs (issue #26): compact summaries of sweep directories, and docs/results/teacher.json.

    # where the runs are (the device machine): per-episode numbers of every <method>/<point>/ of each sweep
    python -m experiments.teacher_runs summarise SWEEP_DIR [SWEEP_DIR ...] --out compact.json
    # here: merge compact files (seeds of one method/point from several runs pool) into the record
    python -m experiments.teacher_runs record compact.json [...] --out docs/results/teacher.json \
        --device "one NVIDIA H200" --command "python -m shed_jax sweep ..."

Per run it keeps, for each seed, the test return of every tested teacher episode (the test set runs
at the episode's last budget step) and, per teacher episode, the means over steps of the diagnostics
``at_bound_fraction``, ``td_error_heldout``, ``state_noise_sd``, ``box_width``, ``action_abs_mean``
and the teacher reward. The record's ``final_*`` is the last tested episode, ``episode0_*`` episode 0
(the untrained teacher), ``paired_gain_*`` their difference per seed, and ``at_bound_fraction`` the
mean over the last teacher episode's steps and seeds. Needs only numpy.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import pathlib

import numpy as np

DIAGNOSTICS = ("at_bound_fraction", "td_error_heldout", "state_noise_sd", "box_width", "action_abs_mean")


def _num(v):
    if v is None:
        return math.nan
    a = np.asarray(v, dtype=np.float64)
    return float(np.nanmean(a)) if a.size else math.nan


def summarise_point(point_dir: pathlib.Path) -> dict:
    """One ``<method>/<point>/`` directory -> per-seed test returns by episode and per-episode diagnostics."""
    summary = json.loads((point_dir / "summary.json").read_text())
    tests: dict[int, dict[int, float]] = {}
    diag: dict[str, dict[int, list]] = {k: {} for k in DIAGNOSTICS + ("teacher_reward",)}
    with open(point_dir / "metrics.jsonl") as f:
        for line in f:
            row = json.loads(line)
            seed, ep = int(row["seed"]), int(row["episode"])
            t = row.get("test_return")
            if t is not None and not (isinstance(t, float) and math.isnan(t)):
                tests.setdefault(seed, {})[ep] = float(t)
            for k in DIAGNOSTICS:
                key = f"info/extras/{k}"
                if key in row:
                    diag[k].setdefault(ep, []).append(_num(row[key]))
            diag["teacher_reward"].setdefault(ep, []).append(_num(row.get("info/teacher_reward")))
    per_episode = {k: {str(ep): float(np.nanmean(v)) if np.isfinite(v).any() else None for ep, v in sorted(d.items())}
                   for k, d in diag.items() if d}
    return {
        "method": summary["method"], "point": summary["point"], "values": summary.get("values", {}),
        "seeds": summary["seeds"], "wall_time_s": summary.get("wall_time_s"),
        "final_per_seed": summary["final_test_return_per_seed"],
        "test_by_seed_episode": {str(s): {str(e): v for e, v in sorted(d.items())} for s, d in sorted(tests.items())},
        "diagnostics_by_episode": per_episode,
    }


def summarise(dirs, out):
    runs = []
    for d in dirs:
        d = pathlib.Path(d)
        sweep = d / "sweep.json"  # a sweep's group names its --set values, e.g. hmdp-x[twin_critics=true]
        groups = {row["dir"]: row.get("group", row["method"])
                  for row in json.loads(sweep.read_text())["rows"]} if sweep.exists() else {}
        for summ in sorted(d.glob("*/*/summary.json")):
            run = summarise_point(summ.parent)
            run["group"] = groups.get(str(summ.parent.relative_to(d)), run["method"])
            runs.append({"sweep": str(d), **run})
    pathlib.Path(out).write_text(json.dumps(runs, indent=1))
    print(f"{len(runs)} runs -> {out}")


def _mean_se(x):
    x = np.asarray(x, np.float64)
    return float(x.mean()), (float(x.std(ddof=1) / math.sqrt(len(x))) if len(x) > 1 else math.nan)


def aggregate(runs: list[dict]) -> dict:
    """Pool the seeds of runs with the same (method, point) -> the record's entry per name."""
    groups: dict[str, list[dict]] = {}
    for r in runs:
        group = r.get("group", r["method"])  # runs summarised before groups were kept: the method
        name = group if r["point"] == "default" else f"{group}[{r['point']}]"
        groups.setdefault(name, []).append(r)
    out = {}
    for name, rs in groups.items():
        finals, ep0s, gains, bounds = [], [], [], []
        for r in rs:
            for seed, by_ep in r["test_by_seed_episode"].items():
                eps = sorted(by_ep, key=int)
                finals.append(by_ep[eps[-1]])
                if "0" in by_ep:
                    ep0s.append(by_ep["0"])
                    gains.append(by_ep[eps[-1]] - by_ep["0"])
            ab = r["diagnostics_by_episode"].get("at_bound_fraction", {})
            if ab:
                bounds.append(ab[max(ab, key=int)])
        last_eps = {max(map(int, by_ep)) for r in rs for by_ep in r["test_by_seed_episode"].values()}
        fm, fs = _mean_se(finals)
        e0m, e0s = _mean_se(ep0s)
        gm, gs = _mean_se(gains)
        out[name] = {
            "seeds": len(finals), "final_episode": sorted(last_eps), "final_mean": fm, "final_se": fs,
            "episode0_mean": e0m, "episode0_se": e0s, "paired_gain_mean": gm, "paired_gain_se": gs,
            "at_bound_fraction": float(np.mean(bounds)) if bounds else None,
            "runs": [{k: r.get(k) for k in ("sweep", "point", "seeds", "wall_time_s")} for r in rs],
            "diagnostics_by_episode": rs[0]["diagnostics_by_episode"] if len(rs) == 1 else
            {k: {ep: float(np.nanmean([r["diagnostics_by_episode"][k][ep] for r in rs
                                       if r["diagnostics_by_episode"].get(k, {}).get(ep) is not None] or [math.nan]))
                 for ep in rs[0]["diagnostics_by_episode"][k]} for k in rs[0]["diagnostics_by_episode"]},
        }
    return out


def _finite(o):
    """NaN/inf -> None, recursively (strict JSON)."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list):
        return [_finite(v) for v in o]
    return None if isinstance(o, float) and not math.isfinite(o) else o


def record(files, out, device, command, date, notes=()):
    runs = [r for f in files for r in json.loads(pathlib.Path(f).read_text())]
    rec = {"device": device, "date": date or datetime.date.today().isoformat(), "command": command,
           "notes": list(notes), "lander": aggregate(runs)}
    pathlib.Path(out).write_text(json.dumps(_finite(rec), indent=1, allow_nan=False) + "\n")
    for name, e in rec["lander"].items():
        print(f"{name}: {e['seeds']} seeds, final {e['final_mean']:.1f} ± {e['final_se']:.1f}, episode 0 "
              f"{e['episode0_mean']:.1f} ± {e['episode0_se']:.1f}, paired gain {e['paired_gain_mean']:.1f} ± "
              f"{e['paired_gain_se']:.1f}, at a bound {e['at_bound_fraction']}, final episodes {e['final_episode']}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("summarise")
    s.add_argument("dirs", nargs="+")
    s.add_argument("--out", required=True)
    r = sub.add_parser("record")
    r.add_argument("files", nargs="+")
    r.add_argument("--out", default="docs/results/teacher.json")
    r.add_argument("--device", required=True)
    r.add_argument("--command", required=True)
    r.add_argument("--date", default=None)
    r.add_argument("--note", action="append", default=[], help="a line for the record's notes (repeatable)")
    a = p.parse_args(argv)
    if a.cmd == "summarise":
        summarise(a.dirs, a.out)
    else:
        record(a.files, a.out, a.device, a.command, a.date, a.note)


if __name__ == "__main__":
    main()
