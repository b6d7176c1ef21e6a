"""Where the test suite's time goes: a pytest plugin that sums JAX's own timing lines per test, and a
summary of what it wrote.

    rm -rf .cache/jax     # an empty compilation cache, as on a fresh clone
    .venv/bin/python -m pytest -q -n 2 --dist worksteal -p experiments.suite_compile_times
    .venv/bin/python -m experiments.suite_compile_times      # the table of docs/log/benchmarks.md

JAX logs, at debug level, ``Finished tracing <f> for jit in <s> sec``, ``Finished jaxpr to MLIR
module conversion <f> in <s> sec`` and ``Finished XLA compilation of <f> in <s> sec``. The plugin
adds them up per test (tracing counts a nested jit again inside its caller, so its sum is an upper
bound) and each xdist worker writes ``suite_compile_times_<worker>.json`` (``SHED_JAX_COMPILE_TIMES``
names the folder, default ``.cache``). Compiles in a test's child processes are not seen.
"""
from __future__ import annotations

import collections
import json
import logging
import os
import pathlib
import re
import time

import pytest

BIG = 2.0  # seconds: a compile at least this long is listed by name
PATTERNS = {
    "trace": re.compile(r"Finished tracing (\S+) for jit in ([0-9.e-]+) sec"),
    "lower": re.compile(r"Finished jaxpr to MLIR module conversion (\S+) in ([0-9.e-]+) sec"),
    "compile": re.compile(r"Finished XLA compilation of (\S+) in ([0-9.e-]+) sec"),
}
LOGGERS = ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.compiler", "jax._src.pjit")
_current = {"test": None}
_times: dict = {}


def _entry(test) -> dict:
    return _times.setdefault(test, {"trace": 0.0, "lower": 0.0, "compile": 0.0, "compiles": 0, "big": []})


class _Timings(logging.Handler):
    def emit(self, record):
        message = record.getMessage()
        for kind, pattern in PATTERNS.items():
            m = pattern.search(message)
            if m:
                d, seconds = _entry(_current["test"]), float(m.group(2))
                d[kind] += seconds
                if kind == "compile":
                    d["compiles"] += 1
                    if seconds >= BIG:
                        d["big"].append((m.group(1), round(seconds, 1)))


def folder() -> pathlib.Path:
    return pathlib.Path(os.environ.get("SHED_JAX_COMPILE_TIMES", ".cache"))


def pytest_configure(config):
    handler = _Timings(level=logging.DEBUG)
    for name in LOGGERS:
        log = logging.getLogger(name)
        log.setLevel(logging.DEBUG)
        log.addHandler(handler)
        log.propagate = False  # the debug lines go to the plugin only, not to pytest's captured logs


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _current["test"] = item.nodeid
    start = time.time()
    yield
    _entry(item.nodeid)["wall"] = time.time() - start


def pytest_sessionfinish(session):
    out = folder()
    out.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    (out / f"suite_compile_times_{worker}.json").write_text(json.dumps(_times))


def summary(times: dict) -> dict:
    """Suite totals: wall time in the tests, tracing, lowering, XLA compile, and the compile split into
    programs of at least BIG seconds (by function name) and the rest."""
    total = collections.Counter()
    by_name, count_by_name = collections.Counter(), collections.Counter()
    for d in times.values():
        for k in ("wall", "trace", "lower", "compile", "compiles"):
            total[k] += d.get(k, 0)
        for name, seconds in d["big"]:
            by_name[name] += seconds
            count_by_name[name] += 1
    big = sum(by_name.values())
    return {"wall": total["wall"], "trace": total["trace"], "lower": total["lower"], "compile": total["compile"],
            "compiles": int(total["compiles"]), "big": big, "big_compiles": int(sum(count_by_name.values())),
            "small": total["compile"] - big, "by_name": {k: [round(v, 1), count_by_name[k]] for k, v in by_name.most_common()}}


def main() -> int:
    times = {}
    for path in sorted(folder().glob("suite_compile_times_*.json")):
        times.update(json.loads(path.read_text()))
    if not times:
        raise SystemExit(f"no suite_compile_times_*.json in {folder()}: run pytest with -p experiments.suite_compile_times first")
    s = summary(times)
    print(f"in-test wall {s['wall']:.0f} s; XLA compile {s['compile']:.0f} s in {s['compiles']} programs "
          f"({s['big']:.0f} s in {s['big_compiles']} of at least {BIG:.0f} s, {s['small']:.0f} s in the rest); "
          f"lowering {s['lower']:.0f} s; tracing at most {s['trace']:.0f} s")
    for name, (seconds, n) in list(s["by_name"].items())[:10]:
        print(f"  {seconds:7.1f} s in {n:3d}  {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
