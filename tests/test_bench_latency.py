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
    assert rec["step"] == "step"


def test_bench_latency_without_reset_names_its_step(tmp_path, monkeypatch):
    import envs
    env = envs.make("cartpole")
    used = []
    made = []
    monkeypatch.setattr(envs, "make", lambda *a, **k: made.append((a, k)) or env)
    monkeypatch.setattr(bench_latency, "env_latency", lambda e, b, n, fn: used.append(fn) or dict(batch=b, steps=n))
    bench_latency.main(["--env", "cartpole", "--batches", "4", "--skip-student", "--step", "without-reset",
                        "--terrain-unroll", "8", "--out", str(tmp_path)])
    assert used == [env.step_without_reset]
    assert made == [(("cartpole",), {"terrain_unroll": 8})]  # the env refuses an option it lacks (not checked here)
    rec = json.loads((tmp_path / "latency_u1.json").read_text())
    assert rec["step"] == "without-reset" and rec["terrain_unroll"] == 8


def test_bench_latency_passes_and_records_student_overrides(tmp_path, monkeypatch, capsys):
    import pytest
    seen = []
    monkeypatch.setattr(bench_latency, "env_latency", lambda e, b, n, fn: dict(batch=b, steps=n))
    monkeypatch.setattr(bench_latency, "student_latency", lambda e, name, ppo, parts: seen.append((name, ppo, parts)) or {"ppo_update_s": 1.0})
    argv = ["--env", "cartpole", "--batches", "4", "--ppo", "reset_draw=per_rollout", "num_envs=8", "--out", str(tmp_path)]
    assert bench_latency.main(argv) == 0
    assert seen == [("cartpole", {"reset_draw": "per_rollout", "num_envs": 8}, ("update", "eval"))]
    rec = json.loads((tmp_path / "latency_u1.json").read_text())
    assert rec["ppo_overrides"] == {"reset_draw": "per_rollout", "num_envs": 8} and rec["ppo_update_s"] == 1.0
    # a bad override stops in one line before any work (and writes nothing)
    with pytest.raises(SystemExit):
        bench_latency.main(["--env", "cartpole", "--ppo", "reset_draw=once", "--out", str(tmp_path / "bad")])
    assert "PPOConfig.reset_draw must be one of 'per_step', 'per_rollout', got 'once'" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    with pytest.raises(SystemExit):
        bench_latency.main(["--env", "cartpole", "--student", "rollout,train", "--out", str(tmp_path / "bad")])
    assert "--student takes a comma-separated list of rollout, update, eval, got 'rollout,train'" in capsys.readouterr().err


def test_student_latency_times_the_parts_asked_for():
    import envs
    env = envs.make("cartpole")
    out = bench_latency.student_latency(env, "cartpole", {"num_envs": 4, "num_steps": 8, "reset_draw": "per_rollout"}, ("rollout",))
    assert set(out) == {"rollout_s", "rollout_compile_s", "num_envs", "num_steps"}
    assert out["rollout_s"] > 0 and out["rollout_compile_s"] > 0 and (out["num_envs"], out["num_steps"]) == (4, 8)


def test_bipedal_speed_fields_from_latency_records(tmp_path):
    from experiments import bipedal_speed

    def latency(name, rows, env="bipedal", **solver):
        path = tmp_path / name
        path.write_text(json.dumps({"env": env, "device": "gpu: X", "date": "d", "command": "c", **solver,
                                    "env_rows": [dict(batch=b, steps=10, compile_s=1.0, s_per_step=s) for b, s in rows]}))
        return str(path)

    a = latency("a.json", [(200, 0.0084)])
    b = latency("b.json", [(200, 0.0080), (65536, 0.05)])
    # fewer solver passes than Box2D's: a row of the record, never a headline figure
    c = latency("c.json", [(200, 0.006), (65536, 0.01)], velocity_iterations=1, position_iterations=1)
    d = latency("d.json", [(200, 0.004)], step="without-reset")
    out = tmp_path / "bipedal.json"
    out.write_text(json.dumps({"parity": {"flat": {"pass": True}}}))
    assert bipedal_speed.main([a, b, c, d, "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["parity"] == {"flat": {"pass": True}}  # the other keys stay
    assert abs(rec["ms_per_step_batch200"] - 8.0) < 1e-9  # the better of the two batch-200 rows at Box2D's passes
    assert abs(rec["steps_per_second_best"] - 65536 / 0.05) < 1e-6
    rows = rec["speed"]["rows"]
    assert len(rows) == 6 and rows[0]["device"] == "gpu: X"
    assert [(r["velocity_iterations"], r["position_iterations"]) for r in rows] == [(180, 60)] * 3 + [(1, 1)] * 2 + [(180, 60)]
    assert [r["step"] for r in rows] == ["step"] * 5 + ["without-reset"]
    assert rec["speed"]["student_rows"] == []  # no record timed the student
    # profile_bipedal_step records: their "default" variant's rows (others change the solver); a full
    # env.step row counts for the headline, a reset-only one does not
    prof = tmp_path / "p.json"
    prof.write_text(json.dumps({"device": "gpu: Y", "date": "d", "step": "step",
                                "command": "python -m experiments.profile_bipedal_step --step step --batches 200",
                                "rows": [dict(variant="default", batch=200, steps=10, compile_s=2.0, ms_per_step=3.0,
                                              steps_per_second=200 / 0.003),
                                         dict(variant="passes_1_1", batch=200, steps=10, compile_s=2.0, ms_per_step=1.0,
                                              steps_per_second=200 / 0.001)]}))
    reset = tmp_path / "r.json"
    reset.write_text(prof.read_text().replace('"step": "step"', '"step": "reset"'))
    assert bipedal_speed.main([a, str(prof), str(reset), "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["ms_per_step_batch200"] == 3.0 and [r["step"] for r in rec["speed"]["rows"]] == ["step", "step", "reset"]
    assert bipedal_speed.main([a, b, c, d, "--out", str(out)]) == 0
    # student parts (bench_latency --student): a rollout whose record keeps its shape, and an older
    # record without it, whose shape is today's preset with its overrides
    e = tmp_path / "e.json"
    e.write_text(json.dumps({"env": "bipedal", "device": "gpu: X", "date": "d", "command": "c", "env_rows": [],
                             "num_envs": 8, "num_steps": 4, "rollout_s": 0.5, "rollout_compile_s": 3.0,
                             "ppo_update_s": 2.0, "ppo_compile_s": 9.0, "ppo_overrides": {"reset_draw": "per_rollout"}}))
    f = tmp_path / "f.json"
    f.write_text(json.dumps({"env": "bipedal", "env_rows": [], "rollout_s": 0.25, "rollout_compile_s": 1.0,
                             "ppo_overrides": {"num_envs": 16}}))
    assert bipedal_speed.main([b, str(e), str(f), "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert abs(rec["ms_per_step_batch200"] - 8.0) < 1e-9 and len(rec["speed"]["rows"]) == 2
    srows = rec["speed"]["student_rows"]
    assert [(r["part"], r["s"], r["num_envs"], r["num_steps"], r["shape_from"]) for r in srows] == [
        ("rollout", 0.5, 8, 4, "record"), ("update", 2.0, 8, 4, "record"), ("rollout", 0.25, 16, 64, "preset")]
    assert srows[0]["env_steps_per_second"] == 64.0 and srows[1]["env_steps_per_second"] == 16.0
    assert srows[2]["env_steps_per_second"] == 16 * 64 / 0.25 and srows[1]["ppo_overrides"] == {"reset_draw": "per_rollout"}
    # a record of another env, or student timings alone (no batch rows for the headline), are refused
    import pytest
    with pytest.raises(SystemExit):
        bipedal_speed.main([str(e), "--out", str(out)])
    assert json.loads(out.read_text()) == rec  # the record is left as it was
    with pytest.raises(SystemExit):
        bipedal_speed.main([latency("c.json", [(200, 0.001)], env="lander"), "--out", str(out)])
