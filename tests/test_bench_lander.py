"""experiments.bench_lander's kernel launch shapes: parsing, and that the module's shape is set per
row and restored afterwards (the throughput measurement itself is stubbed; it is a GPU benchmark)."""
import json

import pytest

from envs.physics2d import fused
from experiments import bench_lander


def test_kernel_shape_parsing():
    assert bench_lander._kernel_shape("256x8") == (256, 8)
    assert bench_lander._kernel_shape("32X1") == (32, 1)
    for bad in ("100x4", "128x3", "128", "ax4", "0x4"):
        with pytest.raises(SystemExit, match="kernel-shapes"):
            bench_lander._kernel_shape(bad)


def test_each_row_runs_under_its_shape_and_the_default_comes_back(monkeypatch, tmp_path):
    seen = []

    def fake(batch, steps, continuous, unroll=1):
        seen.append((fused.BLOCK, fused.NUM_WARPS, batch))
        return dict(batch=batch, unroll=unroll, steps_per_s=1e6 * fused.BLOCK, compile_s=0.0)

    monkeypatch.setattr(bench_lander, "jax_throughput", fake)
    default = (fused.BLOCK, fused.NUM_WARPS)
    assert bench_lander.main(["--batches", "8,16", "--gym-seconds", "0", "--kernel-shapes", "64x2,256x8",
                              "--out", str(tmp_path)]) == 0
    assert seen == [(64, 2, 8), (64, 2, 16), (256, 8, 8), (256, 8, 16)]
    assert (fused.BLOCK, fused.NUM_WARPS) == default
    rows = json.loads((tmp_path / "bench_lander.json").read_text())["rows"]
    assert [(r["kernel_block"], r["kernel_warps"], r["steps_per_s"]) for r in rows] == [
        (64, 2, 64e6), (64, 2, 64e6), (256, 8, 256e6), (256, 8, 256e6)]


def test_the_record_says_where_when_and_how_it_was_measured(monkeypatch, tmp_path):
    monkeypatch.setattr(bench_lander, "jax_throughput",
                        lambda batch, steps, continuous, unroll=1: dict(batch=batch, steps_per_s=1.0, compile_s=0.0))
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/nowhere")
    bench_lander.main(["--batches", "8", "--gym-seconds", "0", "--out", str(tmp_path)])
    text = (tmp_path / "bench_lander.json").read_text()
    rec = json.loads(text)
    assert "NaN" not in text and rec["gym_steps_per_s"] is None  # no anchor: null, strict JSON
    assert rec["command"] == f"python -m experiments.bench_lander --batches 8 --gym-seconds 0 --out {tmp_path}"
    assert rec["device"].startswith("cpu: ") and rec["date"].endswith(" UTC") and "commit" in rec
    assert rec["xla_flags"].startswith("--xla_dump_to=/nowhere")
