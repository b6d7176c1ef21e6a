"""Where a compiled program's time goes: one call of it traced with ``jax.profiler``, summarised.

``jax.profiler`` writes an XSpace (``*.xplane.pb``): one plane per device, one line per stream, one
event per kernel, each kernel tagged with the HLO instruction (``hlo_op``) and module (``hlo_module``)
that launched it. A 2-D walker budget step launches over a million kernels, far too many to read in a
trace viewer, so ``summarise`` reduces them to what speed work needs:

* busy time (the union of the kernels' intervals) against the span from the first kernel's start to
  the last one's end: the rest is the device waiting for launches;
* kernel durations and idle gaps in size buckets (a launch-bound program has many kernels of a few
  microseconds and gaps of the same order);
* the ops grouped by how many times each ran: one loop's body runs its ops equally often, so a
  budget step's evaluation (2,000 steps), rollouts and SGD steps come apart even without names;
* the HLO instructions that took the most time, each with its ``op_name`` (JAX's name stack, read
  from the compiled program's HLO text), the time summed over every prefix of those name stacks, and
  the same summed over the program's own scope names alone (``named_scopes``: ``evaluate``,
  ``evaluate/velocity_passes``, ...), JAX's own words in the stack left out.

``TracedCompiled`` wraps a compiled program so that one chosen call runs under the profiler and its
summary is written as JSON: ``python -m shed_jax run --profile-chunk K`` uses it on a run's chunks.
On a host without an accelerator the host plane's XLA:CPU thunk events are used instead.

This module imports nothing else of ``shed_jax``: ``experiments/run_piece.sh`` copies it beside
``experiments/aot_cache.py`` to profile carried runs whose own sources predate it.
"""
from __future__ import annotations

import glob
import json
import os
import re
import shutil
import tempfile
import time

# bucket edges in microseconds, for kernel durations and idle gaps
EDGES_US = (2, 5, 10, 50, 200, 1000)
_DEF = re.compile(r'^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s.*?\bmetadata=\{[^}]*?op_name="([^"]*)"')


def hlo_op_names(hlo_text: str) -> dict[str, str]:
    """Instruction name -> its ``op_name`` metadata, from HLO text (``Compiled.as_text()``)."""
    names = {}
    for line in hlo_text.splitlines():
        m = _DEF.match(line)
        if m:
            names.setdefault(m.group(1), m.group(2))
    return names


# name-stack components that JAX's transformations and control flow add, not a program's own scopes
_JAX_WORDS = frozenset({"while", "body", "cond", "closed_call", "core_call", "remat", "checkpoint", "scan",
                        "pjit", "jit", "vmap", "jvp", "transpose", "shard_map", "custom_jvp_call",
                        "custom_vjp_call", "named_call", "xla_call", "eval_jaxpr"})
_HELPERS = frozenset({"clip"})  # jnp's jitted helpers without a leading underscore
_WRAPPED = re.compile(r"[\w.]+\((.*)\)")
_BRANCH = re.compile(r"branch_\d+(_fun)?")


def user_scopes(op_name: str) -> tuple[str, ...]:
    """The program's own scope names in an ``op_name`` (``jax.named_scope`` and named functions), outermost
    first: the program's own ``jit(NAME)``, the primitive, JAX's words (``while``, ``body``,
    ``closed_call``, ...), wrappers (``vmap(x)`` counts as ``x``) and jnp's helpers (``_where``, ``clip``) left out,
    a name repeated at once kept once."""
    out = []
    for part in op_name.split("/")[1:-1]:
        name = part
        while (m := _WRAPPED.fullmatch(name)) is not None:
            name = m.group(1)
        if not name or name.startswith("_") or name in _JAX_WORDS or name in _HELPERS or _BRANCH.fullmatch(name):
            continue
        if not out or out[-1] != name:
            out.append(name)
    return tuple(out)


def merge(intervals):
    """Sorted, disjoint ``[start, end)`` intervals covering the given ones."""
    out = []
    for s, e in sorted(intervals):
        if out and s <= out[-1][1]:
            if e > out[-1][1]:
                out[-1][1] = e
        else:
            out.append([s, e])
    return out


def _bucket(us: float) -> str:
    lo = 0
    for hi in EDGES_US:
        if us < hi:
            return f"{lo}-{hi} us"
        lo = hi
    return f">={EDGES_US[-1]} us"


def _buckets(values_us) -> dict:
    out = {}
    for v in values_us:
        b = out.setdefault(_bucket(v), {"count": 0, "ms": 0.0})
        b["count"] += 1
        b["ms"] += v / 1e3
    order = [_bucket(e - 1e-9) for e in EDGES_US] + [f">={EDGES_US[-1]} us"]
    return {k: {"count": out[k]["count"], "ms": round(out[k]["ms"], 6)} for k in order if k in out}


def find_xplane(trace_dir: str) -> str:
    files = sorted(glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True), key=os.path.getmtime)
    if not files:
        raise FileNotFoundError(f"no *.xplane.pb under {trace_dir}")
    return files[-1]


def kernel_events(xplane: str):
    """``(source, events)``: the device planes' kernels (``/device:GPU:N``), or the host plane's XLA
    thunks where there are none; each event ``(start_ns, duration_ns, name, hlo_op, hlo_module)``."""
    from jax.profiler import ProfileData

    data = ProfileData.from_file(xplane)
    planes = [p for p in data.planes if p.name.startswith("/device:")]
    source = "device" if planes else "host"
    if not planes:
        planes = [p for p in data.planes if p.name == "/host:CPU"]
    events = []
    for plane in planes:
        for line in plane.lines:
            for ev in line.events:
                op = module = None
                for k, v in ev.stats:
                    if k == "hlo_op":
                        op = v
                    elif k == "hlo_module":
                        module = v
                if source == "host" and op is None:
                    continue  # host threads' own events (python, thread pools), not the program's
                events.append((float(ev.start_ns), float(ev.duration_ns), ev.name, op, module))
    return source, events


def _prefix_totals(ops, path_of, depth: int | None = None) -> dict:
    """``{prefix: [kernels, ns]}`` summed over every prefix (up to ``depth`` parts) of each op's path
    ``path_of(op)`` (an empty path counts as ``(none)``); ``ops`` as ``summarise`` sorts them."""
    totals = {}
    for (_, op), (n, t, _) in ops:
        path = path_of(op) or ("(none)",)
        for d in range(1, min(len(path), depth or len(path)) + 1):
            r = totals.setdefault("/".join(path[:d]), [0, 0.0])
            r[0] += n
            r[1] += t
    return totals


def summarise(events, op_names: dict[str, str] | None = None, source: str = "device", top: int = 60,
              scope_share: float = 0.005, scope_depth: int = 24, min_share: float = 0.0005,
              max_ops: int = 400) -> dict:
    """The summary (module docstring) of ``kernel_events``' events: the ``top`` ops by time, and more
    (up to ``max_ops``) while each has ``min_share`` of the busy time; ``by_calls``, the ops grouped by
    how many times each ran (classes with ``min_share`` of the time)."""
    op_names = op_names or {}
    if not events:
        return {"source": source, "kernels": 0}
    busy = sum(d for _, d, *_ in events)
    merged = merge([[s, s + d] for s, d, *_ in events])
    union = sum(e - s for s, e in merged)
    span = merged[-1][1] - merged[0][0]
    gaps = [(merged[i + 1][0] - merged[i][1]) / 1e3 for i in range(len(merged) - 1)]
    by_op, by_module = {}, {}
    for s, d, name, op, module in events:
        key = (module or "?", op or name)
        r = by_op.setdefault(key, [0, 0.0, name])
        r[0] += 1
        r[1] += d
        m = by_module.setdefault(module or "?", [0, 0.0])
        m[0] += 1
        m[1] += d
    ops = sorted(by_op.items(), key=lambda kv: -kv[1][1])
    # ops that ran equally often are usually one loop's body: a program's loops told apart by count
    by_calls = {}
    for (module, op), (n, t, _) in ops:
        r = by_calls.setdefault(n, [0, 0, 0.0])
        r[0] += 1
        r[1] += n
        r[2] += t
    def user_path(op):
        return user_scopes(op_names[op]) if op in op_names else ("(none)",)

    def stack_path(op):  # the whole name stack, the primitive itself dropped
        return tuple(op_names[op].split("/")[:-1]) if op in op_names else ("(no op_name)",)

    named, scopes = _prefix_totals(ops, user_path), _prefix_totals(ops, stack_path, scope_depth)
    return {
        "source": source,
        "kernels": len(events),
        "busy_s": round(busy / 1e9, 9),
        "union_s": round(union / 1e9, 9),
        "span_s": round(span / 1e9, 9),
        "idle_s": round((span - union) / 1e9, 9),
        "mean_kernel_us": round(busy / len(events) / 1e3, 3),
        "durations": _buckets(d / 1e3 for _, d, *_ in events),
        "gaps": _buckets(gaps),
        "modules": {k: {"kernels": n, "busy_s": round(t / 1e9, 9)} for k, (n, t) in
                    sorted(by_module.items(), key=lambda kv: -kv[1][1])},
        "ops_with_op_name": sum(1 for (_, op) in by_op if op in op_names),
        "ops": len(by_op),
        "by_calls": [{"calls": n, "ops": k, "kernels": m, "ms": round(t / 1e6, 6), "share": round(t / busy, 5)}
                     for n, (k, m, t) in sorted(by_calls.items(), key=lambda kv: -kv[1][2])
                     if t >= min_share * busy],
        "top_ops": [{"module": module, "hlo_op": op, "kernel": name[:120], "count": n,
                     "ms": round(t / 1e6, 6), "mean_us": round(t / n / 1e3, 3),
                     "share": round(t / busy, 5), "op_name": op_names.get(op)}
                    for i, ((module, op), (n, t, name)) in enumerate(ops)
                    if i < top or (i < max_ops and t >= min_share * busy)],
        "named_scopes": {k: {"kernels": n, "ms": round(t / 1e6, 6), "share": round(t / busy, 5)}
                         for k, (n, t) in sorted(named.items(), key=lambda kv: -kv[1][1])
                         if t >= scope_share * busy},
        "scopes": {k: {"kernels": n, "ms": round(t / 1e6, 6), "share": round(t / busy, 5)}
                   for k, (n, t) in sorted(scopes.items()) if t >= scope_share * busy},
    }


def summarise_trace(trace_dir: str, hlo_text: str | None = None, **kw) -> dict:
    source, events = kernel_events(find_xplane(trace_dir))
    return summarise(events, hlo_op_names(hlo_text) if hlo_text else None, source, **kw)


def labelled(summary: dict, labels: dict[int, str]) -> dict:
    """``summary`` with each ``by_calls`` class named by ``labels`` (calls -> what ran that often) and
    the share of the busy time each label holds (``loops``)."""
    out = dict(summary)
    out["by_calls"] = [dict(b, loop=labels[b["calls"]]) if b["calls"] in labels else b
                       for b in summary.get("by_calls", [])]
    loops = {}
    for b in out["by_calls"]:
        r = loops.setdefault(b.get("loop", "(other, listed)"), {"ops": 0, "kernels": 0, "ms": 0.0})
        r["ops"] += b["ops"]
        r["kernels"] += b["kernels"]
        r["ms"] += b["ms"]
    listed = sum(r["ms"] for r in loops.values())
    busy_ms = summary.get("busy_s", 0) * 1e3
    loops["(other, below the listing's threshold)"] = {"ops": None, "kernels": None,
                                                      "ms": max(busy_ms - listed, 0.0)}
    out["loops"] = {k: dict(v, ms=round(v["ms"], 3), share=round(v["ms"] / busy_ms, 5) if busy_ms else None)
                    for k, v in loops.items()}
    return out


class TraceCount:
    """The call chosen for the trace (1-based, counted over every program that shares this count), where
    its summary goes, and the walls of the calls timed so far."""

    def __init__(self, call: int, out: str, say=print):
        if not isinstance(call, int) or isinstance(call, bool) or call < 1:
            raise ValueError(f"the call to profile must be a whole number >= 1, got {call!r}")
        self.call, self.out, self.say = call, out, say
        self.n, self.walls, self.summary = 0, [], None

    @property
    def traced(self) -> bool:
        return self.n >= self.call

    def write(self):
        record = dict(self.summary or {}, calls_wall_s=self.walls, traced_call=self.call)
        with open(self.out, "w") as f:
            json.dump(record, f, indent=1)


class TracedCompiled:
    """A compiled program whose calls 1 to ``count.call + 1`` are waited for and timed, and whose
    ``count.call``-th call runs under ``jax.profiler``; the summary (with every timed call's wall, and
    rewritten after the call after it) goes to ``count.out``. Later calls run untouched."""

    def __init__(self, compiled, count: TraceCount):
        self._compiled, self._count = compiled, count

    def __call__(self, *args, **kwargs):
        import jax

        c = self._count
        c.n += 1
        k = c.n
        if k > c.call + 1:
            return self._compiled(*args, **kwargs)
        trace_dir = None
        if k == c.call:
            trace_dir = tempfile.mkdtemp(prefix="shed_jax_trace.")
            opts = jax.profiler.ProfileOptions()
            opts.python_tracer_level = 0
            # a 2-D walker chunk launches millions of kernels: above CUPTI's default buffers (2M
            # records; each launch makes a callback and an activity record)
            opts.advanced_configuration = {"gpu_max_activity_api_events": 16 << 20,
                                           "gpu_max_callback_api_events": 16 << 20}
            jax.profiler.start_trace(trace_dir, profiler_options=opts)
        t0 = time.perf_counter()
        out = jax.block_until_ready(self._compiled(*args, **kwargs))
        wall = time.perf_counter() - t0
        c.walls.append(round(wall, 4))
        if trace_dir is not None:
            jax.profiler.stop_trace()
            t1 = time.perf_counter()
            try:
                try:
                    hlo = self._compiled.as_text()
                except Exception as err:  # noqa: BLE001 - op names are a help, the times are the result
                    hlo = None
                    c.say(f"[shed_jax] the profiled program's HLO text is not available ({type(err).__name__}: {err})")
                c.summary = summarise_trace(trace_dir, hlo)
                c.summary["traced_wall_s"] = round(wall, 4)
                c.summary["summarised_in_s"] = round(time.perf_counter() - t1, 1)
            except Exception as err:  # noqa: BLE001 - the program's caller goes on without its profile
                c.summary = {"error": f"{type(err).__name__}: {err}"}
            shutil.rmtree(trace_dir, ignore_errors=True)
            c.say(f"[shed_jax] call {k} profiled ({wall:.2f} s; untraced calls so far {c.walls[:-1]}): "
                  f"{c.summary.get('kernels', '?')} kernels, busy {c.summary.get('union_s', '?')} s of a "
                  f"{c.summary.get('span_s', '?')} s span -> {c.out}")
        if k >= c.call:
            c.write()
        return out

    def __getattr__(self, name):
        return getattr(self._compiled, name)
