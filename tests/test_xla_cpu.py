"""The XLA:CPU deadlock (shed_jax/xla_cpu.py): the old flag guard only adds flags the user has not
set, and vmapped student inits -- which with the library's LAPACK QR hung a two-thread pool in 3
of 3 tries -- finish with our orthogonal initializer."""
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import cpu_deadlock
from shed_jax import xla_cpu
from shed_jax.student.orthogonal import householder_q, orthogonal


def test_guard_adds_missing_flags_and_respects_the_users(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    xla_cpu.apply_cpu_guard()
    assert xla_cpu.FLAGS == ("--xla_cpu_multi_thread_eigen=false", "--xla_cpu_use_xnnpack=false")
    assert os.environ["XLA_FLAGS"].split() == list(xla_cpu.FLAGS)
    # a user's own value of an option stays, and other flags are kept in front
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4 --xla_cpu_use_xnnpack=true")
    xla_cpu.apply_cpu_guard()
    assert os.environ["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=4", "--xla_cpu_use_xnnpack=true",
                                               "--xla_cpu_multi_thread_eigen=false"]
    xla_cpu.apply_cpu_guard()  # idempotent
    assert os.environ["XLA_FLAGS"].count("xla_cpu_multi_thread_eigen") == 1
    # extra flags (the suite's TEST_FLAGS) follow the guard's, under the same rule
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_xnnpack=true")
    xla_cpu.apply_cpu_guard(extra=("--xla_llvm_disable_expensive_passes=true", "--xla_cpu_use_xnnpack=false"))
    assert os.environ["XLA_FLAGS"].split() == ["--xla_cpu_use_xnnpack=true", "--xla_cpu_multi_thread_eigen=false",
                                               "--xla_llvm_disable_expensive_passes=true"]


def test_only_flags_this_jaxlib_knows_are_added(monkeypatch):
    """An unknown flag would abort the process when JAX starts: extra flags the library does not name are dropped."""
    assert xla_cpu.xla_knows(["xla_backend_optimization_level", "xla_cpu_no_such_flag_anywhere"]) == [True, False]
    monkeypatch.setenv("XLA_FLAGS", "")
    xla_cpu.apply_cpu_guard(extra=("--xla_cpu_no_such_flag_anywhere=1", "--xla_backend_optimization_level=1"))
    assert os.environ["XLA_FLAGS"].split() == [*xla_cpu.FLAGS, "--xla_backend_optimization_level=1"]


def test_the_suite_runs_with_its_compile_flag():
    """conftest applied TEST_FLAGS before JAX started (the suite's time depends on it)."""
    for flag in xla_cpu.TEST_FLAGS:
        assert flag.split("=")[0] in os.environ["XLA_FLAGS"]


@pytest.mark.parametrize("shape", [(4, 64), (64, 64), (64, 2), (300, 256), (3, 1), (1, 3)])
def test_orthogonal_matches_the_library_without_lapack(shape):
    key = jax.random.PRNGKey(7)
    for scale in (1.0, np.sqrt(2.0), 0.01):
        ours = jax.jit(lambda k: orthogonal(scale)(k, shape))(key)
        lib = jax.nn.initializers.orthogonal(scale)(key, shape)
        np.testing.assert_allclose(np.asarray(ours) / scale, np.asarray(lib) / scale, atol=2e-6)
    q = np.asarray(ours) / 0.01
    small = min(shape)
    gram = q.T @ q if shape[0] >= shape[1] else q @ q.T  # orthonormal along the shorter side
    np.testing.assert_allclose(gram, np.eye(small), atol=2e-6)
    assert "lapack" not in jax.jit(lambda k: orthogonal()(k, shape)).lower(key).as_text().lower()
    with pytest.raises(ValueError, match="2-D kernel"):
        orthogonal()(key, (2, 3, 4))


@pytest.mark.optimized  # 200 QRs of 64 x 64
@pytest.mark.parametrize("shape, draws", [((64, 64), 200), ((300, 256), 20), ((4, 64), 200)])
def test_orthogonal_matches_numpy_lapack_and_is_haar(shape, draws):
    """Against a JAX-free float64 reference (NumPy's LAPACK QR of the same Gaussian draw, signs fixed
    so diag(R) > 0), ours is as accurate as the library's float32 QR; every singular value equals the
    scale; and over ``draws`` keys the entries have a Haar matrix's moments: mean 0, mean square 1/m
    along the longer side (20 draws of 300 x 256 hold 1.5M entries, more than 200 of 64 x 64 hold:
    0.8M). (A square Gaussian draw can have a condition number in the thousands, so both
    float32 QRs sit up to ~1e-5 from the exact Q; the bound grows with it, as a QR's forward error does.)"""
    scale = np.sqrt(2.0)
    init = jax.jit(jax.vmap(lambda k: orthogonal(scale)(k, shape)))
    keys = jax.random.split(jax.random.PRNGKey(3), draws)
    ours = np.asarray(init(keys)) / scale
    big, small = max(shape), min(shape)
    for i in range(3):  # the library draws z ~ N(0, 1) of shape (longer, shorter) from the same key
        z = np.asarray(jax.random.normal(keys[i], (big, small)), np.float64)
        q, r = np.linalg.qr(z)
        q = q * np.sign(np.diag(r))
        exact = q if shape[0] >= shape[1] else q.T
        bound = 0.1 * np.finfo(np.float32).eps * np.linalg.cond(z) + 1e-6  # measured: 9e-6 at cond 2446
        lib = np.asarray(jax.nn.initializers.orthogonal(1.0)(keys[i], shape))
        assert np.abs(lib - exact).max() <= bound  # the bound holds for the library's float32 QR too
        assert np.abs(ours[i] - exact).max() <= bound, (np.abs(ours[i] - exact).max(), bound)
    sv = np.linalg.svd(ours[:10], compute_uv=False)
    np.testing.assert_allclose(sv, 1.0, atol=1e-5)
    # Haar moments: E[q_ij] = 0 and E[q_ij^2] = 1/big; SE of the mean over draws x big x small entries
    n = ours.size
    assert abs(ours.mean()) < 4.0 / np.sqrt(n * big), ours.mean()
    assert abs((ours ** 2).mean() * big - 1.0) < 1e-5


def test_householder_q_on_a_hand_case():
    # a = [[3, 0], [4, 5], [0, 0]]: first column (3, 4, 0)/5; the second is orthogonal to it, from (0, 5, 0)
    q = np.asarray(householder_q(jnp.array([[3.0, 0.0], [4.0, 5.0], [0.0, 0.0]])))
    np.testing.assert_allclose(q[:, 0], [0.6, 0.8, 0.0], atol=1e-6)
    np.testing.assert_allclose(q[:, 1], [-0.8, 0.6, 0.0], atol=1e-6)  # R[1, 1] = 3 > 0


@pytest.mark.optimized  # 300 calls in a child process
def test_vmapped_student_inits_finish_on_a_two_thread_pool():
    # 16 vmapped students, six QRs each, 300 times on a pool forced to two threads (as on a 2-core
    # machine); `python -m experiments.cpu_deadlock --init library` shows the library init hanging
    finished, _ = cpu_deadlock.run_try("ours", nproc=2, calls=300, timeout=150)
    assert finished, "vmapped student inits deadlocked XLA:CPU (shed_jax/xla_cpu.py)"


def test_the_library_swap_reaches_the_student():
    # the experiment's control arm really puts the LAPACK initializer into the student's networks
    assert "networks.orthogonal = jax.nn.initializers.orthogonal" in cpu_deadlock.child_source("library", 5)
    assert "networks.orthogonal" not in cpu_deadlock.child_source("ours", 5)
    with pytest.raises(ValueError, match="--init"):
        cpu_deadlock.child_source("lapack", 5)


def test_with_flag_replaces_the_option_and_keeps_the_rest():
    flags = "--xla_cpu_use_xnnpack=false --xla_backend_optimization_level=0 --xla_foo=1"
    assert xla_cpu.with_flag(flags, "--xla_backend_optimization_level=1") == \
        "--xla_cpu_use_xnnpack=false --xla_foo=1 --xla_backend_optimization_level=1"
    assert xla_cpu.with_flag("", "--xla_force_host_platform_device_count=4") == "--xla_force_host_platform_device_count=4"
    # a prefix of another option's name is another option
    assert xla_cpu.with_flag("--xla_foo_bar=2", "--xla_foo=3") == "--xla_foo_bar=2 --xla_foo=3"


@pytest.mark.optimized
def test_optimized_tests_compile_at_level_1_in_process_and_in_child_processes():
    levels = [f for f in os.environ["XLA_FLAGS"].split() if f.startswith("--xla_backend_optimization_level")]
    assert levels == ["--xla_backend_optimization_level=1"]  # what a child process reads
    # this test's jits carry the level merged with their own options: an unknown one still reaches XLA
    with pytest.raises(Exception, match="No such compile option: 'xla_no_such_option'"):
        jax.jit(lambda x: x + 1, compiler_options={"xla_no_such_option": 1})(1.0)


def test_other_tests_compile_at_the_suites_level_0():
    assert "--xla_backend_optimization_level=0" in os.environ["XLA_FLAGS"].split()
    assert jax.jit.__module__.startswith("jax")  # the library's own jit, not the optimized wrapper
