"""envs.physics2d.fused: the per-world loop gives the same numbers as lax.fori_loop on every path
(unbatched, vmapped, nested vmaps, and per device under shard_map).

The Pallas kernel itself only compiles on a GPU; here it runs through Pallas' interpreter, which
executes the same kernel program (load rows, loop, store) on the CPU.
"""
import json
import os
import pathlib
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import physics2d
from envs.physics2d import fused
from envs.physics2d.vec import V2
from shed_jax.xla_cpu import with_flag

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


def test_when_skips_per_kernel_block_and_never_on_the_xla_path():
    """``fused.when``: on the XLA path ``fn`` always runs; in the kernel it runs in a block of worlds
    only if some world of that block has its flag set. The ``fn`` here breaks ``when``'s contract on
    purpose (it changes every world it runs for), which shows the granularity: 130 worlds are two
    kernel blocks (128 + 2), and a flag set in world 129 alone changes worlds 128 and 129 only."""
    def body(c, x):
        return fused.when(c["flag"], lambda v: v + 1.0, x, c["enabled"])

    def run(mode, flags, enabled=True):
        one = lambda f, x: fused.per_world_fori_loop(  # noqa: E731
            3, lambda c, s: body(dict(c, enabled=enabled), s), dict(flag=fused.BlockAny(f)), x, mode=mode)
        return np.asarray(jax.vmap(one)(flags, jnp.zeros(130, jnp.float32)))

    flags = jnp.zeros(130, jnp.float32).at[129].set(1.0)
    np.testing.assert_array_equal(run("xla", flags), np.full(130, 3.0))
    expect = np.zeros(130)
    expect[128:] = 3.0
    np.testing.assert_array_equal(run("interpret", flags), expect)
    np.testing.assert_array_equal(run("interpret", jnp.zeros(130, jnp.float32)), np.zeros(130))
    np.testing.assert_array_equal(run("interpret", jnp.zeros(130, jnp.float32), enabled=False), np.full(130, 3.0))
    with pytest.raises(TypeError, match="BlockAny"):
        fused.when(jnp.float32(1.0), lambda v: v, jnp.float32(0.0))


def counted(c, s):
    """x <- a x + b until a world's own ``k`` passes are done (then frozen: ``done``'s contract), with a
    ``runs`` counter that breaks the contract on purpose: it counts every pass the loop really ran."""
    x, cnt, runs = s
    go = cnt < c["k"]
    return jnp.where(go, c["a"] * x + 1.0, x), jnp.where(go, cnt + 1.0, cnt), runs + 1.0


@pytest.mark.parametrize("mode", ["xla", "interpret", "interpret_min_blocks"]
                         + (["pallas"] if jax.default_backend() == "gpu" else []))
def test_loop_with_done_stops_early_with_the_same_result(mode, monkeypatch):
    """``done``: every world ends where the full loop leaves it (x after min(k, n) passes); the loop
    stops per world on the XLA path (a vmapped while freezes each world once done) and per kernel block
    of 128 worlds in the kernel (130 worlds: the first block runs all n passes, as world 5 needs 20, the
    second its slowest world's 4; its padding worlds, whose flag never rises, must not keep it going).
    On a GPU machine the compiled kernel ("pallas") runs too; "interpret_min_blocks" pads the 130 worlds
    to ``MIN_WORLDS`` through the interpreter, as the compiled kernel does (8 blocks, 6 of padding only)."""
    monkeypatch.setattr(fused, "MIN_WORLDS", fused.DEFAULT_MIN_WORLDS)  # whatever a run in this process set
    assert fused._blocks(130, False) == 8 and fused._blocks(130, True) == 2 and fused._blocks(5000, False) == 40
    if mode == "interpret_min_blocks":
        monkeypatch.setattr(fused, "_blocks", lambda w, interpret: -(-max(w, fused.MIN_WORLDS) // fused.BLOCK))
        mode = "interpret"
    n, w = 12, 130
    k = jnp.asarray([i % 9 + 1 for i in range(w)], jnp.float32).at[5].set(20.0)  # world 5 needs more than n
    a = jnp.linspace(0.1, 0.9, w, dtype=jnp.float32)
    done = lambda s: jnp.where((s[1] >= s[3]) & (s[3] > 0.0), 1.0, 0.0)  # noqa: E731

    def one(a, k, stop=True):
        body = lambda c, s: counted(c, s[:3]) + (s[3],)  # noqa: E731
        z = jnp.float32(0.0)
        return fused.per_world_fori_loop(n, body, dict(a=a, k=k), (z, z, z, k), mode=mode,
                                         done=done if stop else None)

    x, cnt, runs, _ = jax.jit(jax.vmap(one))(a, k)
    x_full, cnt_full, runs_full, _ = jax.jit(jax.vmap(lambda a, k: one(a, k, False)))(a, k)
    np.testing.assert_array_equal(np.asarray(x), np.asarray(x_full))
    np.testing.assert_array_equal(np.asarray(cnt), np.minimum(np.asarray(k), n))
    np.testing.assert_array_equal(np.asarray(runs_full), np.full(w, n))
    if mode == "xla":  # the kernel's paths: interpret, pallas
        want = np.minimum(np.asarray(k), n)
    else:
        want = np.concatenate([np.full(128, n), np.full(2, 4.0)])  # block 0 holds world 5 (k = 20 > n)
    np.testing.assert_array_equal(np.asarray(runs), want)
    # unbatched: one world's own count
    assert [float(v) for v in one(jnp.float32(0.5), jnp.float32(3.0))[1:3]] == [3.0, 3.0]


def leaky(c, s, x):
    """A scan body with per-iteration inputs and two outputs: s <- a s + u_i, emitting s and sign(s - 1/2) i."""
    y = c["a"] * s + x["u"]
    return y, (y, jnp.sign(y - 0.5) * x["i"])


def many_fields(c, s):
    """37 consts and 11 carried values, each carried value fed by its own consts: a field read from or
    written to the wrong column of the kernel's tiles changes the result."""
    return tuple(s[j] * c[j] + sum(c[k] for k in range(11 + j, 37, 11)) for j in range(11))


def _kernel_accesses(fn, *args) -> int:
    """Memory reads and writes of per-world fields in the first Pallas kernel of ``fn`` (outside its loop)."""
    def calls(jaxpr):  # the pallas_calls, through the custom_vmap / pjit jaxprs around them
        for e in jaxpr.eqns:
            if e.primitive.name == "pallas_call":
                yield e
            for v in e.params.values():
                inner = getattr(v, "jaxpr", v)
                if isinstance(inner, jax.extend.core.Jaxpr):
                    yield from calls(inner)

    eqn = next(calls(jax.make_jaxpr(fn)(*args).jaxpr))
    return sum(e.primitive.name in ("get", "swap", "load", "store") for e in eqn.params["jaxpr"].eqns)


@pytest.mark.parametrize("tile", [1, 4, 8])
def test_kernel_reads_and_writes_tiles_of_fields_in_order(tile, monkeypatch):
    monkeypatch.setattr(fused, "TILE", tile)
    worlds, n = 130, 3  # two kernel blocks, one of them partly padding
    c = jax.random.uniform(jax.random.PRNGKey(0), (37, worlds), jnp.float32, 0.5, 1.0)
    s0 = jax.random.normal(jax.random.PRNGKey(1), (11, worlds), jnp.float32)
    run = lambda mode: jax.vmap(lambda c, s: fused.per_world_fori_loop(  # noqa: E731
        n, many_fields, tuple(c), tuple(s), mode=mode), in_axes=(1, 1))
    want = np.asarray(run("xla")(c, s0))
    got = np.asarray(run("interpret")(c, s0))
    np.testing.assert_array_equal(got, want)
    # one read per tile of the 48 input fields and one write per tile of the 11 outputs
    assert _kernel_accesses(run("interpret"), c, s0) == -(-48 // tile) + -(-11 // tile)


def test_scan_matches_lax_scan_unbatched_vmapped_and_nested():
    """``per_world_scan``: the kernel (through the interpreter) stores every iteration's outputs where
    ``lax.scan`` stacks them, over more worlds than one block (130 = 128 + 2), with an unbatched
    const, unbatched and under nested vmaps; an iteration count that is not a power of two (200)."""
    n, w = 200, 130
    u = jax.random.uniform(jax.random.PRNGKey(0), (w, n))
    a = jnp.linspace(0.1, 0.9, w, dtype=jnp.float32)
    i = jnp.arange(n, dtype=jnp.float32)

    def run(mode, a, s0, u):
        return fused.per_world_scan(leaky, dict(a=a), s0, dict(u=u, i=i), mode=mode)

    def reference(a, s0, u):  # plain numpy
        s, ys, zs = s0, [], []
        for k in range(n):
            s = np.float32(a * s + u[k])
            ys.append(s)
            zs.append(np.sign(s - 0.5) * k)
        return s, np.array(ys), np.array(zs)

    s, (ys, zs) = run("interpret", a[3], jnp.float32(1.0), u[3])
    want = reference(np.asarray(a[3]), np.float32(1.0), np.asarray(u[3]))
    np.testing.assert_allclose(float(s), want[0], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(ys), want[1], rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(zs), want[2])
    s0 = jnp.ones((w,), jnp.float32)
    got = jax.jit(jax.vmap(lambda a, s, u: run("interpret", a, s, u)))(a, s0, u)
    xla = jax.jit(jax.vmap(lambda a, s, u: run("xla", a, s, u)))(a, s0, u)
    assert got[1][0].shape == (w, n)
    for g, x in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(xla)):
        np.testing.assert_allclose(np.asarray(g), np.asarray(x), rtol=1e-6)
    nested = jax.jit(jax.vmap(jax.vmap(lambda a, s, u: run("interpret", a, s, u), in_axes=(0, None, 0)),
                              in_axes=(0, None, 0)))(a.reshape(2, 65), jnp.float32(1.0), u.reshape(2, 65, n))
    np.testing.assert_allclose(np.asarray(nested[1][0]).reshape(w, n), np.asarray(xla[1][0]), rtol=1e-6)


def test_scan_bad_inputs_raise():
    with pytest.raises(TypeError, match="float32 xs of one shape"):
        fused.per_world_scan(leaky, dict(a=jnp.float32(1.0)), jnp.float32(0.0),
                             dict(u=jnp.zeros(3), i=jnp.zeros(4)), mode="interpret")
    with pytest.raises(ValueError, match="at least one xs leaf"):
        fused.per_world_scan(leaky, {}, jnp.float32(0.0), (), mode="interpret")


def lanes_body(c, s):
    """A loop with lane vectors (``lanes=4``): a per-world counter ``a`` and a lane vector ``v`` that feed
    each other through ``fused.lane`` and ``fused.lanes_of``."""
    a, v = s
    v = v * c["k"] + 0.5 * a
    a = 0.9 * a + fused.lane(v, 2) - 0.1 * fused.lane(v, 0)
    return a, v + 1e-3 * fused.lanes_of(a, 2 * a, 3 * a, 4.0)


def lanes_reference(k, a, v, n):
    """``lanes_body`` in numpy float32, one world at a time."""
    a, v = np.float32(a), v.astype(np.float32)
    for _ in range(n):
        v = v * k + np.float32(0.5) * a
        a = np.float32(0.9) * a + v[2] - np.float32(0.1) * v[0]
        v = v + np.float32(1e-3) * np.asarray([a, 2 * a, 3 * a, 4.0], np.float32)
    return a, v


def test_lanes_loop_matches_numpy_through_xla_and_the_kernels_interpreter():
    rng = np.random.default_rng(0)
    w, n = 37, 20  # not a whole number of blocks: the kernel pads and drops worlds
    k = rng.uniform(0.5, 1.0, (w, 4)).astype(np.float32)
    a0, v0 = rng.normal(size=w).astype(np.float32), rng.normal(size=(w, 4)).astype(np.float32)
    ref = [lanes_reference(k[i], a0[i], v0[i], n) for i in range(w)]
    out = {}
    for mode in ("xla", "interpret"):
        run = jax.vmap(lambda c, s, m=mode: fused.per_world_fori_loop(n, lanes_body, c, s, mode=m, lanes=4))
        out[mode] = jax.jit(run)({"k": jnp.asarray(k)}, (jnp.asarray(a0), jnp.asarray(v0)))
        a, v = (np.asarray(x) for x in out[mode])
        assert a.shape == (w,) and v.shape == (w, 4)
        np.testing.assert_allclose(a, [r[0] for r in ref], rtol=1e-5)
        np.testing.assert_allclose(v, np.stack([r[1] for r in ref]), rtol=1e-5, atol=1e-6)
    for x, y in zip(out["xla"], out["interpret"]):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def lanes_until_body(c, s):
    """Lanes with ``when`` and ``done``: a lane vector ``v`` halves (plus ``u``) in the lanes whose flag
    is set (``on``; ``flag`` is the same as a ``BlockAny``, which the kernel reduces over its block); the
    world counts its passes and is done once its smallest lane is below ``thr`` (0 in padding worlds:
    never), then frozen. Two counters break the contracts on purpose, to show what the kernel ran:
    ``passes`` counts every pass, done or not, and ``ran`` every call of the ``when`` branch."""
    count, v, done, passes, ran = s

    def halve(x):
        v, ran = x
        return jnp.where(c["on"] > 0.5, 0.5 * v + c["u"], v), ran + 1.0

    nv, ran = fused.when(c["flag"], halve, (v, ran))
    frozen = done > 0.5
    return (jnp.where(frozen, count, count + 1.0), jnp.where(frozen, v, nv),
            jnp.where(frozen | (fused.lane_min(nv) < c["thr"]), 1.0, 0.0), passes + 1.0, ran)


def test_lanes_loop_with_flags_and_an_early_stop_matches_numpy():
    """Five kernel blocks of 32 worlds: the first runs all passes (three worlds never finish), the
    second has no flag set (``when`` skips its branch; it never finishes), the third flags only
    lanes 1-3 (so the branch runs; it never finishes), the fourth and the last (5 real worlds, then
    padding that would never finish) stop at their slowest world's pass."""
    rng = np.random.default_rng(1)
    w, n, bw = 133, 30, 32
    flag = (rng.uniform(size=(w, 4)) < 0.6).astype(np.float32)
    flag[:, 0] = 1.0  # every flagged world reaches done, at its own pass
    flag[:3] = 0.0  # ... but these, which run all n passes unchanged
    flag[bw:2 * bw] = 0.0  # and the second block, where ``when`` skips
    flag[2 * bw:3 * bw, 0] = 0.0  # and the third block's lane 0
    u = rng.uniform(0.0, 0.04, (w, 4)).astype(np.float32)
    v0 = rng.uniform(0.5, 8.0, (w, 4)).astype(np.float32)
    want_count, want_v = np.zeros(w, np.float32), v0.copy()
    for i in range(w):
        for _ in range(n):
            if flag[i].any():
                want_v[i] = np.where(flag[i] > 0.5, np.float32(0.5) * want_v[i] + u[i], want_v[i])
            want_count[i] += 1
            if want_v[i].min() < 0.1:
                break
    assert len(set(want_count.tolist())) > 3 and want_count.max() == n  # stops at many different passes
    block_passes = np.repeat([want_count[k:k + bw].max() for k in range(0, w, bw)], bw)[:w]
    assert list(block_passes[::bw] < n) == [False, False, False, True, True]
    out = {}
    for mode in ("xla", "interpret"):
        run = jax.vmap(lambda c, s, m=mode: fused.per_world_fori_loop(
            n, lanes_until_body, c, s, mode=m, lanes=4, done=lambda s: s[2]))
        c = {"flag": fused.BlockAny(jnp.asarray(flag)), "on": jnp.asarray(flag), "u": jnp.asarray(u),
             "thr": jnp.full((w,), 0.1, jnp.float32)}
        z = jnp.zeros(w)
        out[mode] = jax.jit(run)(c, (z, jnp.asarray(v0), z, z, z))
        count, v, done, passes, ran = (np.asarray(x) for x in out[mode])
        np.testing.assert_array_equal(count, want_count)
        np.testing.assert_allclose(v, want_v, rtol=1e-6)
        np.testing.assert_array_equal(done, (want_v.min(1) < 0.1).astype(np.float32))
        assert np.array_equal(np.asarray(fused.lane_min(jnp.asarray(v))), v.min(1))
        if mode == "xla":  # a vmapped while_loop keeps each world's carry from its own last pass on
            np.testing.assert_array_equal(passes, want_count)
            np.testing.assert_array_equal(ran, want_count)
        else:  # each block until its own last real world is done; the unflagged block never takes the branch
            np.testing.assert_array_equal(passes, block_passes)
            np.testing.assert_array_equal(ran, np.where(np.arange(w) // bw == 1, 0.0, block_passes))
    for x, y in zip(out["xla"][:3], out["interpret"][:3]):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_lane_helpers_are_exact_and_lanes_are_checked():
    v = jnp.asarray([-0.0, 1.5, np.float32(np.pi), -2.0], jnp.float32)
    got = [fused.lane(v, j) for j in range(4)]
    assert [np.asarray(g).shape for g in got] == [()] * 4
    np.testing.assert_array_equal(np.asarray(got), np.asarray(v))
    assert not np.signbit(np.asarray(got[0]))  # the sum starts from +0.0: the sign of zero is not kept
    np.testing.assert_array_equal(np.asarray(fused.lanes_of(*got)), np.asarray(v))
    with pytest.raises(ValueError, match="lanes must be 1 or 4"):
        fused.per_world_fori_loop(2, lambda c, s: s, {}, jnp.zeros(()), lanes=3)
    with pytest.raises(TypeError, match="per-world scalars or lane vectors"):
        fused.per_world_fori_loop(2, lambda c, s: s, {}, jnp.zeros(3), mode="interpret", lanes=4)


def test_bad_leaves_and_modes_raise():
    with pytest.raises(ValueError, match="solver kernel"):
        fused.resolve_mode("cuda")
    with pytest.raises(TypeError, match="float32 per-world scalars"):
        fused.per_world_fori_loop(2, lambda c, s: s, {}, jnp.zeros(2), mode="interpret")
    with pytest.raises(ValueError, match="SolverConfig.kernel"):
        physics2d.SolverConfig(kernel="gpu")
    assert fused.resolve_mode("auto") == ("pallas" if jax.default_backend() == "gpu" else "xla")


ROOT = pathlib.Path(__file__).resolve().parents[1]


def motor_on_box(kernel):
    """A box resting on the ground with a second box pinned to it by a motorised, limited joint."""
    cfg = physics2d.SolverConfig(dt=DT, velocity_iterations=12, position_iterations=4, kernel=kernel)
    polys = [physics2d.Polygon(0, BOX, 2.0, 0.4), physics2d.Polygon(1, BOX, 0.5, 0.3)]
    j = physics2d.RevoluteJoint(0, 1, (0.5, 0.25), (-0.5, 0.0), enable_motor=True, motor_speed=2.0,
                                max_motor_torque=4.0, enable_limit=True, lower=-0.3, upper=0.6)
    return physics2d.make_model(2, polys, (j,), cfg)


def runs_of_worlds(kernel):
    """A run = 3 worlds of ``motor_on_box`` pushed at different speeds and spins, 30 steps each.

    Returns per world and step the COMs (30, 2, 2), spins (30, 2), touching slots (30, 8) and the
    position-solved flag (30,): contacts, friction, the motor, the limits and both passes."""
    m = motor_on_box(kernel)

    def world(vx):
        b = physics2d.bodies_from_origin(m, [[5.0, 1.3], [6.0, 1.55]], [0.0, 0.0],
                                         vel=[[vx, 0.0], [0.0, 0.0]], omega=[0.0, 1.5 * vx])

        def body(w, _):
            w, info = physics2d.step(m, w, FLAT, -10.0)
            return w, (w.bodies.com, w.bodies.omega, info["touching"], info["position_solved"])

        return jax.lax.scan(body, physics2d.init_world(m, b), None, length=30)[1]

    return jax.vmap(world)


RUN_SPEEDS = np.linspace(-2.0, 2.0, 12, dtype=np.float32).reshape(4, 3)  # 4 runs x 3 worlds

_SHARDED = textwrap.dedent(
    """
    import json, sys
    import jax, numpy as np
    sys.path.insert(0, "tests")
    from test_fused import RUN_SPEEDS, runs_of_worlds
    from shed_jax import sharding
    from jax.sharding import PartitionSpec as P

    mesh = sharding.batch_mesh()
    run = jax.jit(sharding.per_device(jax.vmap(runs_of_worlds("interpret")), mesh, P("batch")))
    out = run(sharding.put_batch(RUN_SPEEDS, mesh))
    print(json.dumps(dict(devices=sorted(d.id for d in sharding.devices_of(out)),
                          out=[np.asarray(x).astype(float).tolist() for x in out])))
    """
)


def test_solver_kernel_inside_per_device_shard_map_equals_xla():
    """The full step with the kernel (Pallas' interpreter) on 2 virtual devices through the sweep's
    sharded path (``sharding.per_device``): each device vmaps its runs x worlds (nested vmap) into its
    own kernel calls, and gets the numbers of the unsharded XLA loops."""
    # the suite's XLA:CPU guard and compile flags (tests/conftest.py), as this process has, plus two devices
    env = {**os.environ, "XLA_FLAGS": with_flag(os.environ.get("XLA_FLAGS", ""), "--xla_force_host_platform_device_count=2"),
           "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", _SHARDED], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    ref = jax.jit(jax.vmap(runs_of_worlds("xla")))(RUN_SPEEDS)  # meanwhile, in this process
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr[-4000:]
    out = json.loads(stdout.strip().splitlines()[-1])
    assert out["devices"] == [0, 1]
    com, omega, touching, solved = (np.asarray(x) for x in ref)
    # equal up to XLA:CPU fusing the sharded program differently (seen: 5e-7)
    for r, k in zip((com, omega), out["out"][:2]):
        np.testing.assert_allclose(np.asarray(k), r, rtol=0, atol=1e-5)
    for r, k in zip((touching, solved), out["out"][2:]):
        np.testing.assert_array_equal(np.asarray(k, bool), r)
    assert touching.any() and solved.any()  # contacts made, position passes ran to tolerance
    assert float(np.std(com[:, :, -1, 0, 0])) > 0.05  # the worlds really differ


def test_batch_any_is_the_flag_alone_and_any_over_every_batch_axis_under_vmap():
    assert bool(fused.batch_any(jnp.asarray(True))) and not bool(fused.batch_any(jnp.asarray(False)))
    flags = jnp.asarray([[False, False, True], [False, False, False]])
    # one value for the whole batch (vmap broadcasts it back to the batch's shape)
    np.testing.assert_array_equal(jax.vmap(fused.batch_any)(flags[1]), [False] * 3)
    np.testing.assert_array_equal(jax.vmap(fused.batch_any)(flags[0]), [True] * 3)
    np.testing.assert_array_equal(jax.vmap(jax.vmap(fused.batch_any))(flags), np.ones((2, 3), bool))
    # a cond on it stays a cond under vmap (one branch for the batch), not both branches and a select
    f = lambda x, flag: jax.lax.cond(fused.batch_any(flag), lambda v: v + 1.0, lambda v: v, x)  # noqa: E731
    jaxpr = str(jax.make_jaxpr(jax.vmap(f))(jnp.zeros(3), flags[0]))
    assert "cond[" in jaxpr and "select_n" not in jaxpr
    np.testing.assert_array_equal(jax.vmap(f)(jnp.zeros(3), flags[0]), [1.0, 1.0, 1.0])  # the branch ran for all
    np.testing.assert_array_equal(jax.vmap(f)(jnp.zeros(3), flags[1]), [0.0, 0.0, 0.0])
