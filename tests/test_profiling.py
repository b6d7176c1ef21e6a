"""shed_jax.profiling (a profiled call's summary), its command line experiments/trace_summary.py and
aot_cache's traced chunk calls: the summary's arithmetic on hand-made kernels, op names read from HLO
text, and a traced call on this host's CPU."""
import json

import jax
import jax.numpy as jnp
import pytest

from experiments import aot_cache, trace_summary
from shed_jax import profiling

HLO = """HloModule jit_f, entry_computation_layout={(f32[4]{0})->f32[4]{0}}

%fused_computation (p: f32[4]) -> f32[4] {
  %p = f32[4]{0} parameter(0)
  ROOT %sine.1 = f32[4]{0} sine(f32[4]{0} %p), metadata={op_name="jit(f)/beta/sin" source_file="x.py" source_line=3}
}

ENTRY %main (x: f32[4]) -> f32[4] {
  %x = f32[4]{0} parameter(0)
  %dot.2 = f32[4]{0} dot(f32[4]{0} %x, f32[4]{0} %x), metadata={op_name="jit(f)/alpha/dot_general" source_file="x.py"}
  ROOT %loop_fusion.7 = f32[4]{0} fusion(f32[4]{0} %dot.2), kind=kLoop, calls=%fused_computation, metadata={op_name="jit(f)/beta/sin"}
}
"""


def test_op_names_from_hlo_text():
    names = profiling.hlo_op_names(HLO)
    assert names == {"sine.1": "jit(f)/beta/sin", "dot.2": "jit(f)/alpha/dot_general",
                     "loop_fusion.7": "jit(f)/beta/sin"}


def test_user_scopes_leave_out_jax_words_and_wrappers():
    f = profiling.user_scopes
    assert f("jit(chunk)/vmap()/while/body/closed_call/evaluate/while/body/closed_call/vmap(velocity_passes)/add") == \
        ("evaluate", "velocity_passes")
    assert f("jit(f)/alpha/dot_general") == ("alpha",)
    assert f("jit(f)/jit(_where)/select_n") == ()
    assert f("jit(f)/transpose(jvp(ppo_update))/cond/branch_1_fun/ppo_update/mul") == ("ppo_update",)
    assert f("tanh") == ()


def test_merge_intervals():
    assert profiling.merge([[5, 7], [0, 2], [1, 3], [6, 9], [10, 11]]) == [[0, 3], [5, 9], [10, 11]]


def test_summary_of_hand_made_kernels():
    # two streams; times in ns: kernel A 0-1000 and 3000-4000, B 500-2000 on another stream, C 10000-10004
    events = [(0.0, 1000.0, "kA", "dot.2", "jit_f"), (3000.0, 1000.0, "kA", "dot.2", "jit_f"),
              (500.0, 1500.0, "kB", "loop_fusion.7", "jit_f"), (10000.0, 4.0, "kC", "copy.1", "jit_f")]
    s = profiling.summarise(events, profiling.hlo_op_names(HLO), scope_share=0.0)
    assert s["kernels"] == 4
    assert s["busy_s"] == pytest.approx(3504e-9)
    assert s["union_s"] == pytest.approx((2000 + 1000 + 4) * 1e-9)  # [0,2000], [3000,4000], [10000,10004]
    assert s["span_s"] == pytest.approx(10004e-9)
    assert s["idle_s"] == pytest.approx((10004 - 3004) * 1e-9)
    # gaps 1000 ns and 6000 ns: one in 0-2 us, one in 5-10 us
    assert s["gaps"] == {"0-2 us": {"count": 1, "ms": 0.001}, "5-10 us": {"count": 1, "ms": 0.006}}
    assert s["durations"]["0-2 us"]["count"] == 4
    top = {o["hlo_op"]: o for o in s["top_ops"]}
    assert top["dot.2"]["count"] == 2 and top["dot.2"]["ms"] == pytest.approx(0.002)
    assert top["loop_fusion.7"]["op_name"] == "jit(f)/beta/sin" and top["copy.1"]["op_name"] is None
    assert s["scopes"]["jit(f)/alpha"]["ms"] == pytest.approx(0.002)
    assert s["scopes"]["jit(f)/beta"]["ms"] == pytest.approx(0.0015)
    assert s["scopes"]["(no op_name)"]["kernels"] == 1
    assert s["named_scopes"]["alpha"]["ms"] == pytest.approx(0.002)
    assert s["named_scopes"]["beta"]["kernels"] == 1 and s["named_scopes"]["(none)"]["kernels"] == 1
    assert s["ops_with_op_name"] == 2 and s["ops"] == 3
    # dot.2 ran twice (2 us), the other two once each (1.5 us and 4 ns)
    assert s["by_calls"] == [{"calls": 2, "ops": 1, "kernels": 2, "ms": 0.002, "share": pytest.approx(0.57078, abs=1e-5)},
                             {"calls": 1, "ops": 2, "kernels": 2, "ms": 0.001504, "share": pytest.approx(0.42922, abs=1e-5)}]


def test_traced_call_profiles_one_call_and_keeps_results(tmp_path):
    def f(x):
        with jax.named_scope("alpha"):
            y = jnp.tanh(x @ x)
        with jax.named_scope("beta"):
            return jnp.sin(y).sum(0)

    out = tmp_path / "trace.json"
    said = []
    lower = aot_cache.traced_calls(lambda j, *a: j.lower(*a), 2, str(out), said.append)
    x = jnp.ones((256, 256))
    compiled = lower(jax.jit(f), x).compile()
    want = jax.jit(f)(x)
    for _ in range(4):
        assert jnp.array_equal(compiled(x), want)
    r = json.loads(out.read_text())
    assert r["traced_call"] == 2 and len(r["calls_wall_s"]) == 3  # calls 1-3 timed, the 4th untouched
    assert r["source"] == "host" and r["kernels"] >= 2
    assert r["union_s"] <= r["span_s"] + 1e-9 and r["busy_s"] > 0
    assert any(k.endswith("/alpha") for k in r["scopes"]), r["scopes"]
    assert r["named_scopes"]["alpha"]["ms"] > 0
    assert len(said) == 1 and "call 2 profiled" in said[0] and str(out) in said[0]


@pytest.mark.parametrize("call", [0, -1, 1.5, True])
def test_trace_count_takes_a_call_number(call, tmp_path):
    with pytest.raises(ValueError, match="whole number >= 1"):
        profiling.TraceCount(call, str(tmp_path / "x.json"))


@pytest.mark.parametrize("call,out,msg", [("0", "x.json", "call number from 1"), ("two", "x.json", "call number"),
                                          ("2", "", "needs AOT_TRACE_OUT")])
def test_trace_request_errors(monkeypatch, call, out, msg):
    monkeypatch.setenv("AOT_TRACE_CALL", call)
    monkeypatch.setenv("AOT_TRACE_OUT", out)
    with pytest.raises(ValueError, match=msg):
        aot_cache._trace_request()


def test_no_trace_request(monkeypatch):
    monkeypatch.delenv("AOT_TRACE_CALL", raising=False)
    monkeypatch.delenv("AOT_TRACE_OUT", raising=False)
    assert aot_cache._trace_request() is None


def test_labelled_loops_split_the_busy_time():
    summary = {"busy_s": 0.010, "by_calls": [{"calls": 4000, "ops": 2, "kernels": 8000, "ms": 6.0, "share": 0.6},
                                             {"calls": 384, "ops": 1, "kernels": 384, "ms": 3.0, "share": 0.3}]}
    out = profiling.labelled(summary, {4000: "evaluation"})
    assert out["by_calls"][0]["loop"] == "evaluation" and "loop" not in out["by_calls"][1]
    assert out["loops"]["evaluation"] == {"ops": 2, "kernels": 8000, "ms": 6.0, "share": 0.6}
    assert out["loops"]["(other, listed)"]["ms"] == 3.0
    assert out["loops"]["(other, below the listing's threshold)"]["ms"] == pytest.approx(1.0)


def test_cli_records_a_summary_and_rejects_bad_labels(tmp_path, capsys):
    src = tmp_path / "s.json"
    src.write_text(json.dumps({"busy_s": 0.002, "by_calls": [{"calls": 2, "ops": 1, "kernels": 2, "ms": 2.0, "share": 1.0}]}))
    out = tmp_path / "r.json"
    assert trace_summary.main([str(src), "--label", "2=twice", "--device", "cpu", "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["device"] == "cpu" and r["loops"]["twice"]["share"] == 1.0 and "recorded_by" in r
    assert trace_summary.main([str(src), "--label", "two=twice"]) == 2
    assert "CALLS=TEXT" in capsys.readouterr().err
    assert trace_summary.main([str(tmp_path / "missing")]) == 2
