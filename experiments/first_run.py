"""Time the README's first command on a fresh clone: ``make setup``, then ``make run ENV=lander`` twice.

    python -m experiments.first_run [--repo .] [--out docs/results/first_run.json]

Clones ``--repo`` (its committed HEAD) into a temporary folder, runs ``make setup`` there, then
``make run ENV=lander`` with no compilation cache (the first time) and again (from the cache),
stamping every output line as it arrives. Writes the wall times, the longest silence between two
lines of each run (tqdm's in-place redraws count as lines) and the machine to ``--out``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import platform
import subprocess
import sys
import tempfile
import time


def cpu_model() -> str:
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def timed(cmd: list[str], cwd: pathlib.Path) -> dict:
    """Run ``cmd``; its wall time, exit code, longest gap between output chunks, and the last lines."""
    start = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    last, gap, tail, buf = start, 0.0, [], b""
    while True:
        chunk = proc.stdout.read1(4096)
        if not chunk:
            break
        now = time.monotonic()
        gap, last = max(gap, now - last), now
        buf += chunk
        *lines, buf = buf.replace(b"\r", b"\n").split(b"\n")
        tail = (tail + [ln.decode(errors="replace") for ln in lines if ln.strip()])[-5:]
    rc = proc.wait()
    end = time.monotonic()
    return {"seconds": round(end - start, 1), "rc": rc, "longest_silence_s": round(max(gap, end - last), 1),
            "last_lines": tail}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repo", default=".")
    p.add_argument("--out", default="docs/results/first_run.json")
    args = p.parse_args()
    repo = pathlib.Path(args.repo).resolve()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        clone = pathlib.Path(tmp) / "shed_jax"
        subprocess.run(["git", "clone", "-q", str(repo), str(clone)], check=True)
        rows = {}
        for name, cmd in (("make setup", ["make", "setup"]), ("make run ENV=lander (first)", ["make", "run", "ENV=lander"]),
                          ("make run ENV=lander (second, compile cache)", ["make", "run", "ENV=lander"])):
            rows[name] = timed(cmd, clone)
            print(f"{name}: {rows[name]['seconds']} s (rc {rows[name]['rc']}, longest silence "
                  f"{rows[name]['longest_silence_s']} s)", flush=True)
            if rows[name]["rc"] != 0:
                print("\n".join(rows[name]["last_lines"]), file=sys.stderr)
                break
    record = {
        "device": f"CPU: {cpu_model()}, {len(__import__('os').sched_getaffinity(0))} cores",
        "date": datetime.date.today().isoformat(), "commit": commit,
        "command": "python -m experiments.first_run", "runs": rows,
        "targets": {"first_s": 240, "second_s": 90, "silence_s": 60},
    }
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {out}")
    return 0 if all(r["rc"] == 0 for r in rows.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
