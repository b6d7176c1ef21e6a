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
    frames = jax.config.jax_traceback_in_locations_limit
    yield
    jax.config.update("jax_include_full_tracebacks_in_locations", before)
    jax.config.update("jax_traceback_in_locations_limit", frames)


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
    jax.config.update("jax_traceback_in_locations_limit", kernel_census.DEFAULT_FRAMES)
    monkeypatch.setenv("JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS", "1")
    assert runtime.call_site_free_locations() is False
    assert jax.config.jax_include_full_tracebacks_in_locations is True
    assert jax.config.jax_traceback_in_locations_limit == kernel_census.DEFAULT_FRAMES


def test_one_frame_locations_keep_the_name_stack(locations, monkeypatch):
    """``call_site_free_locations`` cuts locations to one frame and keeps JAX's name stack in the
    compiled HLO's op names (a profile's only way to tell a program's parts apart by name); turning
    tracebacks off instead drops it."""
    import re

    import jax.numpy as jnp

    def f(x):
        with jax.named_scope("alpha"):
            return jnp.tanh(x @ x)

    def op_names():
        jax.clear_caches()
        # the persistent cache's keys ignore metadata: a hit would return the other setting's names
        cached = jax.config.jax_enable_compilation_cache
        jax.config.update("jax_enable_compilation_cache", False)
        try:
            text = jax.jit(f).lower(jnp.ones((4, 4))).compile().as_text()
        finally:
            jax.config.update("jax_enable_compilation_cache", cached)
        return set(re.findall(r'op_name="([^"]*)"', text)) - {"x"}

    monkeypatch.delenv("JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS", raising=False)
    monkeypatch.delenv("JAX_TRACEBACK_IN_LOCATIONS_LIMIT", raising=False)
    assert runtime.call_site_free_locations() is True
    assert jax.config.jax_traceback_in_locations_limit == 1 and not runtime.call_stacks_in_locations()
    assert op_names() == {"jit(f)/alpha/dot_general", "jit(f)/alpha/tanh"}
    jax.config.update("jax_include_full_tracebacks_in_locations", False)
    assert op_names() == {"dot_general", "tanh"}


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


def _two_batch_program(worlds_a: int, worlds_b: int) -> str:
    """The CUDA lowering of one small fused loop run at two batches of worlds (an evaluation's and a
    training rollout's, say), as text."""
    import jax.numpy as jnp

    body = lambda c, s: s * c["a"] + 1.0  # noqa: E731
    loop = lambda a, x: fused.per_world_fori_loop(3, body, {"a": a}, x)  # noqa: E731

    def program(a1, x1, a2, x2):
        return jax.vmap(loop)(a1, x1).sum() + jax.vmap(loop)(a2, x2).sum()

    args = [jnp.zeros((w,), jnp.float32) for w in (worlds_a, worlds_a, worlds_b, worlds_b)]
    with fused.auto_as("pallas"):
        return jax.jit(program).trace(*args).lower(lowering_platforms=("cuda",)).as_text()


def test_padding_to_the_largest_batch_makes_one_kernel_of_two(locations):
    """A loop at 200 and at 5,000 worlds is two grids (8 and 40 blocks) and two Triton compiles under
    the default padding, one once kernels are padded to the larger batch; the setting is process-wide,
    never below the default, and a bad value is one line."""
    runtime.call_site_free_locations()
    before = fused.MIN_WORLDS
    try:
        assert fused.pad_worlds_to(10) == fused.DEFAULT_MIN_WORLDS == fused.MIN_WORLDS
        two = kernel_census.census(kernel_census.triton_calls(_two_batch_program(200, 5000)))
        assert two["triton_calls"] == 2 and two["distinct_by_grid_x"] == {"8": 1, "40": 1}
        assert runtime.pad_kernels_to(5000) == 5000 == fused.MIN_WORLDS
        one = kernel_census.census(kernel_census.triton_calls(_two_batch_program(200, 5000)))
        assert one == {"triton_calls": 2, "triton_kernels_distinct": 1, "distinct_by_grid_x": {"40": 1}}
        with pytest.raises(ValueError, match="pad_worlds_to needs a whole number of worlds >= 1, got 0"):
            fused.pad_worlds_to(0)
        assert fused.MIN_WORLDS == 5000
    finally:
        fused.MIN_WORLDS = before


def test_a_run_pads_to_its_devices_training_batch():
    """``driver.kernel_worlds``: runs on a device x the student's training envs (all K students' for a pool)."""
    from experiments import checkpoint_size as cs
    from shed_jax import driver, sharding
    from shed_jax.methods.parallel_students import StudentPool

    _, batch = cs.build_batch("lander", "dr", "quick", 3)
    placed = driver.place(batch, sharding.batch_mesh(jax.devices()[:1]))
    assert batch.student.train_envs == batch.student.config.num_envs
    assert driver.kernel_worlds(batch, placed) == 3 * batch.student.config.num_envs
    assert StudentPool(batch.student, 4).train_envs == 4 * batch.student.config.num_envs


def test_a_resume_with_no_chunk_left_still_pads_its_final_evaluations_kernels():
    """A run resumed after its last budget step compiles no chunk, but lowers its final evaluation next:
    its kernels are padded as the run's others (else another program, and its cache entry missed)."""
    from experiments import checkpoint_size as cs
    from shed_jax import driver, sharding

    _, batch = cs.build_batch("lander", "dr", "quick", 3)
    placed = driver.place(batch, sharding.batch_mesh(jax.devices()[:1]))
    before = fused.MIN_WORLDS
    try:
        fused.MIN_WORLDS = 7  # not what the run pads to
        state, compiled = driver.compile_batch(batch, placed, batch.total, state={"kept": 1}, say=lambda _: None)
        assert state == {"kept": 1} and compiled == {}
        assert fused.MIN_WORLDS == max(driver.kernel_worlds(batch, placed), fused.DEFAULT_MIN_WORLDS)
    finally:
        fused.MIN_WORLDS = before
