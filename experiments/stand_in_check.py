"""Check and time stand-ins (``experiments/aot_cache.py``) on a small run: start it, then resume it
twice from the same checkpoint, once reading its chunk from the stand-in the start wrote and once
tracing it (``AOT_STAND_INS=0``), and compare what the two resumes wrote.

The run is ``python experiments/aot_cache.py run -m shed_jax run FLAGS`` in a scratch folder holding a
copy of the sources (this tree's, or a carried run's ``src.tgz``), with its own compilation cache. The
record names each resume's "compiled in" seconds, whether the stand-in was read, and whether
``metrics.jsonl`` is byte for byte the same.

    python -m experiments.stand_in_check --out docs/results/stand_in_check_cpu.json
    python -m experiments.stand_in_check --src docs/results/bipedal_paper_shedx_inflight/src.tgz --out F.json
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
FLAGS = "--env lander --method shed --preset quick --seeds 1 --episodes 1 --steps-per-episode 6 --chunk 2"


def _run(work: pathlib.Path, args: list[str], log: str, **env) -> tuple[int, str]:
    cmd = [sys.executable, str(work / "aot_cache_tool.py"), "run", "-m", "shed_jax", "run", *args, "--no-gif"]
    r = subprocess.run(cmd, cwd=work, capture_output=True, text=True, timeout=1800,
                       env={**os.environ, "SHED_JAX_CACHE": str(work / ".cache"), **env})
    (work / log).write_text(r.stdout + r.stderr)
    return r.returncode, r.stdout + r.stderr


def _compiled_s(text: str) -> float | None:
    m = re.findall(r"compiled in ([0-9.]+) s", text)
    return float(m[-1]) if m else None


def check(src: str | None, flags: str, work: pathlib.Path) -> dict:
    if src:
        with tarfile.open(src) as tar:
            tar.extractall(work, filter="data")
    else:
        for d in ("shed_jax", "envs", "experiments"):
            shutil.copytree(ROOT / d, work / d, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "experiments" / "aot_cache.py", work / "aot_cache_tool.py")  # this tree's tool
    rc, text = _run(work, [*flags.split(), "--out", "runs/x", "--stop-after", "2"], "start.log")
    if rc != 75:
        raise RuntimeError(f"the start exited {rc}: {text[-500:]}")
    shutil.copytree(work / "runs", work / "at_start")
    out = {}
    for name, env in (("stand_in", {}), ("traced", {"AOT_STAND_INS": "0"})):
        shutil.rmtree(work / "runs")
        shutil.copytree(work / "at_start", work / "runs")
        rc, text = _run(work, ["--resume", "runs/x", "--stop-after", "4"], f"{name}.log", **env)
        if rc != 75:
            raise RuntimeError(f"the {name} resume exited {rc}: {text[-500:]}")
        out[name] = {"compiled_s": _compiled_s(text), "read_from_stand_in": "read from its stand-in" in text,
                     "metrics": (work / "runs" / "x" / "metrics.jsonl").read_bytes()}
    return {"flags": flags, "sources": src or "this tree",
            "stand_in_compiled_s": out["stand_in"]["compiled_s"], "traced_compiled_s": out["traced"]["compiled_s"],
            "stand_in_read": out["stand_in"]["read_from_stand_in"],
            "traced_read_a_stand_in": out["traced"]["read_from_stand_in"],
            "metrics_equal": out["stand_in"]["metrics"] == out["traced"]["metrics"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--src", default=None, help="a carried run's src.tgz (default: this tree's sources)")
    ap.add_argument("--flags", default=FLAGS, help=f"the run's flags (default: {FLAGS!r})")
    ap.add_argument("--out", default=None, help="write the record here (JSON)")
    a = ap.parse_args(argv)
    if a.src and not os.path.isfile(a.src):
        print(f"stand_in_check: no file {a.src}", file=sys.stderr)
        return 2
    import jax

    from experiments.aot_cache import _cpu_model

    with tempfile.TemporaryDirectory(prefix="stand_in_check.") as tmp:
        rec = check(a.src, a.flags, pathlib.Path(tmp))
    rec.update(date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), jax=jax.__version__,
               device=f"{_cpu_model()} ({os.cpu_count()} CPUs), backend {jax.default_backend()}",
               command=" ".join(["python -m experiments.stand_in_check", *(argv if argv is not None else sys.argv[1:])]))
    print(json.dumps(rec, indent=1))
    if a.out:
        pathlib.Path(a.out).write_text(json.dumps(rec, indent=1) + "\n")
    return 0 if rec["stand_in_read"] and rec["metrics_equal"] and not rec["traced_read_a_stand_in"] else 1


if __name__ == "__main__":
    sys.exit(main())
