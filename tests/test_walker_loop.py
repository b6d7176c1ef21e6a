"""experiments.walker_loop's arithmetic: the protocol estimate from per-kind step times, and the
flat-level PPO record read from a bench_ppo results file (hand-computed cases)."""
import json

import pytest

from experiments import walker_loop
from shed_jax.loop import LoopSpec


def test_protocol_estimate_counts_each_kind_of_step():
    # 3 episodes of 4 steps, the test set in episodes 0 and 2 (the last): 8 tested steps, 3 starts
    spec = LoopSpec(steps_per_episode=4, num_episodes=3, test_episode_every=2)
    est = walker_loop.protocol_estimate(spec, {"plain": 1.0, "tested": 3.0, "episode_start": 1.5})
    assert est["total_steps"] == 12 and est["tested_steps"] == 8
    assert est["protocol_s_estimate"] == pytest.approx(12 * 1.0 + 8 * 2.0 + 3 * 0.5)
    assert est["budget_step_s_mean"] == pytest.approx(29.5 / 12)
    # a schedule that tests every step has no plain step to time: every step costs "tested"
    every = LoopSpec(steps_per_episode=5, num_episodes=1)
    assert walker_loop.protocol_estimate(every, {"tested": 2.0})["protocol_s_estimate"] == pytest.approx(10.0)


def test_ppo_flat_record(tmp_path):
    evals = [{"env_steps_per_seed": 2_000_000, "per_seed": [100.0, 240.0, 250.0]},
             {"env_steps_per_seed": 4_000_000, "per_seed": [200.0, 231.0, 260.0]},
             {"env_steps_per_seed": 6_000_000, "per_seed": [229.0, 235.0, 262.0]},
             {"env_steps_per_seed": 12_000_000, "per_seed": [240.0, 235.0, 262.0]}]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"device": "H200", "date": "2026-11-25", "command": "x",
                                "sections": {"walker": {"evals": evals}}}))
    r = walker_loop.ppo_flat(str(path))
    assert r["seeds"] == 3 and r["eval_median"] == [240.0, 231.0, 235.0, 240.0]
    assert r["median_steps_to_230"] == 2_000_000  # median 240 >= 230 at the first evaluation
    assert r["seeds_at_230_by_10M"] == 2  # the first seed reaches 230 only at 12M
    assert r["source"]["device"] == "H200"


def test_record_composed_from_measured_parts(tmp_path):
    loops = {"device": "NVIDIA H200", "date": "2026-11-25", "command": "python -m experiments.walker_loop",
             "loops": {"dr": {"budget_step_s_mean": 21.0}}, "budget_step_seconds": {"dr": 21.0}}
    ppo = {"device": "NVIDIA H200", "date": "2026-11-25", "command": "bench",
           "sections": {"walker": {"evals": [{"env_steps_per_seed": 1_000_000, "per_seed": [240.0, 250.0]}]}}}
    (tmp_path / "loops.json").write_text(json.dumps(loops))
    (tmp_path / "ppo.json").write_text(json.dumps(ppo))
    out = tmp_path / "record.json"
    assert walker_loop.main(["--loops-from", str(tmp_path / "loops.json"), "--ppo-results", str(tmp_path / "ppo.json"),
                             "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["device"] == "NVIDIA H200" and rec["date"] == "2026-11-25"  # the measurement's, not today's machine
    assert rec["budget_step_seconds"] == {"dr": 21.0} and rec["loops_source"]["command"] == loops["command"]
    assert rec["ppo_flat"]["median_steps_to_230"] == 1_000_000 and rec["named_solved_rate"] is None
