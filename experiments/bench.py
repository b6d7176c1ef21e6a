"""``make bench``: environment throughput benchmarks on whatever device JAX sees.

Runs the lander benchmark (env steps/s from 1k to 1M envs, plus Gymnasium on one CPU core as the
anchor) and the walker benchmark (1k to 32k envs, plus Brax's walker2d as the anchor), each in its
own module so either can be run alone:

    python -m experiments.bench [--only lander|walker] [--out DIR]
    python -m experiments.bench_lander --help
    python -m experiments.bench_walker --help

On a CPU the batch sizes are cut down so the run takes minutes, not hours; the GPU figures in
docs/benchmarks.md (dated entries in docs/log/benchmarks.md) come from the full sizes on an H200.
"""
from __future__ import annotations

import argparse
import os

import jax


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=("lander", "walker"), default=None)
    p.add_argument("--out", default=os.environ.get("OUT", "runs/bench"))
    args = p.parse_args(argv)
    gpu = jax.default_backend() == "gpu"
    print(f"[bench] backend={jax.default_backend()} devices={jax.devices()}")
    if args.only in (None, "lander"):
        from experiments import bench_lander

        batches = "1024,16384,131072,1048576" if gpu else "256,1024"
        bench_lander.main(["--batches", batches, "--out", args.out])
    if args.only in (None, "walker"):
        from experiments import bench_walker

        sizes = "1024,4096,8192,16384,32768" if gpu else "64"
        extra = [] if gpu else ["--steps", "10", "--repeats", "1"]
        bench_walker.main(["--batch-sizes", sizes, "--out", args.out] + extra)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
