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
