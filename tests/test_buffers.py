"""Ring buffers: wrap-around, add-many ordering, sampling support, mixed batches, use under jit/scan."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from shed_jax.teacher.buffers import (
    buffer_add,
    buffer_add_many,
    buffer_init,
    buffer_sample,
    make_transition,
    num_real_in_batch,
    sample_mixed,
)


def _item(v, m=2, da=3):
    return make_transition(m, da).replace(s=jnp.full(m, v), r=jnp.float32(v))


def test_wrap_around_one_by_one():
    buf = buffer_init(make_transition(2, 3), 4)
    add = jax.jit(buffer_add)
    for v in range(6):
        buf = add(buf, _item(float(v)))
    np.testing.assert_array_equal(buf.data.r, [4.0, 5.0, 2.0, 3.0])
    np.testing.assert_array_equal(buf.data.s[:, 0], [4.0, 5.0, 2.0, 3.0])
    assert int(buf.pos) == 2 and int(buf.count) == 4 and buf.capacity == 4


def test_add_many_equals_successive_adds():
    buf_a = buffer_init(make_transition(2, 3), 5)
    buf_b = buf_a
    values = np.arange(1.0, 9.0)  # 8 items in batches of 3, 3, 2 into capacity 5
    for chunk in (values[:3], values[3:6], values[6:]):
        batch = make_transition(2, 3, (len(chunk),)).replace(r=jnp.asarray(chunk, jnp.float32))
        buf_a = buffer_add_many(buf_a, batch)
        for v in chunk:
            buf_b = buffer_add(buf_b, make_transition(2, 3).replace(r=jnp.float32(v)))
    np.testing.assert_array_equal(buf_a.data.r, buf_b.data.r)
    np.testing.assert_array_equal(buf_a.data.r, [6.0, 7.0, 8.0, 4.0, 5.0])
    assert int(buf_a.pos) == int(buf_b.pos) == 3 and int(buf_a.count) == 5
    with pytest.raises(ValueError, match="capacity"):
        buffer_add_many(buf_a, make_transition(2, 3, (6,)))


def test_sampling_uses_only_valid_entries_uniformly():
    buf = buffer_init(make_transition(2, 3), 16)
    buf = buffer_add_many(buf, make_transition(2, 3, (3,)).replace(r=jnp.array([1.0, 2.0, 3.0])))
    batch = jax.jit(buffer_sample, static_argnums=2)(buf, jax.random.PRNGKey(0), 3000)
    vals, counts = np.unique(np.asarray(batch.r), return_counts=True)
    np.testing.assert_array_equal(vals, [1.0, 2.0, 3.0])  # never the zero padding
    assert np.all(np.abs(counts / 3000 - 1 / 3) < 0.04)
    assert batch.s.shape == (3000, 2) and batch.u.shape == (3000, 3)


def test_mixed_batch_ratio_and_layout():
    real = buffer_add_many(buffer_init(make_transition(2, 3), 40), make_transition(2, 3, (40,)).replace(r=jnp.ones(40)))
    syn = buffer_add_many(buffer_init(make_transition(2, 3), 40), make_transition(2, 3, (40,)).replace(r=-jnp.ones(40)))
    batch, real_mask = sample_mixed(real, syn, jax.random.PRNGKey(1), 32, 0.75)
    np.testing.assert_array_equal(real_mask, [True] * 24 + [False] * 8)
    np.testing.assert_array_equal(batch.r, [1.0] * 24 + [-1.0] * 8)
    assert num_real_in_batch(10, 0.33) == 3 and num_real_in_batch(5, 1.0) == 5 and num_real_in_batch(5, 0.0) == 0
    assert num_real_in_batch(10, 0.7) == 7  # floor, robust to 0.7 * 10 = 6.9999...
    with pytest.raises(ValueError, match="psi"):
        num_real_in_batch(32, 1.5)


def test_buffer_inside_scan_and_vmap_over_seeds():
    def fill(key):
        def body(buf, k):
            return buffer_add(buf, _item(jax.random.uniform(k))), None

        buf, _ = jax.lax.scan(body, buffer_init(make_transition(2, 3), 8), jax.random.split(key, 10))
        return buf

    bufs = jax.jit(jax.vmap(fill))(jax.random.split(jax.random.PRNGKey(0), 3))
    assert bufs.data.r.shape == (3, 8) and np.all(np.asarray(bufs.count) == 8) and np.all(np.asarray(bufs.pos) == 2)
    assert not np.allclose(bufs.data.r[0], bufs.data.r[1])  # different seeds, different data
    with pytest.raises(ValueError, match="capacity"):
        buffer_init(make_transition(2, 3), 0)
