"""experiments.suite_compile_times: JAX's timing lines summed per test, and the summary's totals."""
import logging

from experiments import suite_compile_times as sct


def test_timing_lines_are_summed_per_test_and_split_by_size(monkeypatch):
    monkeypatch.setattr(sct, "_times", {})
    handler = sct._Timings()
    log = lambda msg: handler.emit(logging.makeLogRecord({"msg": msg}))  # noqa: E731
    sct._current["test"] = "a"
    log("Finished tracing run for jit in 1.5 sec")
    log("Finished jaxpr to MLIR module conversion jit(run) in 0.25 sec")
    log("Finished XLA compilation of jit(run) in 3.0 sec")
    log("Finished XLA compilation of jit(add) in 0.05 sec")
    log("Compiling something else")  # not a timing line
    sct._current["test"] = "b"
    log("Finished XLA compilation of jit(run) in 2.5 sec")
    a, b = sct._times["a"], sct._times["b"]
    assert (a["trace"], a["lower"], a["compile"], a["compiles"]) == (1.5, 0.25, 3.05, 2)
    assert a["big"] == [("jit(run)", 3.0)] and b["big"] == [("jit(run)", 2.5)]
    a["wall"], b["wall"] = 5.0, 3.0
    s = sct.summary(sct._times)
    assert s["wall"] == 8.0 and s["compiles"] == 3 and s["big_compiles"] == 2
    assert abs(s["big"] - 5.5) < 1e-9 and abs(s["small"] - 0.05) < 1e-9
    assert s["by_name"] == {"jit(run)": [5.5, 2]}
