"""The XLA:CPU hang guards only add XLA flags the user has not set either way."""
from shed_jax import xla_cpu


def test_guard_adds_missing_flags_and_respects_the_users(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    xla_cpu.apply_cpu_guard()
    assert xla_cpu.FLAGS == ("--xla_cpu_multi_thread_eigen=false", "--xla_cpu_use_xnnpack=false")
    import os

    assert os.environ["XLA_FLAGS"].split() == list(xla_cpu.FLAGS)
    # a user's own value of an option stays, and other flags are kept in front
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4 --xla_cpu_use_xnnpack=true")
    xla_cpu.apply_cpu_guard()
    assert os.environ["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=4", "--xla_cpu_use_xnnpack=true",
                                               "--xla_cpu_multi_thread_eigen=false"]
    xla_cpu.apply_cpu_guard()  # idempotent
    assert os.environ["XLA_FLAGS"].count("xla_cpu_multi_thread_eigen") == 1
