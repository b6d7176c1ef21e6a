"""experiments/toi_census.py: the candidate counts per call site and batch-step, on hand-made flags."""
import numpy as np

from experiments.toi_census import summarise


def test_counts_per_site_and_batch_step():
    records = [(0, np.array([[True, False]])),  # the first reset, one batch-step of 1 walker x 2 polygons
               (1, np.array([[False, False]])), (2, np.array([[False, False]])),
               (1, np.array([[True, True]])), (2, np.array([[False, False]])),
               (1, np.array([[False, True]])), (2, np.array([[False, False]]))]
    r = summarise(records)
    assert list(r) == ["first reset", "step", "auto-reset"]
    assert r["first reset"] == {"batch_steps": 1, "searches_per_batch_step": 2, "candidate_share": 0.5,
                                "batch_steps_with_any": 1.0, "fewest_candidates_in_a_batch_step": 1}
    assert r["step"] == {"batch_steps": 3, "searches_per_batch_step": 2, "candidate_share": 0.5,
                         "batch_steps_with_any": round(2 / 3, 4), "fewest_candidates_in_a_batch_step": 0}
    assert r["auto-reset"]["candidate_share"] == 0.0 and r["auto-reset"]["batch_steps_with_any"] == 0.0
    assert list(summarise([(3, np.array([True]))])) == ["site 3"]


def test_record_searches_keeps_each_runs_flags_over_the_whole_batch():
    """The wrapped search records, per run, one flag per search of the (nested) vmapped batch: whether
    its time of impact is before the step's end; its results are the search's own."""
    import jax
    import jax.numpy as jnp

    from envs.physics2d import toi
    from experiments import toi_census

    original = toi.earliest_impact
    try:
        records = toi_census.record_searches()
        assert toi_census.record_searches() is records and toi.earliest_impact._recording  # wrapped once
        box = jnp.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]], jnp.float32)
        ground = jnp.array([[[-5.0, -1.0], [5.0, -1.0], [5.0, 0.0], [-5.0, 0.0]]], jnp.float32)  # top at y = 0

        def search(y1):  # a unit box falling from y = 2 to y1 onto the ground slab
            return toi.earliest_impact(box, jnp.array([0.0, 2.0]), 0.0, jnp.array([0.0, y1]), 0.0, ground,
                                       jnp.array([True]), target=0.01, tolerance=0.0025, candidates=1)

        y1 = jnp.array([[1.5, 0.0], [0.2, 1.0], [3.0, -1.0]], jnp.float32)  # (3, 2): a batch of batches
        alpha = jax.jit(jax.vmap(jax.vmap(lambda y: search(y)[0])))(y1)
        jax.block_until_ready(alpha)
        assert len(records) == 1
        site, flags = records[0]
        assert site == 0 and flags.shape == (3, 2)
        np.testing.assert_array_equal(flags, np.asarray(alpha) < 1.0)
        np.testing.assert_array_equal(flags, [[False, True], [True, False], [False, True]])
        ref = jax.vmap(jax.vmap(lambda y: original(box, jnp.array([0.0, 2.0]), 0.0, jnp.array([0.0, y]), 0.0, ground,
                                                   jnp.array([True]), target=0.01, tolerance=0.0025,
                                                   candidates=1)[0]))(y1)
        np.testing.assert_array_equal(np.asarray(alpha), np.asarray(ref))
        assert toi_census.summarise(records, names=("step",))["step"]["candidate_share"] == 0.5
    finally:
        toi.earliest_impact = original
