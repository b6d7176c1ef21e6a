"""experiments/gpu_compile.py reads ptxas' report of each Pallas kernel out of XLA's log (the compile
itself needs the CUDA plugin and runs on a CPU host by hand)."""
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
