"""experiments/gpu_compile.py reads ptxas' report of each Pallas kernel out of XLA's log (the compile
itself needs the CUDA plugin and runs on a CPU host by hand)."""
import pytest

from experiments import gpu_compile

# XLA's log of one compile, abridged: an XLA fusion, then two Pallas kernels (XLA names them 'kernel', 'kernel__1', ...)
LOG = """\
I1205 00:04:18.0 subprocess_compilation.cc:356] ptxas info    : 0 bytes gmem
ptxas info    : Compiling entry function 'loop_pad_fusion' for 'sm_90a'
ptxas info    : Function properties for loop_pad_fusion
    0 bytes stack frame, 0 bytes spill stores, 0 bytes spill loads
ptxas info    : Used 11 registers, used 0 barriers
I1205 00:04:18.8 subprocess_compilation.cc:349] ptxas warning : Registers are spilled to local memory in \
function 'kernel', 928 bytes spill stores, 936 bytes spill loads
ptxas info    : 0 bytes gmem
ptxas info    : Compiling entry function 'kernel' for 'sm_90a'
ptxas info    : Function properties for kernel
    1176 bytes stack frame, 928 bytes spill stores, 936 bytes spill loads
ptxas info    : Used 255 registers, used 0 barriers, 1176 bytes cumulative stack size
ptxas info    : Compile time = 378.583 ms
I1205 00:04:29.0 subprocess_compilation.cc:356] ptxas info    : 0 bytes gmem
ptxas info    : Compiling entry function 'kernel__10' for 'sm_90a'
ptxas info    : Function properties for kernel__10
    32 bytes stack frame, 0 bytes spill stores, 0 bytes spill loads
ptxas info    : Used 243 registers, used 1 barriers, 32 bytes cumulative stack size
"""


def test_ptxas_report_reads_each_pallas_kernel_and_skips_xla_fusions():
    assert gpu_compile.ptxas_report(LOG) == [
        {"kernel": "kernel", "registers": 255, "spill_stores": 928, "spill_loads": 936, "stack_frame": 1176},
        {"kernel": "kernel__10", "registers": 243, "spill_stores": 0, "spill_loads": 0, "stack_frame": 32},
    ]
    assert gpu_compile.ptxas_report("no kernels compiled") == []


def test_compile_counts_a_programs_launches_per_budget_step(capsys):
    """A program of three budget steps, each a loop of 4 trips over one kernel: the launches per
    budget step are the HLO count over 3, whatever the host compiles for."""
    import jax
    import jax.numpy as jnp

    from experiments import hlo_launches

    def chunk(x):
        def budget_step(x, _):
            with jax.named_scope("evaluate"):
                x = jax.lax.fori_loop(0, 4, lambda i, y: jnp.sin(y) * 2.0 + i, x)
            return x, None
        return jax.lax.scan(budget_step, x, None, length=3)[0]

    lower = lambda: jax.jit(chunk).trace(jnp.ones(8)).lower()  # noqa: E731
    row = gpu_compile._compile("chunk of 3", lower, launches_depth=2, per=3)
    text = lower().compile().as_text()
    total = hlo_launches.count(text)["total"]
    assert row["launches"]["per"] == 3 and row["launches"]["total"] == round(total / 3, 1)
    assert row["launches"]["unknown_trips"] == 0
    assert sum(row["launches"]["by_scope"].values()) == pytest.approx(row["launches"]["total"], abs=0.2)
    # (how XLA fuses the loop, and so the count and the scopes' names, depends on the process's compiler
    # state: a full suite's worker counted it otherwise than a lone run, so only the arithmetic is asserted)
    assert "launches" not in capsys.readouterr().out  # the printed line stays short
    assert "launches" not in gpu_compile._compile("x", lower)
