"""The scaling experiment's host-side arithmetic: GPU assignment, the record's speed-ups, and the
busy time of a profiler trace (the union of kernel intervals), on hand-made inputs."""
import gzip
import json

from experiments import scaling


def test_plan_spreads_workers_and_adds_the_baseline_where_asked():
    jobs = scaling.plan(scaling.parse_configs("dr:1024,dr:64@1"), [1, 2, 4], 4, ("dr", 1024, [2]))
    assert [(j["name"], j["gpus"], j["turn"]) for j in jobs] == [
        ("dr-1024-1gpu-new", [0], 0), ("dr-1024-2gpu-new", [0, 1], 1), ("dr-1024-2gpu-old", [0, 1], 2),
        ("dr-1024-4gpu-new", [0, 1, 2, 3], 3), ("dr-64-1gpu-new", [1], 4)]
    assert [j["devices"] for j in scaling.plan(scaling.parse_configs("dr:8"), [1, 2, 4], 2, None)] == [1, 2]


def test_record_speedups_are_against_the_same_run_on_one_gpu(tmp_path):
    for name, devices, tree, sec in (("a", 1, "new", 6.0), ("b", 2, "new", 4.0), ("c", 4, "new", 2.5), ("d", 2, "old", 5.0)):
        (tmp_path / f"dr-8-{devices}gpu-{tree}.json").write_text(json.dumps({
            "name": name, "method": "dr", "seeds": 8, "devices": devices, "tree": tree, "seconds_per_chunk": sec,
            "chunk_budget_steps": 2, "compile_s": 1.0, "write_s": [0.5], "final_step": 6,
            "final_test_return_mean": 1.0, "final_test_return_se": 0.1, "device_kind": "x", "jax": "y"}))
    rec = scaling.record(tmp_path, tmp_path / "out.json", "cmd")
    got = {(r["code"], r["devices"]): r["speedup"] for r in rec["rows"]}
    assert got == {("new", 1): 1.0, ("new", 2): 1.5, ("new", 4): 2.4, ("old", 2): None}
    assert json.loads((tmp_path / "out.json").read_text())["command"] == "cmd"


def _worker_file(d, method, seeds, devices, sec, checkpoint=True, tree="new"):
    d.mkdir(exist_ok=True)
    (d / f"{method}-{seeds}-{devices}gpu-{tree}.json").write_text(json.dumps({
        "name": f"{method}-{seeds}-{devices}gpu-{tree}", "method": method, "seeds": seeds, "devices": devices,
        "tree": tree, "seconds_per_chunk": sec, "chunk_budget_steps": 2, "compile_s": 1.0, "write_s": [0.5],
        "final_step": 6, "final_test_return_mean": 1.0, "final_test_return_se": 0.1, "checkpoint": checkpoint,
        "device_kind": "x", "jax": "y"}))


def test_record_keep_adds_a_run_and_keeps_the_rows_it_did_not_measure_again(tmp_path):
    to = tmp_path / "scaling.json"
    _worker_file(tmp_path / "r0", "dr", 8, 1, 6.0)
    _worker_file(tmp_path / "r0", "dr", 8, 2, 4.0)
    _worker_file(tmp_path / "r0", "shed", 8, 1, 9.0)
    scaling.record(tmp_path / "r0", to, "first")
    # the second run times DR on 2 GPUs again and SHED without checkpoints: a mode of its own
    _worker_file(tmp_path / "r1", "dr", 8, 1, 6.0)
    _worker_file(tmp_path / "r1", "dr", 8, 2, 3.0)
    _worker_file(tmp_path / "r1", "shed", 8, 1, 4.0, checkpoint=False)
    _worker_file(tmp_path / "r1", "shed", 8, 2, 2.5, checkpoint=False)
    rec = scaling.record(tmp_path / "r1", to, "second", keep=True)
    assert [r["command"] for r in rec["runs"]] == ["first", "second"]
    got = {(r["method"], r["devices"], r["checkpoint"]): (r["seconds_per_chunk"], r["speedup"], r["run"])
           for r in rec["rows"]}
    assert got == {("dr", 1, True): (6.0, 1.0, 1), ("dr", 2, True): (3.0, 2.0, 1),
                   ("shed", 1, True): (9.0, 1.0, 0),              # kept: not measured again
                   ("shed", 1, False): (4.0, 1.0, 1), ("shed", 2, False): (2.5, 1.6, 1)}  # against 4.0, not 9.0
    assert len(rec["rows"]) == 5
    # without keep, the record is this run's alone
    assert len(scaling.record(tmp_path / "r1", to, "third")["rows"]) == 4


def test_trace_busy_time_is_the_union_of_kernel_intervals(tmp_path):
    events = [{"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
              {"ph": "M", "name": "process_name", "pid": 2, "args": {"name": "/host:CPU"}},
              {"ph": "X", "pid": 1, "ts": 0, "dur": 10, "name": "k1"},
              {"ph": "X", "pid": 1, "ts": 5, "dur": 10, "name": "k2"},   # overlaps k1: busy 0..15
              {"ph": "X", "pid": 1, "ts": 30, "dur": 10, "name": "k1"},  # busy 30..40, a gap of 15
              {"ph": "X", "pid": 2, "ts": 0, "dur": 100, "name": "host"}]
    d = tmp_path / "plugins" / "profile" / "run"
    d.mkdir(parents=True)
    with gzip.open(d / "perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    gpu = scaling.trace_summary(tmp_path, wall=1.0)["gpus"]["/device:GPU:0"]
    assert gpu["events"] == 3
    assert abs(gpu["kernel_s"] - 30e-6) < 1e-12 and abs(gpu["busy_s"] - 25e-6) < 1e-12 and abs(gpu["span_s"] - 40e-6) < 1e-12
    assert gpu["top"][0] == ["k1", 20e-6]
