"""experiments/hlo_launches.py: kernel launches counted from optimized HLO text, on a hand-written
module whose count is known: loops multiply, conditionals take their largest branch, bookkeeping
launches nothing, scopes come from op_name."""
import pytest

from experiments import hlo_launches as hl

HLO = """HloModule jit_run, entry_computation_layout={(f32[4]{0})->f32[4]{0}}

%fused_add (p0: f32[4]) -> f32[4] {
  %p0 = f32[4]{0} parameter(0)
  %x = f32[4]{0} add(%p0, %p0)
  %y = f32[4]{0} multiply(%x, %x)
}

%body (t: (s32[], f32[4])) -> (s32[], f32[4]) {
  %t = (s32[], f32[4]{0}) parameter(0)
  %i = s32[] get-tuple-element(%t), index=0
  %v = f32[4]{0} get-tuple-element(%t), index=1
  %f = f32[4]{0} fusion(%v), kind=kLoop, calls=%fused_add, metadata={op_name="jit(run)/while/body/vmap(time_of_impact)/vmap(jit(_where))/add"}
  %k = f32[4]{0} custom-call(%f), custom_call_target="__gpu$xla.gpu.triton", metadata={op_name="jit(run)/while/body/vmap(velocity_passes)/pallas_call"}
  %j = s32[] fusion(%i), kind=kLoop, calls=%fused_add, metadata={op_name="jit(run)/while/body/add"}
  ROOT %r = (s32[], f32[4]{0}) tuple(%j, %k)
}

%cond (t: (s32[], f32[4])) -> pred[] {
  %t = (s32[], f32[4]{0}) parameter(0)
  %i = s32[] get-tuple-element(%t), index=0
  ROOT %c = pred[] fusion(%i), kind=kLoop, calls=%fused_add, metadata={op_name="jit(run)/while/lt"}
}

%small (a: f32[4]) -> f32[4] {
  %a = f32[4]{0} parameter(0)
  ROOT %b = f32[4]{0} fusion(%a), kind=kLoop, calls=%fused_add, metadata={op_name="jit(run)/vmap(collide)/x"}
}

%big (a: f32[4]) -> f32[4] {
  %a = f32[4]{0} parameter(0)
  %b = f32[4]{0} fusion(%a), kind=kLoop, calls=%fused_add, metadata={op_name="jit(run)/vmap(collide)/x"}
  %c = f32[4]{0} copy(%b), metadata={op_name="jit(run)/vmap(collide)/y"}
  ROOT %d = f32[4]{0} fusion(%c), kind=kLoop, calls=%fused_add, metadata={op_name="jit(run)/vmap(collide)/z"}
}

%helper (a: f32[4]) -> f32[4] {
  %a = f32[4]{0} parameter(0)
  ROOT %b = f32[4]{0} sort(%a), dimensions={0}, metadata={op_name="jit(run)/vmap(lidar)/sort"}
}

ENTRY %main (x: f32[4]) -> f32[4] {
  %x = f32[4]{0} parameter(0)
  %z = s32[] constant(0)
  %t0 = (s32[], f32[4]{0}) tuple(%z, %x)
  %w = (s32[], f32[4]{0}) while(%t0), condition=%cond, body=%body, backend_config={"known_trip_count":{"n":"5"}}
  %v = f32[4]{0} get-tuple-element(%w), index=1
  %p = pred[] fusion(%v), kind=kLoop, calls=%fused_add, metadata={op_name="jit(run)/eq"}
  %b = f32[4]{0} conditional(%p, %v, %v), true_computation=%small, false_computation=%big
  %h = f32[4]{0} call(%b), to_apply=%helper
  %u = (s32[], f32[4]{0}) while(%t0), condition=%cond, body=%body
  ROOT %o = f32[4]{0} bitcast(%h)
}
"""


def test_launches_of_a_known_module():
    c = hl.count(HLO)
    # loop of 5: body 3 launches x 5, condition 1 x 6 = 21; the eq fusion 1; the conditional's larger
    # branch 3; the call's sort 1; the loop without a trip count once: 3 + 2 = 5
    assert c["total"] == 21 + 1 + 3 + 1 + 5
    assert c["by_op"] == {"fusion": 5 * 2 + 6 + 1 + 2 + (2 + 2), "custom-call": 5 + 1, "copy": 1, "sort": 1}
    assert c["unknown_trips"] == ["body"]


def test_launches_by_scope():
    s = hl.by_scope(HLO, depth=2)
    assert s == {"(no scope)": 5 + 6 + 1 + 1 + 2, "time_of_impact": 6, "velocity_passes": 6, "collide": 3, "lidar": 1}
    assert sum(s.values()) == hl.count(HLO)["total"]


def test_opcode_reads_past_nested_result_types():
    assert hl.opcode("  %w = (s32[], (f32[4]{0}, u32[2])) while(%t0), condition=%c, body=%b") == "while"
    assert hl.opcode("  %k = f32[4]{0} custom-call(%f), custom_call_target=\"x\"") == "custom-call"


def test_a_module_without_entry_is_refused():
    with pytest.raises(ValueError, match="no ENTRY"):
        hl.count("HloModule m\n%c (a: f32[]) -> f32[] {\n  ROOT %a = f32[] parameter(0)\n}\n")
