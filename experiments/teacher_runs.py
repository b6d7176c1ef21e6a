"""The learning teacher's runs (issue #26): compact summaries of sweep and run directories, and docs/results/teacher.json.

    # where the runs are (the device machine): per-episode numbers of every <method>/<point>/ of each
    # sweep, or of the directory of one `shed_jax run` (labelled by what it sets apart from its preset)
    python -m experiments.teacher_runs summarise DIR [DIR ...] --out compact.json
    # here: merge compact files (seeds of one method/point from several runs pool) into the record
    python -m experiments.teacher_runs record compact.json [...] --out docs/results/teacher.json \
        --device "one NVIDIA H200" --command "python -m shed_jax sweep ..." \
        [--paper-csv docs/results/lander_shed_hmdp_10seeds_2026-11-23.csv] [--dr docs/results/baselines.json]
    # the walker's runs: their own record (default docs/results/teacher_walker.json), DR from the
    # baselines record of the same student
    python -m experiments.teacher_runs record compact.json --env walker \
        --dr docs/results/walker_baselines_per_rollout_h100_2026-11-28.json --device ... --command ...

``--paper-csv`` adds the paper teachers (SHED, h-MDP) from the long-form CSV their 10-seed runs were
exported to (a row per seed, teacher episode and budget step, tested episodes only): each becomes a
compact run as ``summarise`` would make it (its at-bound fraction was not logged then: null).
``--dr`` adds domain randomisation's final test return from the baselines record (DR has no
teacher episodes: its episode-0 and gain fields are null). ``--control FILE`` adds the two sets of a
``paired`` file (below) the same way, except a set made of the record's own runs (a teacher paired
against its control), which the record has already. The record's ``targets`` says, per teacher, whether each of
issue #26's targets is shown, against the entry ``--dr-reference`` names (:func:`targets`).

    # the mean box of the levels a teacher generated from teacher episode 30 on: a fixed-box DR control
    python -m experiments.teacher_runs late-box SWEEP_DIR/hmdp-x/default [...] --from-episode 30

    # two sets of sweeps with one point each, or of run directories (e.g. DR on a teacher's late box,
    # and on Θ): final test returns pooled per set, and their difference paired by (root seed, seed index)
    python -m experiments.teacher_runs paired BOX_SWEEP [...] --vs FULL_SWEEP [...] --out control.json \
        [--plot control.png --labels box Θ]

    # a figure: test return (mean ± SE over seeds) and diagnostics by teacher episode, one line per run
    python -m experiments.teacher_runs plot compact.json [...] --only NAME [--only NAME] --out fig.png

Runs with ``--set reward_noise_check=true`` also get ``reward_noise``: the noise SD of the teacher
reward with common random numbers (one key for s and s') and with two keys, beside the reward's own
SD, by budget step of the episode (:func:`reward_noise`).

Per run it keeps, for each seed, the test return of every tested teacher episode (the test set runs
at the episode's last budget step) and, per teacher episode, the means over steps of the diagnostics
``at_bound_fraction``, ``td_error_heldout``, ``state_noise_sd``, ``box_width``, ``action_abs_mean``
and the teacher reward. The record's ``final_*`` is the last tested episode, ``episode0_*`` episode 0
(the untrained teacher), ``paired_gain_*`` their difference per seed, and ``at_bound_fraction`` the
mean over the last teacher episode's steps and seeds. ``late_*`` and ``paired_late_gain_*`` use, per
seed, the mean of the last ``LATE`` tested episodes instead of the last one alone: one seed's test
return moves by 10-20 between tested episodes, so a single endpoint swings (null where a seed was
tested fewer than ``LATE`` + 1 times). Needs only numpy.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import pathlib

import numpy as np

LATE = 3  # the late endpoint: the mean of a seed's last LATE tested episodes (module doc)
DIAGNOSTICS = ("at_bound_fraction", "td_error_heldout", "state_noise_sd", "box_width", "action_abs_mean")


def _num(v):
    if v is None:
        return math.nan
    a = np.asarray(v, dtype=np.float64)
    return float(np.nanmean(a)) if a.size else math.nan


CHECKS = ("reward_again", "reward_crossed", "reward_crossed_back")
#: budget-step buckets of a teacher episode for the reward noise: the first step (the fresh student's
#: big change), the next four, and the rest (the student near its plateau)
NOISE_BUCKETS = (("t0", 0, 1), ("t1-4", 1, 5), ("t5+", 5, math.inf))


def reward_noise(rows: list[tuple[int, float, float, float, float]]) -> dict:
    """The teacher reward's noise from ``reward_noise_check`` rows (step in episode, r, again, crossed,
    crossed back), per bucket of ``NOISE_BUCKETS`` and over all steps.

    r and ``again`` reward the same two students with one key each for s and s' (common random
    numbers), ``crossed`` and ``crossed_back`` with different keys for s and s'. Two independent draws
    x, y of one quantity give its SD as sqrt(mean((x - y)^2) / 2): ``paired_noise_sd`` from (r, again),
    ``crossed_noise_sd`` from (crossed, crossed_back). ``reward_sd`` is the SD of r over the rows
    (signal and noise), ``reward_mean`` its mean, ``n`` the rows."""
    a = np.asarray(rows, np.float64).reshape(-1, 5)
    a = a[np.all(np.isfinite(a[:, 1:]), axis=1)]
    out = {}
    for name, lo, hi in NOISE_BUCKETS + (("all", 0, math.inf),):
        b = a[(a[:, 0] >= lo) & (a[:, 0] < hi)]
        if len(b) < 2:
            continue
        out[name] = {"n": int(len(b)), "reward_mean": float(b[:, 1].mean()), "reward_sd": float(b[:, 1].std(ddof=1)),
                     "paired_noise_sd": float(np.sqrt(np.mean((b[:, 1] - b[:, 2]) ** 2) / 2)),
                     "crossed_noise_sd": float(np.sqrt(np.mean((b[:, 3] - b[:, 4]) ** 2) / 2))}
    return out


def run_settings(config: dict) -> list[str] | None:
    """What one ``shed_jax run`` (its config.json) sets apart from today's preset, as ``key=value``
    strings in the form of a sweep's ``--set`` values (``episodes=3``, ``level_switch=episode``);
    None where this version no longer has the run's preset or method. A field the run's config lacks
    and today's preset holds at its declared default was added after the run, with the default that
    keeps the earlier behaviour: no setting (runs carried across sessions keep their own sources)."""
    from shed_jax.checkpoint import MISSING, config_differences
    from shed_jax.presets import build_experiment

    exp = config["experiment"]
    try:
        default = build_experiment(exp["env"], exp["method"], exp["preset"])
    except (KeyError, ValueError, TypeError):
        return None
    short = {"loop.num_episodes": "episodes"}
    out = []
    for key, saved, now in config_differences({"e": exp}, {"e": default.to_dict()}, ["e"]):
        key = key.removeprefix("e.")
        if saved == MISSING and _is_field_default(default, key, now):
            continue  # a field added after the run, at the default that keeps the earlier behaviour
        out.append(f"{short.get(key, key.removeprefix('method_config.'))}={saved}")
    return out


def _is_field_default(obj, dotted: str, value) -> bool:
    """Whether ``value`` (JSON-read) is the declared default of the dataclass field at ``dotted`` under
    ``obj`` (``ppo.log_std_min`` of an Experiment); False where the path is not a dataclass field."""
    import dataclasses

    from shed_jax.checkpoint import jsonable

    *parents, name = dotted.split(".")
    for part in parents:
        obj = getattr(obj, part, None)
    fields = {f.name: f for f in dataclasses.fields(obj)} if dataclasses.is_dataclass(obj) else {}
    field = fields.get(name)
    if field is None:
        return False
    if field.default is not dataclasses.MISSING:
        declared = field.default
    elif field.default_factory is not dataclasses.MISSING:
        declared = field.default_factory()
    else:
        return False
    return jsonable(declared) == jsonable(value)  # either form of a non-finite float (-Infinity or "-inf")


def run_group(config: dict) -> str:
    """The label of one ``shed_jax run``: the method with :func:`run_settings`, e.g.
    ``hmdp-x[episodes=3]``, as a sweep's group names its ``--set`` values, so runs of other lengths
    or settings never pool with the preset's."""
    exp = config["experiment"]
    parts = run_settings(config)
    if parts is None:
        return f"{exp['method']}[preset={exp.get('preset')}?]"
    return f"{exp['method']}[{','.join(parts)}]" if parts else exp["method"]


def summarise_point(point_dir: pathlib.Path) -> dict:
    """One run directory -> per-seed test returns by episode and per-episode diagnostics: a sweep's
    ``<method>/<point>/``, or the directory of one ``shed_jax run`` (grouped by :func:`run_group`).

    A run stopped by ``--time-limit`` has no summary.json: it is summarised from config.json and its
    metrics so far, with ``"stopped": true`` and no final returns; its last tested episode stands as final.
    """
    config = json.loads((point_dir / "config.json").read_text()) if (point_dir / "config.json").exists() else {}
    one_run = "sweep_point" not in config and "experiment" in config  # the directory of one ``shed_jax run``
    if (point_dir / "summary.json").exists():
        summary = json.loads((point_dir / "summary.json").read_text())
    elif "sweep_point" in config:  # a sweep's point
        point = config["sweep_point"]
        summary = {"method": point_dir.parent.name, "point": point["name"], "values": point["values"],
                   "seeds": config["seeds"], "final_test_return_per_seed": None, "stopped": True,
                   "group": point.get("group", point_dir.parent.name)}  # no sweep.json row names it
    elif one_run:
        summary = {"method": config["experiment"]["method"], "point": "default", "seeds": config["seeds"],
                   "final_test_return_per_seed": None, "stopped": True}
    else:
        raise SystemExit(f"summarise: {point_dir} has neither summary.json nor a run's config.json")
    # a run's label comes from its config; a stopped sweep point's from its config's sweep point (a
    # finished point's from its sweep.json row, in summarise)
    group = run_group(config) if one_run else summary.get("group") if summary.get("stopped") else None
    tests: dict[int, dict[int, float]] = {}
    diag: dict[str, dict[int, list]] = {k: {} for k in DIAGNOSTICS + ("teacher_reward",)}
    checks = []
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
            if row.get(f"info/extras/{CHECKS[0]}") is not None:
                checks.append((row["step_in_episode"], _num(row.get("info/teacher_reward")),
                               *(_num(row.get(f"info/extras/{k}")) for k in CHECKS)))
    per_episode = {k: {str(ep): float(np.nanmean(v)) if np.isfinite(v).any() else None for ep, v in sorted(d.items())}
                   for k, d in diag.items() if d}
    return {
        "method": summary["method"], "point": summary.get("point", "default"), "values": summary.get("values", {}),
        "env": summary.get("env", config.get("experiment", {}).get("env")),
        "seeds": summary["seeds"], "wall_time_s": summary.get("wall_time_s"),
        "final_per_seed": summary["final_test_return_per_seed"],
        "test_by_seed_episode": {str(s): {str(e): v for e, v in sorted(d.items())} for s, d in sorted(tests.items())},
        "diagnostics_by_episode": per_episode,
        **({"reward_noise": reward_noise(checks)} if checks else {}),
        **({"stopped": True} if summary.get("stopped") else {}),
        **({"group": group} if group else {}),
    }


def _with_episodes(group: str, episodes) -> str:
    """A sweep's group label, with ``episodes=N`` added when the sweep was given --episodes, so runs of
    other lengths are never pooled with full ones: 'shed-x' -> 'shed-x[episodes=20]',
    'shed-x[a=1]' -> 'shed-x[a=1,episodes=20]'."""
    if episodes is None:
        return group
    return f"{group[:-1]},episodes={episodes}]" if group.endswith("]") else f"{group}[episodes={episodes}]"


def _point_dirs(d: pathlib.Path) -> list[pathlib.Path]:
    """The run directories in ``d``: a sweep's ``<method>/<point>/``, or ``d`` itself when it is the
    directory of one ``shed_jax run`` (metrics.jsonl at its top)."""
    if (d / "metrics.jsonl").exists() and not (d / "sweep.json").exists():
        return [d]
    return [m.parent for m in sorted(d.glob("*/*/metrics.jsonl"))]


def summarise(dirs, out):
    runs = []
    for d in dirs:
        d = pathlib.Path(d)
        sweep = d / "sweep.json"  # a sweep's group names its --set values, e.g. hmdp-x[twin_critics=true]
        groups = {row["dir"]: row.get("group", row["method"])
                  for row in json.loads(sweep.read_text())["rows"]} if sweep.exists() else {}
        args = d / "sweep_args.json"
        episodes = json.loads(args.read_text()).get("episodes") if args.exists() else None
        found = _point_dirs(d)
        if not found:
            raise SystemExit(f"summarise: {d} holds no run (give a sweep directory or a `shed_jax run` directory "
                             "with metrics.jsonl)")
        for point_dir in found:
            try:
                run = summarise_point(point_dir)
            except (OSError, KeyError, ValueError) as err:
                raise SystemExit(f"summarise: {point_dir} is not a readable run ({type(err).__name__}: {err})") from None
            group = groups.get(str(point_dir.relative_to(d)), run.get("group", run["method"]))
            run["group"] = _with_episodes(group, episodes)
            runs.append({"sweep": str(d), **run})
    pathlib.Path(out).write_text(json.dumps(runs, indent=1))
    print(f"{len(runs)} runs -> {out}")


PAPER_NAMES = {"SHED": "shed", "h-MDP": "hmdp"}  # the CSV's method column -> the record's name


def paper_runs(csv_path) -> list[dict]:
    """The paper teachers' CSV -> compact runs: per seed and tested episode, the test return at the episode's
    last budget step; the teacher reward's mean per episode. Rows of other methods (e.g. 'SHED eta=10') are
    left out."""
    import csv
    tests: dict[str, dict[int, dict[int, tuple[int, float]]]] = {}
    reward: dict[str, dict[int, list[float]]] = {}
    envs: dict[str, set] = {}
    with open(csv_path, newline="") as f:
        for row in csv.DictReader(f):
            name = PAPER_NAMES.get(row["method"])
            if name is None or row["test_return"] == "":
                continue
            seed, ep, t = int(row["seed"]), int(row["episode"]), int(row["step_in_episode"])
            by_ep = tests.setdefault(name, {}).setdefault(seed, {})
            if ep not in by_ep or t > by_ep[ep][0]:
                by_ep[ep] = (t, float(row["test_return"]))
            reward.setdefault(name, {}).setdefault(ep, []).append(float(row["teacher_reward"]))
            envs.setdefault(name, set()).add(row.get("env"))
    return [{"sweep": str(csv_path), "method": name, "group": name, "point": "default", "values": {},
             "env": next(iter(envs[name])) if len(envs[name]) == 1 else None,
             "seeds": len(by_seed), "wall_time_s": None,
             "test_by_seed_episode": {str(s): {str(e): v for e, (_, v) in sorted(d.items())}
                                      for s, d in sorted(by_seed.items())},
             "diagnostics_by_episode": {"teacher_reward": {str(e): float(np.mean(v))
                                                           for e, v in sorted(reward[name].items())}}}
            for name, by_seed in tests.items()]


def dr_entry(baselines_path, env: str = "lander") -> dict:
    """DR's entry for ``env`` from a baselines record (``experiments.baselines_record``): its final test
    return (the walker's entries keep it as ``test_set_b``); no teacher, so no episode 0."""
    try:
        dr = json.loads(pathlib.Path(baselines_path).read_text())[env]["dr"]
        mean, se = (dr["final_mean"], dr["final_se"]) if "final_mean" in dr else (dr["test_set_b"]["mean"], dr["test_set_b"]["se"])
    except (OSError, KeyError, ValueError) as err:
        raise SystemExit(f"record: --dr {baselines_path} has no {env} DR entry ({type(err).__name__}: {err})") from None
    return _no_teacher_entry(dr["seeds"], mean, se, baselines_path)


def _no_teacher_entry(seeds, mean, se, source) -> dict:
    """A record entry of a method without teacher episodes (DR): its finals, null teacher fields."""
    return {"seeds": seeds, "final_mean": mean, "final_se": se, "episode0_mean": None, "episode0_se": None,
            "paired_gain_mean": None, "paired_gain_se": None, "at_bound_fraction": None, "source": str(source)}


def _mean_se(x):
    x = np.asarray(x, np.float64)
    return float(x.mean()), (float(x.std(ddof=1) / math.sqrt(len(x))) if len(x) > 1 else math.nan)


def _nanmean(xs) -> float:
    """Mean of the finite values; NaN (no warning) when there are none."""
    x = np.asarray(xs, np.float64)
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else math.nan


def aggregate(runs: list[dict]) -> dict:
    """Pool the seeds of runs with the same (method, point) -> the record's entry per name."""
    groups: dict[str, list[dict]] = {}
    for r in runs:
        group = r.get("group", r["method"])  # runs summarised before groups were kept: the method
        name = group if r["point"] == "default" else f"{group}[{r['point']}]"
        groups.setdefault(name, []).append(r)
    out = {}
    for name, rs in groups.items():
        finals, ep0s, gains, lates, late_gains, bounds = [], [], [], [], [], []
        for r in rs:
            for seed, by_ep in r["test_by_seed_episode"].items():
                eps = sorted(by_ep, key=int)
                finals.append(by_ep[eps[-1]])
                late = float(np.mean([by_ep[e] for e in eps[-LATE:]])) if len(eps) > LATE else None
                if late is not None:
                    lates.append(late)
                if "0" in by_ep:
                    ep0s.append(by_ep["0"])
                    gains.append(by_ep[eps[-1]] - by_ep["0"])
                    if late is not None:
                        late_gains.append(late - by_ep["0"])
            ab = r["diagnostics_by_episode"].get("at_bound_fraction", {})
            if ab:
                bounds.append(ab[max(ab, key=int)])
        last_eps = {max(map(int, by_ep)) for r in rs for by_ep in r["test_by_seed_episode"].values()}
        fm, fs = _mean_se(finals)
        e0m, e0s = _mean_se(ep0s)
        gm, gs = _mean_se(gains)
        lm, ls = _mean_se(lates) if lates else (None, None)
        lgm, lgs = _mean_se(late_gains) if late_gains else (None, None)
        out[name] = {
            "seeds": len(finals), "final_episode": sorted(last_eps), "final_mean": fm, "final_se": fs,
            "episode0_mean": e0m, "episode0_se": e0s, "paired_gain_mean": gm, "paired_gain_se": gs,
            "late_episodes": LATE, "late_mean": lm, "late_se": ls, "paired_late_gain_mean": lgm, "paired_late_gain_se": lgs,
            "at_bound_fraction": float(np.mean(bounds)) if bounds else None,
            "runs": [{k: r.get(k) for k in ("sweep", "point", "seeds", "wall_time_s")}
                     | ({"stopped": True} if r.get("stopped") else {}) for r in rs],
            **({"reward_noise": [r["reward_noise"] for r in rs]} if any("reward_noise" in r for r in rs) else {}),
            "diagnostics_by_episode": rs[0]["diagnostics_by_episode"] if len(rs) == 1 else
            {k: {ep: _nanmean([r["diagnostics_by_episode"][k][ep] for r in rs
                               if r["diagnostics_by_episode"].get(k, {}).get(ep) is not None])
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


def control_entries(path, env: str = "lander", known: dict | None = None) -> dict:
    """A ``paired`` comparison file -> one DR-like entry per set (no teacher: null teacher fields),
    named by the set's group with its seed count, e.g. ``dr[level_switch=episode] (40 seeds)``. A set
    whose sweeps all feed the record's own entries ``known`` (e.g. the teacher a control was paired
    with; matched by sweep directory, not by name) is left out, with a line saying so: the record has
    those runs already, with their teacher fields. A file that compares runs on another environment
    than ``env`` is refused (files written before ``paired`` recorded the environment say none, and
    are taken as they are)."""
    c = json.loads(pathlib.Path(path).read_text())
    if c.get("env") not in (None, env):
        raise SystemExit(f"record: --control {path} compares runs on {c['env']}, the record is on {env}; give --env to match")
    names = {k: f"{' + '.join(sorted({s.get('group') or '?' for s in c[k]['sweeps']}))} ({c[k]['seeds']} seeds)"
             for k in ("a", "b")}
    if names["a"] == names["b"]:  # the same group on both sides: tell them apart by side
        names = {k: f"{n} [{'first' if k == 'a' else 'second'} set of {path}]" for k, n in names.items()}
    own = {os.path.normpath(r["sweep"]) for e in (known or {}).values() for r in e.get("runs") or () if r.get("sweep")}
    out = {}
    for k in ("a", "b"):
        sweeps = {os.path.normpath(s["sweep"]) for s in c[k]["sweeps"] if s.get("sweep")}
        if sweeps and sweeps <= own:
            print(f"record: --control {path}: its {'first' if k == 'a' else 'second'} set ({names[k]}) is "
                  "already in the record from its runs; left out")
            continue
        out[names[k]] = _no_teacher_entry(c[k]["seeds"], c[k]["mean"], c[k]["se"], path)
    return out


TARGET_SE = 2.0  # a difference counts as shown when it exceeds this many standard errors


def _finite_num(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def targets(lander: dict, dr_reference: str = "dr") -> dict:
    """Issue #26's targets, per teacher entry (those with an episode 0): the gain over its own episode 0
    (paired; the late endpoint where it exists, else the last tested episode), the margin over the
    entry ``dr_reference`` (unpaired: the SE of a difference of independent means; none if absent),
    and the fraction of generated parameters at a bound (target: below 0.1). ``*_shown`` is
    margin > TARGET_SE x SE."""
    dr = lander.get(dr_reference)
    out = {"se_multiple": TARGET_SE, "dr_reference": dr_reference if dr else None, "by_method": {}}
    for name, e in lander.items():
        if not _finite_num(e.get("episode0_mean")):  # no teacher (DR entries), or never tested at episode 0
            continue
        late = e.get("paired_late_gain_mean") is not None
        g, gs = (e["paired_late_gain_mean"], e["paired_late_gain_se"]) if late else (e["paired_gain_mean"], e["paired_gain_se"])
        t = {"endpoint": "late" if late else "final", "gain_over_episode0": g, "gain_se": gs,
             "gain_shown": bool(_finite_num(g) and _finite_num(gs) and g > TARGET_SE * gs),
             "at_bound_fraction": e.get("at_bound_fraction"),
             "at_bound_met": None if e.get("at_bound_fraction") is None else bool(e["at_bound_fraction"] < 0.1)}
        vals = (e["late_mean"] if late else e["final_mean"], e["late_se"] if late else e["final_se"],
                dr and dr.get("final_mean"), dr and dr.get("final_se"))
        if dr is not None and all(map(_finite_num, vals)):  # else no margin (e.g. a 1-seed reference: no SE)
            m, se = vals[0] - vals[2], math.hypot(vals[1], vals[3])
            t |= {"margin_over_dr": m, "margin_se": se, "beats_dr_shown": bool(m > TARGET_SE * se)}
        out["by_method"][name] = t
    return out


def record(files, out, device, command, date, notes=(), paper_csv=None, dr=None, controls=(), dr_reference=None,
           env="lander"):
    """Write the record; its entries go under ``env`` (the runs' environment; summaries that name another
    are refused); ``dr_reference`` names the entry ``targets`` compares with (default "dr", if any)."""
    runs = [r for f in files for r in json.loads(pathlib.Path(f).read_text())]
    runs += paper_runs(paper_csv) if paper_csv else []
    others = sorted({r["env"] for r in runs if r.get("env") not in (None, env)})
    if others:
        raise SystemExit(f"record: the runs are on {', '.join(others)}, the record on {env}; give --env to match")
    own = aggregate(runs)
    parts = [{"dr": dr_entry(dr, env)} if dr else {}, *(control_entries(c, env, own) for c in controls), own]
    entries = {}
    for part in parts:
        for k, v in part.items():
            if k in entries:
                raise SystemExit(f"record: two entries named {k!r} (from --dr, --control or the runs); give one of each")
            entries[k] = v
    if dr_reference is not None and dr_reference not in entries:
        raise SystemExit(f"record: --dr-reference {dr_reference!r} is not an entry; entries without a teacher: "
                         + ", ".join(k for k, e in entries.items() if e.get("episode0_mean") is None))
    dr_reference = "dr" if dr_reference is None else dr_reference
    rec = {"device": device, "date": date or datetime.date.today().isoformat(), "command": command,
           "notes": list(notes), "targets": targets(entries, dr_reference), env: entries}
    pathlib.Path(out).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(out).write_text(json.dumps(_finite(rec), indent=1, allow_nan=False) + "\n")
    f1 = lambda x: "-" if x is None else f"{x:.1f}"  # noqa: E731
    for name, e in entries.items():
        print(f"{name}: {e['seeds']} seeds, final {f1(e['final_mean'])} ± {f1(e['final_se'])}, episode 0 "
              f"{f1(e['episode0_mean'])} ± {f1(e['episode0_se'])}, paired gain {f1(e['paired_gain_mean'])} ± "
              f"{f1(e['paired_gain_se'])}, late gain {f1(e.get('paired_late_gain_mean'))} ± {f1(e.get('paired_late_gain_se'))}, at a bound {e['at_bound_fraction']}, final episodes {e.get('final_episode')}")


#: the figure's panels after the test return, each drawn only where some run logged it (the paper
#: teachers log no actor or box diagnostics, the learning teachers all of them)
PLOT_DIAGNOSTICS = (("fraction of level parameters at a bound", "at_bound_fraction"),
                    ("teacher reward", "teacher_reward"), ("critic TD error, held-out", "td_error_heldout"),
                    ("mean |u| of the actor", "action_abs_mean"), ("box width", "box_width"))


def plot_panels(runs: list[dict]) -> list[tuple[str, str | None]]:
    """(title, diagnostic key) per panel: the test return, then each of :data:`PLOT_DIAGNOSTICS`
    that holds a value for some teacher episode of some run."""
    def logged(key):
        return any(v is not None for r in runs for v in r["diagnostics_by_episode"].get(key, {}).values())
    return [("test return", None)] + [(title, key) for title, key in PLOT_DIAGNOSTICS if logged(key)]


def plot_labels(runs: list[dict]) -> list[str]:
    """Each run's group; runs that share one (the same group pooled from several sweeps) add their sweep's folder."""
    groups = [r.get("group", r["method"]) for r in runs]
    return [f"{g} ({pathlib.Path(r['sweep']).name})" if groups.count(g) > 1 else g for g, r in zip(groups, runs)]


def plot(files, out, only=()):
    """Test return (mean ± SE over seeds) and per-episode diagnostics of compact runs, one line per run."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    runs = [r for f in files for r in json.loads(pathlib.Path(f).read_text())]
    runs = [r for r in runs if not only or r.get("group", r["method"]) in only]
    if not runs:
        raise SystemExit(f"plot: no run named {', '.join(only)} in {', '.join(map(str, files))}")
    panels = plot_panels(runs)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4), squeeze=False)
    axes = axes[0]
    for r, label in zip(runs, plot_labels(runs)):
        eps = sorted({int(e) for d in r["test_by_seed_episode"].values() for e in d})
        stats = [_mean_se([d[str(e)] for d in r["test_by_seed_episode"].values() if str(e) in d]) for e in eps]
        m, se = np.array([x[0] for x in stats]), np.nan_to_num(np.array([x[1] for x in stats]))
        (line,) = axes[0].plot(eps, m, marker="o", label=label)
        axes[0].fill_between(eps, m - se, m + se, color=line.get_color(), alpha=0.2)
        for ax, (_, key) in zip(axes[1:], panels[1:]):
            d = r["diagnostics_by_episode"].get(key, {})
            xs = sorted(int(e) for e, v in d.items() if v is not None)
            ax.plot(xs, [d[str(e)] for e in xs], color=line.get_color())
    for ax, (title, key) in zip(axes, panels):
        ax.set_title(title)
        ax.set_xlabel("teacher episode")
        if key == "td_error_heldout":
            ax.set_yscale("log")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="lower center", ncol=min(len(runs), 3), fontsize=8)
    fig.tight_layout(rect=(0, 0.06 * ((len(runs) + 2) // 3) + 0.04, 1, 1))
    fig.savefig(out, dpi=110)
    print(f"{len(runs)} runs -> {out}")


def late_box(point_dirs, from_episode: int) -> dict:
    """The box a teacher drew its levels from late in its runs, for a fixed-box DR control: over every
    budget step of teacher episodes >= ``from_episode`` (every seed, every run), the per-parameter mean
    of that step's lowest and highest generated level (``info/levels``, [n, d]). With n levels drawn
    uniformly in a box, these under-state its width by about 1/(n+1) at each end."""
    lows, highs = [], []
    for d in point_dirs:
        with open(pathlib.Path(d) / "metrics.jsonl") as f:
            for line in f:
                row = json.loads(line)
                if int(row["episode"]) >= from_episode and row.get("info/levels") is not None:
                    levels = np.asarray(row["info/levels"], float)
                    lows.append(levels.min(0))
                    highs.append(levels.max(0))
    if not lows:
        raise SystemExit(f"late-box: no budget step with info/levels at teacher episode >= {from_episode}")
    lo, hi = np.asarray(lows), np.asarray(highs)
    return {"from_episode": from_episode, "steps": len(lo), "low": lo.mean(0).tolist(), "high": hi.mean(0).tolist(),
            "low_sd": lo.std(0).tolist(), "high_sd": hi.std(0).tolist()}


def sweep_env(d: pathlib.Path, point: pathlib.Path) -> str | None:
    """A sweep's environment: its saved arguments, else its point's config; None where neither says."""
    for f, get in ((d / "sweep_args.json", lambda c: c.get("env")),
                   (point / "config.json", lambda c: c.get("experiment", {}).get("env"))):
        if f.is_file():
            return get(json.loads(f.read_text()))
    return None


def _finals(sweep_dirs) -> dict:
    """{(root seed, seed index): final test return} of one-point sweeps, and each sweep's provenance.
    Seed i of a sweep with root seed r has the key ``fold_in(PRNGKey(r), i)`` whatever the seed count."""
    finals, prov = {}, []
    for d in map(pathlib.Path, sweep_dirs):
        try:
            if _point_dirs(d) == [d]:  # one `shed_jax run`: its own point; its config holds the root seed
                config = json.loads((d / "config.json").read_text())
                point, group, root = d, run_group(config), config["root_seed"]
                meta = {"device": f"{config.get('backend')}: {', '.join(config.get('devices') or [])}",
                        "env": config["experiment"]["env"]}
            else:
                sweep = json.loads((d / "sweep.json").read_text())
                if len(sweep["rows"]) != 1:
                    raise SystemExit(f"paired: {d} has {len(sweep['rows'])} points; give sweeps of one point each")
                point, group = d / sweep["rows"][0]["dir"], sweep["rows"][0].get("group")
                # sweeps from before sweep.json kept the root seed have it in the point's config
                root = sweep["root_seed"] if "root_seed" in sweep else json.loads((point / "config.json").read_text())["root_seed"]
                meta = {k: sweep.get(k) for k in ("device", "command", "date", "wall_time_s")}
                meta["env"] = sweep_env(d, point)
            summary = json.loads((point / "summary.json").read_text())
            per_seed = summary.get("final_test_return_per_seed")
            meta.setdefault("wall_time_s", summary.get("wall_time_s"))  # a run's own wall time
        except (OSError, KeyError, ValueError) as err:
            raise SystemExit(f"paired: {d} is not a finished sweep or run ({type(err).__name__}: {err})") from None
        if not per_seed or not all(map(_finite_num, per_seed)):
            raise SystemExit(f"paired: {d} has no finite final test return per seed (a stopped run?)")
        if any((root, i) in finals for i in range(len(per_seed))):
            raise SystemExit(f"paired: root seed {root} appears twice in one set ({d}): its seeds would count twice")
        for i, v in enumerate(per_seed):
            finals[(root, i)] = float(v)
        prov.append({"sweep": str(d), "group": group, "root_seed": root, "seeds": len(per_seed),
                     **{k: meta.get(k) for k in ("device", "command", "date", "wall_time_s", "env")}})
    return {"finals": finals, "sweeps": prov}


def paired(a_dirs, b_dirs) -> dict:
    """Final test returns of two sets of sweeps: each set pooled (mean, SE over its seeds), and a - b over
    the seeds both sets hold, matched by (root seed, seed index): such seeds start their students from
    the same initialisations, so the pairing removes that part of the noise."""
    a, b = _finals(a_dirs), _finals(b_dirs)
    envs = sorted({p["env"] for side in (a, b) for p in side["sweeps"] if p.get("env")})
    if len(envs) > 1:
        raise SystemExit(f"paired: the sets hold runs on {' and '.join(envs)}; pair runs of one environment")
    both = sorted(set(a["finals"]) & set(b["finals"]))
    if len(both) < 2:
        raise SystemExit(f"paired: {len(both)} seed(s) common to both sets; pairing needs at least 2")
    out = {}
    for name, s in (("a", a), ("b", b)):
        m, se = _mean_se(list(s["finals"].values()))
        out[name] = {"seeds": len(s["finals"]), "mean": m, "se": se, "sweeps": s["sweeps"],
                     "final_by_root_seed": {str(r): [v for (rr, _), v in sorted(s["finals"].items()) if rr == r]
                                            for r in sorted({r for r, _ in s["finals"]})}}
    m, se = _mean_se([a["finals"][k] - b["finals"][k] for k in both])
    out["paired"] = {"seeds": len(both), "mean": m, "se": se}
    out["env"] = envs[0] if envs else None
    return out


def plot_paired(res: dict, out, labels=("a", "b")) -> None:
    """Each set's per-seed finals (dots) with mean ± SE, and each pair's difference a - b."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    per = {k: {(r, i): v for r, vs in res[k]["final_by_root_seed"].items() for i, v in enumerate(vs)} for k in ("a", "b")}
    both = sorted(set(per["a"]) & set(per["b"]))
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(8, 3.6), gridspec_kw={"width_ratios": [2, 1]})
    rng = np.random.default_rng(0)  # horizontal jitter only
    for x, k in enumerate(("a", "b")):
        v = np.array(list(per[k].values()))
        ax.scatter(x + rng.uniform(-0.15, 0.15, len(v)), v, s=10, alpha=0.6)
        ax.errorbar(x + 0.3, res[k]["mean"], yerr=res[k]["se"], fmt="o", color="k", capsize=4)
    ax.set_xticks([0, 1], [f"{lab}\n{res[k]['mean']:.1f} ± {res[k]['se']:.1f} ({res[k]['seeds']})"
                           for lab, k in zip(labels, ("a", "b"))], fontsize=8)
    ax.set_ylabel("final test return")
    d = np.array([per["a"][k] - per["b"][k] for k in both])
    bx.scatter(rng.uniform(-0.15, 0.15, len(d)), d, s=10, alpha=0.6)
    bx.errorbar(0.3, res["paired"]["mean"], yerr=res["paired"]["se"], fmt="o", color="k", capsize=4)
    bx.axhline(0, color="grey", lw=0.8)
    bx.set_xticks([0], [f"a - b, paired\n{res['paired']['mean']:+.1f} ± {res['paired']['se']:.1f} ({len(d)})"], fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(f"-> {out}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("summarise", help="compact per-episode summaries of sweep or run directories")
    s.add_argument("dirs", nargs="+", help="sweep directories, or directories of one `shed_jax run`")
    s.add_argument("--out", required=True)
    r = sub.add_parser("record")
    r.add_argument("files", nargs="+")
    r.add_argument("--out", default=None, help="default docs/results/teacher.json for the lander, "
                   "docs/results/teacher_<env>.json for another env (never the lander's record)")
    r.add_argument("--device", required=True)
    r.add_argument("--command", required=True)
    r.add_argument("--date", default=None)
    r.add_argument("--note", action="append", default=[], help="a line for the record's notes (repeatable)")
    r.add_argument("--paper-csv", default=None, help="the paper teachers' (SHED, h-MDP) long-form CSV")
    r.add_argument("--dr", default=None, help="the baselines record whose lander DR entry to add")
    r.add_argument("--control", action="append", default=[],
                   help="a `paired` comparison file whose two sets join the record as DR entries, but for a set "
                        "of the record's own runs (repeatable)")
    r.add_argument("--dr-reference", default=None, help="the entry the targets compare each teacher with (default: dr)")
    r.add_argument("--env", default="lander", help="the environment the runs are on: the record's block (default lander)")
    q = sub.add_parser("plot")
    q.add_argument("files", nargs="+")
    q.add_argument("--out", required=True)
    q.add_argument("--only", action="append", default=[], help="a run's group name to include (repeatable)")
    b = sub.add_parser("late-box", help="the mean box of the generated levels late in runs (a DR control)")
    b.add_argument("dirs", nargs="+", help="<method>/<point>/ directories")
    b.add_argument("--from-episode", type=int, default=30)
    c = sub.add_parser("paired", help="two sets of one-point sweeps or runs: pooled finals and their paired difference")
    c.add_argument("dirs", nargs="+", help="the first set: sweep directories, or directories of one `shed_jax run`")
    c.add_argument("--vs", nargs="+", required=True, help="the second set, as the first")
    c.add_argument("--out", default=None, help="write the comparison here (JSON, with date and command)")
    c.add_argument("--plot", default=None, help="a figure of the per-seed finals and differences (PNG)")
    c.add_argument("--labels", nargs=2, default=("a", "b"), help="the two sets' names in the figure")
    a = p.parse_args(argv)
    if a.cmd == "paired":
        res = paired(a.dirs, a.vs)
        f1 = lambda e: f"{e['mean']:.1f} ± {e['se']:.1f} ({e['seeds']} seeds)"  # noqa: E731
        print(f"a: {f1(res['a'])}; b: {f1(res['b'])}; a - b, paired: {f1(res['paired'])}")
        if a.out:
            devices = "; ".join(sorted({s["device"] for k in ("a", "b") for s in res[k]["sweeps"] if s.get("device")})) \
                or "not recorded (sweeps from before sweep.json kept the device)"
            rec = {"date": datetime.date.today().isoformat(),
                   "command": "python -m experiments.teacher_runs paired " + " ".join(a.dirs) + " --vs " + " ".join(a.vs)
                   + f" --out {a.out}", "device": devices, **res}
            pathlib.Path(a.out).write_text(json.dumps(_finite(rec), indent=1, allow_nan=False) + "\n")
        if a.plot:
            plot_paired(res, a.plot, a.labels)
    elif a.cmd == "late-box":
        box = late_box(a.dirs, a.from_episode)
        print(json.dumps(box))
        fmt = lambda v: "[" + ",".join(f"{x:.3g}" for x in v) + "]"  # noqa: E731
        print(f"--set low={fmt(box['low'])} --set high={fmt(box['high'])}")
    elif a.cmd == "summarise":
        summarise(a.dirs, a.out)
    elif a.cmd == "plot":
        plot(a.files, a.out, a.only)
    else:
        out = a.out or ("docs/results/teacher.json" if a.env == "lander" else f"docs/results/teacher_{a.env}.json")
        record(a.files, out, a.device, a.command, a.date, a.note, a.paper_csv, a.dr, a.control, a.dr_reference, a.env)


if __name__ == "__main__":
    main()
