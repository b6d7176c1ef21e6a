"""minibatch_sgd: every sample once per epoch, and the same numbers as a hand-written loop."""
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from shed_jax.student.sgd import minibatch_sgd


def _problem(n):
    """A least-squares fit w . x ~ y on n samples; each sample carries its index."""
    x = jax.random.normal(jax.random.PRNGKey(0), (n, 3))
    y = x @ jnp.array([1.0, -2.0, 0.5]) + 0.1 * jax.random.normal(jax.random.PRNGKey(1), (n,))
    return {"x": x, "y": y, "i": jnp.arange(n)}, {"w": jnp.zeros(3), "b": jnp.zeros(())}


def _loss(n):
    def loss_fn(params, mb):
        err = mb["x"] @ params["w"] + params["b"] - mb["y"]
        loss = jnp.mean(err**2)
        return loss, {"loss": loss, "visits": jnp.zeros(n, jnp.int32).at[mb["i"]].add(1)}

    return loss_fn


@pytest.mark.parametrize("n, k", [(12, 4), (14, 4)])  # 14 = 4 x 3 + 2: two samples sit out each epoch
def test_every_sample_once_per_epoch(n, k):
    batch, params = _problem(n)
    epochs = 5
    _, aux = jax.jit(lambda p, b, key: minibatch_sgd(_loss(n), optax.sgd(0.05), p, optax.sgd(0.05).init(p), b, key,
                                                     epochs, k))(params, batch, jax.random.PRNGKey(2))
    visits = np.asarray(aux["visits"])  # [epochs, k, n]
    assert visits.shape == (epochs, k, n) and aux["loss"].shape == (epochs, k)
    per_epoch = visits.sum(axis=1)
    assert per_epoch.max() == 1  # no sample twice in an epoch
    np.testing.assert_array_equal(per_epoch.sum(axis=1), (n // k) * k)
    np.testing.assert_array_equal(visits.sum(axis=2), n // k)  # full minibatches
    if n % k == 0:
        np.testing.assert_array_equal(per_epoch, 1)
    assert len({tuple(np.flatnonzero(visits[e, 0])) for e in range(epochs)}) > 1  # reshuffled every epoch


def test_equals_a_hand_written_loop_and_reports_grad_norms():
    n, k, epochs = 12, 3, 4
    batch, params = _problem(n)
    tx = optax.chain(optax.clip_by_global_norm(0.5), optax.adam(0.1))
    key = jax.random.PRNGKey(3)
    loss_fn = _loss(n)
    (p_got, s_got), aux = minibatch_sgd(loss_fn, tx, params, tx.init(params), batch, key, epochs, k, grad_norm=True)

    p, s, norms, losses = params, tx.init(params), [], []
    for ek in jax.random.split(key, epochs):
        perm = np.asarray(jax.random.permutation(ek, n))
        for j in range(k):
            rows = perm[j * (n // k):(j + 1) * (n // k)]
            mb = {name: v[rows] for name, v in batch.items()}
            (loss, _), g = jax.value_and_grad(loss_fn, has_aux=True)(p, mb)
            norms.append(float(np.sqrt(sum(np.sum(np.asarray(x) ** 2) for x in jax.tree_util.tree_leaves(g)))))
            losses.append(float(loss))
            u, s = tx.update(g, s, p)
            p = optax.apply_updates(p, u)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7), p_got, p)
    np.testing.assert_allclose(np.asarray(aux["grad_norm"]).ravel(), norms, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(aux["loss"]).ravel(), losses, rtol=1e-5)
    assert float(losses[-1]) < 0.5 * float(losses[0])  # and it fits


def test_too_few_samples():
    batch, params = _problem(3)
    with pytest.raises(ValueError, match="3 samples cannot fill 4 minibatches"):
        minibatch_sgd(_loss(3), optax.sgd(0.1), params, optax.sgd(0.1).init(params), batch, jax.random.PRNGKey(0), 1, 4)


def test_scalar_aux_leaves_the_scan_stacked_with_the_same_values():
    """Float32 scalar aux (PPO's losses) leave the scan as one vector a step; unstacked after, they are
    what the per-leaf path (forced here by an int leaf) gives, bit for bit, in their own tree."""
    n, k, epochs = 12, 3, 2
    batch, params = _problem(n)
    tx = optax.adam(0.1)

    def loss_fn(params, mb, extra=False):
        err = mb["x"] @ params["w"] + params["b"] - mb["y"]
        loss = jnp.mean(err**2)
        aux = {"loss": loss, "inner": {"bias": params["b"], "err": jnp.mean(err)}}
        return loss, (dict(aux, count=jnp.int32(mb["i"].shape[0])) if extra else aux)

    def run(extra):
        f = lambda p, b: minibatch_sgd(lambda q, mb: loss_fn(q, mb, extra), tx, p, tx.init(p), b,  # noqa: E731
                                       jax.random.PRNGKey(4), epochs, k, grad_norm=True)
        return jax.jit(f)(params, batch)

    (p_stacked, _), stacked = run(False)
    (p_leafwise, _), leafwise = run(True)
    assert set(stacked) == {"loss", "inner", "grad_norm"} and set(stacked["inner"]) == {"bias", "err"}
    assert int(leafwise.pop("count")[0, 0]) == n // k
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), stacked, leafwise)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), p_stacked, p_leafwise)
    assert stacked["loss"].shape == (epochs, k) and stacked["loss"].dtype == jnp.float32
