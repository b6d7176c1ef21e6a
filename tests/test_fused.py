"""envs.physics2d.fused: the per-world loop gives the same numbers as lax.fori_loop on every path.

The Pallas kernel itself only compiles on a GPU; here it runs through Pallas' interpreter, which
executes the same kernel program (load rows, loop, store) on the CPU.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import physics2d
from envs.physics2d import fused
from envs.physics2d.vec import V2

DT = 1.0 / 50.0
BOX = ((-0.5, -0.25), (0.5, -0.25), (0.5, 0.25), (-0.5, 0.25))
FLAT = jnp.asarray([[0.0, 1.0], [10.0, 1.0], [20.0, 1.0]], jnp.float32)


def affine(c, s):
    """x <- a x + b on a V2 and a scalar counter: closed form a^n x0 + b (1 - a^n) / (1 - a)."""
    x, count = s
    return V2(c["a"] * x.x + c["b"], c["a"] * x.y - c["b"]), count + 1.0


def closed_form(a, b, x0, n):
    an = a ** n
    return an * x0 + b * (1 - an) / (1 - a)


@pytest.mark.parametrize("mode", ["xla", "interpret"])
def test_loop_matches_closed_form_unbatched_vmapped_and_nested(mode):
    n = 7
    run = lambda a, b, x0: fused.per_world_fori_loop(  # noqa: E731
        n, affine, dict(a=a, b=b), (V2(x0, -x0), jnp.float32(0.0)), mode=mode)
    x, count = run(jnp.float32(0.5), jnp.float32(1.0), jnp.float32(2.0))
    assert float(count) == n
    np.testing.assert_allclose(float(x.x), closed_form(0.5, 1.0, 2.0, n), rtol=1e-6)
    np.testing.assert_allclose(float(x.y), -closed_form(0.5, 1.0, 2.0, n), rtol=1e-6)
    # vmapped over worlds, ``b`` shared (unbatched) across them
    a = jnp.linspace(0.1, 0.9, 5, dtype=jnp.float32)
    x0 = jnp.arange(5, dtype=jnp.float32)
    x, count = jax.vmap(run, in_axes=(0, None, 0))(a, jnp.float32(0.25), x0)
    np.testing.assert_allclose(np.asarray(x.x), closed_form(np.asarray(a), 0.25, np.asarray(x0), n), rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(count), np.full(5, n))
    # nested vmap (seeds x worlds), as in the UED loop; more worlds than one kernel block
    a2 = jnp.tile(a, (3, 30))
    x2 = jnp.tile(x0, (3, 30)) + jnp.arange(3, dtype=jnp.float32)[:, None]
    x, _ = jax.vmap(jax.vmap(run, in_axes=(0, None, 0)), in_axes=(0, None, 0))(a2, jnp.float32(0.25), x2)
    assert x.x.shape == (3, 150)
    np.testing.assert_allclose(np.asarray(x.x), closed_form(np.asarray(a2), 0.25, np.asarray(x2), n), rtol=1e-5)


def test_bad_leaves_and_modes_raise():
    with pytest.raises(ValueError, match="solver kernel"):
        fused.resolve_mode("cuda")
    with pytest.raises(TypeError, match="float32 per-world scalars"):
        fused.per_world_fori_loop(2, lambda c, s: s, {}, jnp.zeros(2), mode="interpret")
    with pytest.raises(ValueError, match="SolverConfig.kernel"):
        physics2d.SolverConfig(kernel="gpu")
    assert fused.resolve_mode("auto") == ("pallas" if jax.default_backend() == "gpu" else "xla")


def motor_on_box(kernel):
    """A box resting on the ground with a second box pinned to it by a motorised, limited joint."""
    cfg = physics2d.SolverConfig(dt=DT, velocity_iterations=12, position_iterations=4, kernel=kernel)
    polys = [physics2d.Polygon(0, BOX, 2.0, 0.4), physics2d.Polygon(1, BOX, 0.5, 0.3)]
    j = physics2d.RevoluteJoint(0, 1, (0.5, 0.25), (-0.5, 0.0), enable_motor=True, motor_speed=2.0,
                                max_motor_torque=4.0, enable_limit=True, lower=-0.3, upper=0.6)
    return physics2d.make_model(2, polys, (j,), cfg)


def test_solver_interpret_kernel_equals_xla_on_contacts_and_joints():
    """Seeds x worlds of the full step (contacts, friction, motor, limits, position passes)."""
    def rollout(kernel):
        m = motor_on_box(kernel)

        def world(vx, spin):
            b = physics2d.bodies_from_origin(m, [[5.0, 1.3], [6.0, 1.55]], [0.0, 0.0],
                                             vel=[[vx, 0.0], [0.0, 0.0]], omega=[0.0, spin])
            w = physics2d.init_world(m, b)

            def body(w, _):
                w, info = physics2d.step(m, w, FLAT, -10.0)
                return w, (w.bodies.com, w.bodies.omega, info["touching"], info["position_solved"])

            return jax.lax.scan(body, w, None, length=40)[1]

        vx = jnp.linspace(-2.0, 2.0, 12, dtype=jnp.float32).reshape(2, 6)
        spin = jnp.linspace(-3.0, 3.0, 12, dtype=jnp.float32).reshape(2, 6)
        return jax.jit(jax.vmap(jax.vmap(world)))(vx, spin)

    ref, ker = rollout("xla"), rollout("interpret")
    for r, k in zip(ref, ker):
        np.testing.assert_array_equal(np.asarray(r), np.asarray(k))
    com, omega, touching, solved = ref
    assert bool(jnp.any(touching)) and bool(jnp.any(solved))  # contacts and position passes exercised
    assert float(jnp.max(jnp.std(com[..., 0, 0], axis=(0, 1)))) > 0.05  # the worlds really differ
