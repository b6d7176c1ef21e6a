"""``experiments.bench_latency`` writes a record that says where, how and when it was measured."""
import json

from experiments import bench_latency


def test_bench_latency_record(tmp_path):
    argv = ["--env", "cartpole", "--batches", "4,8", "--steps", "3", "--skip-student", "--out", str(tmp_path)]
    assert bench_latency.main(argv) == 0
    rec = json.loads((tmp_path / "latency_u1.json").read_text())
    assert rec["device"].startswith("cpu: ") and rec["date"].endswith(" UTC")
    assert rec["command"] == "python -m experiments.bench_latency " + " ".join(argv)
    assert [r["batch"] for r in rec["env_rows"]] == [4, 8]
    assert all(r["steps"] == 3 and r["s_per_step"] > 0 and r["compile_s"] > 0 for r in rec["env_rows"])


def test_bipedal_speed_fields_from_latency_records(tmp_path):
    from experiments import bipedal_speed

    def latency(name, rows, env="bipedal"):
        path = tmp_path / name
        path.write_text(json.dumps({"env": env, "device": "gpu: X", "date": "d", "command": "c",
                                    "env_rows": [dict(batch=b, steps=10, compile_s=1.0, s_per_step=s) for b, s in rows]}))
        return str(path)

    a = latency("a.json", [(200, 0.0084)])
    b = latency("b.json", [(200, 0.0080), (65536, 0.05)])
    out = tmp_path / "bipedal.json"
    out.write_text(json.dumps({"parity": {"flat": {"pass": True}}}))
    assert bipedal_speed.main([a, b, "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["parity"] == {"flat": {"pass": True}}  # the other keys stay
    assert abs(rec["ms_per_step_batch200"] - 8.0) < 1e-9  # the better of the two batch-200 rows
    assert abs(rec["steps_per_second_best"] - 65536 / 0.05) < 1e-6
    assert len(rec["speed"]["rows"]) == 3 and rec["speed"]["rows"][0]["device"] == "gpu: X"
    # a record of another env is refused with one line
    import pytest
    with pytest.raises(SystemExit):
        bipedal_speed.main([latency("c.json", [(200, 0.001)], env="lander"), "--out", str(out)])
