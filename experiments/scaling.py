"""Seconds per chunk of lander sweeps on 1, 2 and 4 GPUs: the sharded driver's scaling record.

    python -m experiments.scaling --out DIR [--configs dr:256,dr:1024,shed:256,shed:1024]
        [--devices 1,2,4] [--chunk 2] [--chunks 3] [--trace dr:1024@1+2] [--old-tree .old --old-config dr:1024@2]
        [--checkpoint-max-gb G] [--checkpoint-every SECONDS]
    python -m experiments.scaling --record DIR --to docs/results/scaling.json [--keep]   # the record, from a run's files

One worker process per (method, seeds, devices), each on its own ``CUDA_VISIBLE_DEVICES`` subset,
all started at once. Every worker builds its batch with the sweep's own code (the paper preset;
``driver.make_batch``, ``driver.place`` on a mesh of its devices), compiles it, then waits at a
barrier until every worker has compiled (XLA's autotuning runs kernels on the GPUs, so no compile
overlaps a timed run). The timed part runs one worker at a time, in the order of ``--configs``
(each worker hands the turn to the next; a worker that dies hands it on through this script): ``driver.train``
exactly as a sweep calls it, with checkpoints and ``metrics.jsonl`` on, for ``--chunks`` chunks of
``--chunk`` budget steps. The figure is the cadence: seconds between consecutive chunks' results
reaching the host (the first chunk, which pays one-off start-up costs, is left out), with the
writer thread's time per chunk beside it.

SHED is timed with ``ddpg_threshold``, ``diffusion_threshold`` and ``syn_threshold`` at 1, so that
its DDPG, diffusion and mixed-batch updates all run in the few chunks timed (at the paper's values
the first DDPG update comes at budget step 33); the program is the same, only those conditions
differ. ``--old-tree`` names a copy of an earlier ``shed_jax`` (``git archive``) whose driver runs
``--old-config`` alongside, on the same machine, as the baseline. ``--trace M:S@D+D`` records one
extra chunk of that configuration with ``jax.profiler`` on those device counts (all without
``@``) and summarises the trace: each
GPU's busy time (the union of its kernels' intervals) against the chunk's wall time, and the
kernels that took longest.
"""
from __future__ import annotations

import argparse
import datetime
import gzip
import json
import os
import pathlib
import shutil
import subprocess
import sys
import time

SHED_TIMING = {"ddpg_threshold": 1, "diffusion_threshold": 1, "syn_threshold": 1}


def parse_configs(text: str) -> list[tuple[str, int, list[int] | None]]:
    """``dr:256,shed:1024@1+2`` -> [("dr", 256, None), ("shed", 1024, [1, 2])] (None: every --devices)."""
    out = []
    for item in text.split(","):
        spec, _, on = item.partition("@")
        method, _, seeds = spec.partition(":")
        out.append((method.strip(), int(seeds), [int(x) for x in on.split("+")] if on else None))
    return out


def gpu_count() -> int:
    try:
        listed = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return 0
    return sum(1 for line in listed.splitlines() if line.startswith("GPU "))


def plan(configs, devices: list[int], ngpu: int, old: tuple | None) -> list[dict]:
    """Every worker: its name, method, seeds, device count and GPU subset (spread so that no GPU
    holds more than its share of the waiting workers' memory)."""
    jobs, turn = [], {d: 0 for d in devices}
    for method, seeds, only in configs:
        for d in only or devices:
            if d > ngpu:
                continue
            groups = [list(range(i, i + d)) for i in range(0, ngpu - d + 1, d)]
            gpus = groups[turn[d] % len(groups)]
            turn[d] += 1
            trees = ["new"] + (["old"] if old and (method, seeds) == old[:2] and d in (old[2] or [d]) else [])
            for tree in trees:
                jobs.append({"name": f"{method}-{seeds}-{d}gpu-{tree}", "method": method, "seeds": seeds,
                             "devices": d, "gpus": gpus, "tree": tree, "turn": len(jobs)})
    return jobs


def orchestrate(args) -> int:
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ngpu = gpu_count()
    if ngpu == 0:
        print("[scaling] no GPU (nvidia-smi -L lists none); this experiment times GPUs", file=sys.stderr)
        return 2
    old = parse_configs(args.old_config)[0] if args.old_tree else None
    jobs = plan(parse_configs(args.configs), [int(x) for x in args.devices.split(",")], ngpu, old)
    sync = out / "sync"
    shutil.rmtree(sync, ignore_errors=True)
    sync.mkdir()
    print(f"[scaling] {len(jobs)} workers on {ngpu} GPUs: " + ", ".join(j["name"] for j in jobs), flush=True)
    procs = []
    for job in jobs:
        env = dict(os.environ, CUDA_VISIBLE_DEVICES=",".join(map(str, job["gpus"])), PYTHONUNBUFFERED="1",
                   XLA_PYTHON_CLIENT_PREALLOCATE="false")
        if job["tree"] == "old":
            env["PYTHONPATH"] = os.pathsep.join([str(pathlib.Path(args.old_tree).resolve()), os.getcwd(),
                                                 env.get("PYTHONPATH", "")])
        cmd = [sys.executable, "-m", "experiments.scaling", "--worker", json.dumps(job), "--out", str(out),
               "--chunk", str(args.chunk), "--chunks", str(args.chunks), "--barrier", str(len(jobs)),
               "--trace", args.trace or "", "--checkpoint-max-gb", str(args.checkpoint_max_gb),
               "--checkpoint-every", str(args.checkpoint_every)]
        log = open(out / f"{job['name']}.log", "w")
        procs.append((job, subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT), log))
    t0 = time.time()
    while any(p.poll() is None for _, p, _ in procs):
        time.sleep(2)
        for job, p, _ in procs:  # a worker that died passes the barrier and hands its turn on
            if p.poll() is not None:
                (sync / f"{job['name']}.ready").touch()
                if (sync / f"turn-{job['turn']}").exists():
                    (sync / f"turn-{job['turn'] + 1}").touch()
        if time.time() - t0 > args.max_seconds:
            print(f"[scaling] stopping the workers after {args.max_seconds} s", flush=True)
            for _, p, _ in procs:
                p.kill()
                p.wait()
            break
    for job, p, log in procs:
        log.close()
        print(f"[scaling] {job['name']}: exit {p.returncode}", flush=True)
    record(out, out / "scaling.json")
    return 0


def worker(args) -> int:
    job = json.loads(args.worker)
    import jax
    import numpy as np

    from shed_jax import driver, reporting, sharding
    from shed_jax.experiment import build
    from shed_jax.presets import build_experiment

    out = pathlib.Path(args.out)
    name, S, d = job["name"], job["seeds"], job["devices"]
    overrides = SHED_TIMING if job["method"] in ("shed", "hmdp") else {}
    exp = build_experiment("lander", job["method"], "paper", method_overrides=dict(overrides))
    batch = driver.make_batch(exp, build(exp), [({}, {})], num_seeds=S, root_seed=0, chunk=args.chunk)
    devices = jax.devices()
    assert len(devices) >= d, f"{name}: {len(devices)} visible devices, needs {d}"
    placed = driver.place(batch, sharding.batch_mesh(devices[:d]))
    t0 = time.time()
    state, compiled = driver.compile_batch(batch, placed, 0)
    jax.block_until_ready(state)
    compile_s = time.time() - t0
    (out / "sync" / f"{name}.ready").write_text("")
    while len(list((out / "sync").glob("*.ready"))) < args.barrier:
        time.sleep(1)
    spec, _, on = args.trace.partition("@")
    traced = (spec == f"{job['method']}:{S}" and job["tree"] == "new"
              and (not on or str(d) in on.split("+")))
    chunks = args.chunks + (1 if traced else 0)
    rundir = pathlib.Path(os.environ.get("TMPDIR", "/tmp")) / f"scaling-{name}"
    shutil.rmtree(rundir, ignore_errors=True)
    rundir.mkdir(parents=True)
    if job["turn"] == 0:
        (out / "sync" / "turn-0").touch()
    while not (out / "sync" / f"turn-{job['turn']}").exists():
        time.sleep(0.5)
    stamps, trace_dir = [], out / f"trace-{name}"

    class Cadence(driver.Reporter):
        def chunk(self, progress, steps, flat):
            stamps.append(time.time())
            if traced and len(stamps) == chunks - 1:
                jax.profiler.start_trace(str(trace_dir), create_perfetto_trace=True)

    state_gb = sum(x.nbytes for x in jax.tree_util.tree_leaves(state)) / 1e9
    checkpoint = state_gb <= args.checkpoint_max_gb
    progress = driver.Progress(state=state)
    output = driver.Output([rundir], [name], rundir if checkpoint else None, 1, {"scaling": name},
                           lambda p: {"wall_time_s": p.wall()}, label=name)
    if args.checkpoint_every:  # the driver before --checkpoint-every (--old-tree) has no such field
        output.every = args.checkpoint_every
    t_train = time.time()
    driver.train(batch, compiled, progress, output, driver.StopRules(stop_after=chunks * args.chunk), Cadence(),
                 lambda: "")
    if traced:
        jax.profiler.stop_trace()
    (out / "sync" / f"turn-{job['turn'] + 1}").touch()
    gaps = np.diff(np.asarray([t_train] + stamps))
    timed = gaps[1:args.chunks] if args.chunks > 1 else gaps[:1]  # one chunk: it is all there is
    tr = np.asarray(progress.history["test_return"])[:, -1]
    mean, se = reporting.mean_se(tr)
    result = {"name": name, "method": job["method"], "seeds": S, "devices": d, "gpus": job["gpus"], "tree": job["tree"],
              "chunk_budget_steps": args.chunk, "compile_s": compile_s, "chunk_gaps_s": gaps.tolist(),
              "seconds_per_chunk": float(np.median(timed)),
              "write_s": list(getattr(progress, "write_s", [])), "final_step": progress.done,
              "final_test_return_mean": float(mean), "final_test_return_se": float(se),
              "method_overrides": overrides, "state_gb": state_gb, "checkpoint": checkpoint,
              "checkpoint_every": args.checkpoint_every, "device_kind": devices[0].device_kind, "jax": jax.__version__}
    if traced:
        result["trace"] = trace_summary(trace_dir, gaps[-1])
    (out / f"{name}.json").write_text(json.dumps(result, indent=2))
    shutil.rmtree(rundir, ignore_errors=True)
    print(json.dumps({k: result[k] for k in ("name", "compile_s", "seconds_per_chunk", "final_test_return_mean")}))
    return 0


def trace_summary(trace_dir: pathlib.Path, wall: float) -> dict:
    """Per GPU: kernel time, busy time (union of kernel intervals) and the longest kernels, from the
    perfetto trace ``jax.profiler`` wrote under ``trace_dir``."""
    files = sorted(trace_dir.rglob("*trace.json.gz"))
    if not files:
        return {"error": f"no *trace.json.gz under {trace_dir}"}
    with gzip.open(files[-1], "rt") as f:
        events = json.load(f).get("traceEvents", [])
    names = {e["pid"]: e.get("args", {}).get("name", "") for e in events
             if e.get("ph") == "M" and e.get("name") == "process_name"}
    per: dict = {}
    for e in events:
        if e.get("ph") != "X" or "dur" not in e:
            continue
        pname = names.get(e.get("pid"), "")
        if "GPU" not in pname and "gpu" not in pname:
            continue
        per.setdefault(pname, []).append((float(e["ts"]), float(e["dur"]), e.get("name", "")))
    summary = {"wall_s": float(wall), "processes": sorted(set(names.values()))[:40], "gpus": {}}
    for pname, evs in per.items():
        evs.sort()
        busy, end, total, by_name = 0.0, -1e30, 0.0, {}
        for ts, dur, kname in evs:
            total += dur
            by_name[kname] = by_name.get(kname, 0.0) + dur
            if ts + dur > end:
                busy += ts + dur - max(ts, end)
                end = ts + dur
        span = (evs[-1][0] + evs[-1][1] - evs[0][0]) if evs else 0.0
        top = sorted(by_name.items(), key=lambda kv: -kv[1])[:12]
        summary["gpus"][pname] = {"events": len(evs), "kernel_s": total / 1e6, "busy_s": busy / 1e6,
                                  "span_s": span / 1e6, "top": [[k[:80], v / 1e6] for k, v in top]}
    return summary


def record(run_dir: pathlib.Path, to: pathlib.Path, command: str = "", keep: bool = False) -> dict:
    """``scaling.json`` from the workers' files: rows with speed-ups against the same run on one GPU.

    A row's speed-up is against the one-GPU row of the same run, method, seeds, code and checkpoint
    mode. With ``keep``, the rows already in ``to`` that this run did not measure again (same code,
    method, seeds, devices and checkpoint mode) stay, with the run that measured them: every row
    names its run by index into ``runs`` (date and command)."""
    results = [json.loads(p.read_text()) for p in sorted(run_dir.glob("*gpu-*.json"))]
    today = datetime.date.today().isoformat()
    command = command or "python -m experiments.scaling " + " ".join(sys.argv[1:])
    old = json.loads(to.read_text()) if keep and to.exists() else {}
    runs = old.get("runs") or ([{"date": old["date"], "command": old["command"]}] if old else [])
    run = len(runs)
    runs.append({"date": today, "command": command})

    def mode(r):  # what a speed-up compares across device counts (a worker file says "tree", a row "code")
        return r.get("code", r.get("tree")), r["method"], r["seeds"], r.get("checkpoint", True)

    def key(r):  # what a new run measures again
        return mode(r) + (r["devices"],)

    base = {mode(r): r["seconds_per_chunk"] for r in results if r["devices"] == 1}
    rows = []
    for r in results:
        one = base.get(mode(r))
        rows.append({"method": r["method"], "seeds": r["seeds"], "devices": r["devices"], "code": r["tree"],
                     "seconds_per_chunk": round(r["seconds_per_chunk"], 3), "budget_steps_per_chunk": r["chunk_budget_steps"],
                     "speedup": round(one / r["seconds_per_chunk"], 3) if one else None,
                     "compile_s": round(r["compile_s"], 1), "state_gb": round(r.get("state_gb", 0.0), 2),
                     "checkpoint": r.get("checkpoint", True), "checkpoint_every": r.get("checkpoint_every", 0.0),
                     "writer_s_per_chunk": [round(x, 2) for x in r["write_s"]],
                     "final_step": r["final_step"], "final_test_return_mean": round(r["final_test_return_mean"], 2),
                     "final_test_return_se": round(r["final_test_return_se"], 2), "run": run})
    fresh = {key(r) for r in rows}
    kept = [dict(r, run=r.get("run", 0)) for r in old.get("rows", []) if key(r) not in fresh]
    rows = sorted(kept + rows, key=lambda r: (r["code"], r["method"], not r["checkpoint"], r["seeds"], r["devices"]))
    traces = dict(old.get("traces", {}))
    traces.update({f"{r['name']} (run {run})": r["trace"] for r in results if "trace" in r})
    device = results[0]["device_kind"] if results else old.get("device", "unknown")
    rec = {"device": device, "date": today, "command": command, "runs": runs,
           "jax": results[0]["jax"] if results else old.get("jax"),
           "note": "seconds_per_chunk: median seconds between consecutive chunks' results (first chunk left out); "
                   "speedup: against the one-GPU row of the same run, code, method, seeds and checkpoint mode; "
                   "SHED with ddpg/diffusion/syn thresholds at 1 so every teacher update runs in the timed chunks; "
                   "run: index into runs",
           "rows": rows, "traces": traces}
    to.write_text(json.dumps(rec, indent=2))
    for row in rows:
        print(f"{row['code']:4s} {row['method']:5s} {row['seeds']:5d} seeds {row['devices']} GPU  "
              f"{'ckpt' if row['checkpoint'] else '    '}  {row['seconds_per_chunk']:7.2f} s/chunk  x{row['speedup']}  "
              f"test {row['final_test_return_mean']:.1f} ± {row['final_test_return_se']:.1f}  (run {row['run']})")
    return rec


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=os.environ.get("OUT", "runs/scaling"))
    p.add_argument("--configs", default="dr:256,dr:1024,shed:256,shed:1024")
    p.add_argument("--devices", default="1,2,4")
    p.add_argument("--chunk", type=int, default=2)
    p.add_argument("--chunks", type=int, default=3)
    p.add_argument("--trace", default="")
    p.add_argument("--checkpoint-every", type=float, default=0.0,
                   help="seconds between checkpoints (driver.Output.every; 0: every chunk, as sweeps default)")
    p.add_argument("--checkpoint-max-gb", type=float, default=float("inf"),
                   help="time batches whose state is larger without checkpoints (recorded per row)")
    p.add_argument("--old-tree", default="")
    p.add_argument("--old-config", default="dr:1024")
    p.add_argument("--max-seconds", type=float, default=540.0)
    p.add_argument("--record", default="")
    p.add_argument("--to", default="docs/results/scaling.json")
    p.add_argument("--command", default="", help="with --record: the measuring command(s) to name in the record")
    p.add_argument("--keep", action="store_true",
                   help="with --record: keep the rows of --to that this run did not measure again")
    p.add_argument("--worker", default="", help=argparse.SUPPRESS)
    p.add_argument("--barrier", type=int, default=1, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        return worker(args)
    if args.record:
        record(pathlib.Path(args.record), pathlib.Path(args.to), args.command, args.keep)
        return 0
    return orchestrate(args)


if __name__ == "__main__":
    raise SystemExit(main())
