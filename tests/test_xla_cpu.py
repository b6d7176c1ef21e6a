"""The XLA:CPU deadlock guard (shed_jax/xla_cpu.py): it sets NPROC and the flags unless the user
did, and with it a loop of vmapped orthogonal inits -- concurrent batched LAPACK QRs, which hung
the 2-core machine's default two-thread pool in 5 of 5 tries within 300 calls -- finishes."""
import os
import subprocess
import sys
import textwrap

from shed_jax import xla_cpu


def test_guard_adds_missing_settings_and_respects_the_users(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.delenv("NPROC", raising=False)
    xla_cpu.apply_cpu_guard()
    assert xla_cpu.FLAGS == ("--xla_cpu_multi_thread_eigen=false", "--xla_cpu_use_xnnpack=false")
    assert os.environ["XLA_FLAGS"].split() == list(xla_cpu.FLAGS)
    assert os.environ["NPROC"] == str(max(64, os.cpu_count()))
    # a user's own value of an option stays, and other flags are kept in front
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4 --xla_cpu_use_xnnpack=true")
    monkeypatch.setenv("NPROC", "12")
    xla_cpu.apply_cpu_guard()
    assert os.environ["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=4", "--xla_cpu_use_xnnpack=true",
                                               "--xla_cpu_multi_thread_eigen=false"]
    assert os.environ["NPROC"] == "12"
    xla_cpu.apply_cpu_guard()  # idempotent
    assert os.environ["XLA_FLAGS"].count("xla_cpu_multi_thread_eigen") == 1


# eight independent batched QRs per call; a fresh process, so the guard runs before JAX starts
_STRESS = textwrap.dedent("""
    from shed_jax.xla_cpu import apply_cpu_guard
    apply_cpu_guard()
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    class Wide(nn.Module):
        @nn.compact
        def __call__(self, x):
            return sum(nn.Dense(32, kernel_init=nn.initializers.orthogonal())(x) for _ in range(8))

    init = jax.jit(jax.vmap(lambda k: Wide().init(k, jnp.zeros((1, 32)))))
    for i in range(300):
        jax.block_until_ready(init(jax.random.split(jax.random.PRNGKey(i), 16)))
    print("finished")
""")


def test_concurrent_batched_lapack_calls_finish_under_the_guard():
    env = {k: v for k, v in os.environ.items() if k not in ("NPROC", "XLA_FLAGS")}
    env["JAX_PLATFORMS"] = "cpu"
    try:
        out = subprocess.run([sys.executable, "-c", _STRESS], env=env, capture_output=True, text=True, timeout=150)
    except subprocess.TimeoutExpired:
        raise AssertionError("vmapped orthogonal inits deadlocked XLA:CPU despite the guard (shed_jax/xla_cpu.py)")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("finished")
