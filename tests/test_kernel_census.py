"""experiments.kernel_census and the locations it depends on: a fused loop called from two places is
one Triton kernel for XLA only when MLIR locations leave out the call stack
(``runtime.call_site_free_locations``); ``fused.auto_as`` lowers a GPU's kernels on any host."""
import jax
import pytest

from envs.physics2d import fused
from experiments import kernel_census
from shed_jax import runtime


@pytest.fixture
def locations():
    before = jax.config.jax_include_full_tracebacks_in_locations
    yield
    jax.config.update("jax_include_full_tracebacks_in_locations", before)


def test_call_stacks_in_locations_split_each_kernel_by_call_site(locations, monkeypatch):
    """The lander's DR chunk (quick preset, 2 seeds): its fused loops run at a level assignment's
    reset, in the training rollout and in the test set. With JAX's default locations every call is a
    kernel of its own; with the innermost user frame only, calls of one loop at one grid share one."""
    monkeypatch.delenv("JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS", raising=False)
    jax.config.update("jax_include_full_tracebacks_in_locations", True)
    full = kernel_census.measure("lander", "dr", "quick", 2, full_tracebacks=True)
    assert full["full_tracebacks_in_locations"] is True and full["min_worlds"] == fused.MIN_WORLDS
    assert full["triton_calls"] >= 6 and full["triton_kernels_distinct"] == full["triton_calls"]
    short = kernel_census.measure("lander", "dr", "quick", 2)
    assert short["full_tracebacks_in_locations"] is False
    assert short["triton_calls"] == full["triton_calls"]
    assert short["triton_kernels_distinct"] <= full["triton_calls"] - 2
    assert jax.config.jax_include_full_tracebacks_in_locations is True  # measure() leaves the setting as it was


def test_an_explicit_environment_setting_wins(locations, monkeypatch):
    jax.config.update("jax_include_full_tracebacks_in_locations", True)
    monkeypatch.setenv("JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS", "1")
    assert runtime.call_site_free_locations() is False
    assert jax.config.jax_include_full_tracebacks_in_locations is True


def test_auto_as_is_scoped_and_checked():
    assert fused.resolve_mode("auto") == "xla"  # the suite runs on a CPU
    with fused.auto_as("interpret"):
        assert fused.resolve_mode("auto") == "interpret" and fused.resolve_mode("xla") == "xla"
        with fused.auto_as("pallas"):
            assert fused.resolve_mode("auto") == "pallas"
        assert fused.resolve_mode("auto") == "interpret"
    assert fused.resolve_mode("auto") == "xla"
    with pytest.raises(ValueError, match="auto_as needs one of"):
        with fused.auto_as("auto"):
            pass


def test_parser_reads_grid_and_ir_of_each_call():
    text = ('%1 = stablehlo.custom_call @__gpu$xla.gpu.triton(%0) {mhlo.backend_config = {debug = false, '
            'grid_x = 40 : i32, grid_y = 1 : i32, grid_z = 1 : i32, ir = "ML\\EFR\\22x", name = "kernel", '
            'num_warps = 4 : i32}} : (tensor<8xf32>) -> tensor<8xf32>\n'
            '%2 = stablehlo.custom_call @__gpu$xla.gpu.triton(%1) {mhlo.backend_config = {debug = false, '
            'grid_x = 40 : i32, grid_y = 1 : i32, grid_z = 1 : i32, ir = "ML\\EFR\\22x", name = "kernel", '
            'num_warps = 4 : i32}} : (tensor<8xf32>) -> tensor<8xf32>\n'
            '%3 = stablehlo.custom_call @__gpu$xla.gpu.triton(%2) {mhlo.backend_config = {debug = false, '
            'grid_x = 2 : i32, grid_y = 1 : i32, grid_z = 1 : i32, ir = "other", name = "kernel"}}\n')
    calls = kernel_census.triton_calls(text)
    assert [c["grid_x"] for c in calls] == [40, 40, 2]
    assert calls[0] == calls[1] and calls[0]["num_warps"] == 4 and "num_warps" not in calls[2]
    assert calls[0]["ir_sha256"] != calls[2]["ir_sha256"]
    assert kernel_census.census(calls) == {"triton_calls": 3, "triton_kernels_distinct": 2,
                                           "distinct_by_grid_x": {"2": 1, "40": 1}}


def test_bad_seeds_and_padding_are_one_line(capsys):
    assert kernel_census.main(["--seeds", "0"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == ["kernel_census: --seeds must be at least 1, got 0"]
    assert kernel_census.main(["--min-worlds", "0"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == ["kernel_census: --min-worlds must be at least 1, got 0"]
