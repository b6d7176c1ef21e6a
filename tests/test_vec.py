"""The solver's branch-free ``sincos`` against float64 references."""
import jax
import numpy as np
import pytest

from envs.physics2d.vec import LARGEST_ANGLE, V2, rotate2, sincos


def _points():
    rng = np.random.default_rng(0)
    return np.concatenate([rng.uniform(-8192, 8192, 200_000), rng.uniform(-4, 4, 200_000),
                           np.arange(-64, 65) * (np.pi / 4),  # octant boundaries, where the reduction switches
                           [0.0, 1e-30, 1e-8, 1.0, np.pi / 2, np.pi]]).astype(np.float32)


def _error(s, c, x):
    x = x.astype(np.float64)
    return max(np.abs(np.asarray(s, np.float64) - np.sin(x)).max(), np.abs(np.asarray(c, np.float64) - np.cos(x)).max())


@pytest.mark.optimized  # the jit below at LLVM level 1, which fuses the polynomials' multiply-adds as runs do
def test_absolute_error_within_float32_rounding_of_unit_values():
    x = _points()
    assert _error(*sincos(x), x) < 1e-7  # 2**-24 ~ 6e-8 is half an ulp at 1; jnp.sin is within about that
    assert _error(*jax.jit(sincos)(x), x) < 1e-7


def test_huge_angles_stay_bounded():
    x = np.array([1e5, -3e6, 1e9, 1.7e9, -3e38, LARGEST_ANGLE], np.float32)
    s, c = (np.asarray(v) for v in sincos(x))
    assert np.all(np.isfinite(s)) and np.all(np.isfinite(c))
    assert np.all(np.abs(s) <= 1.0) and np.all(np.abs(c) <= 1.0)
    np.testing.assert_array_equal(s[2:5], np.asarray(sincos(np.sign(x[2:5]) * LARGEST_ANGLE)[0]))


def test_exact_symmetry_and_special_values():
    x = _points()
    s, c = (np.asarray(v) for v in sincos(x))
    ns, nc = (np.asarray(v) for v in sincos(-x))
    np.testing.assert_array_equal(ns, -s)
    np.testing.assert_array_equal(nc, c)
    s0, c0 = (float(v) for v in sincos(np.float32(0.0)))
    assert (s0, c0) == (0.0, 1.0)
    tiny = np.float32(1e-8)
    assert float(sincos(tiny)[0]) == float(tiny)  # sin x = x below float32 resolution
    assert np.all(np.abs(s) <= 1.0) and np.all(np.abs(c) <= 1.0)


def test_rotation_by_quarter_turns():
    v = V2(np.float32(2.0), np.float32(-1.0))
    for k, (ex, ey) in enumerate([(2.0, -1.0), (1.0, 2.0), (-2.0, 1.0), (-1.0, -2.0)]):
        r = rotate2(np.float32(k * np.pi / 2), v)
        np.testing.assert_allclose([float(r.x), float(r.y)], [ex, ey], atol=5e-7)
