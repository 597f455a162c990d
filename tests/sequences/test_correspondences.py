"""Per-frame correspondences of top-1 matches and their precision, against plain loops."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from hypothesis import given, settings, strategies as st

from seqvpr.data.ground_truth import GroundTruth
from seqvpr.evaluation.metrics import frame_precision
from seqvpr.sequences.adaptive import AdaptiveScorer
from seqvpr.sequences.correspondences import adaptive_correspondences, window_correspondences
from seqvpr.sequences.windows import SequenceSpec, window_starts
from tests.helpers import examples


@settings(max_examples=examples(40), deadline=None)
@given(seed=st.integers(0, 9999), length=st.integers(1, 5), align=st.sampled_from(["centered", "causal"]),
       boundary=st.sampled_from(["drop", "shift"]))
def test_window_correspondences_pair_frame_k_with_frame_k(seed, length, align, boundary):
    rng = np.random.default_rng(seed)
    q_seg, r_seg = np.sort(rng.integers(0, 2, 15)), np.sort(rng.integers(0, 3, 20))
    best = rng.integers(-1, 20, 15)
    spec = SequenceSpec(length, align, boundary)
    q_rows, r_rows = window_correspondences(best, spec, q_seg, r_seg)
    qs = window_starts(q_seg, length, spec.offset, boundary)
    rs = window_starts(r_seg, length, spec.offset, boundary)
    for i in range(15):
        if qs[i] < 0 or best[i] < 0 or rs[best[i]] < 0:
            assert (q_rows[i] == -1).all() and (r_rows[i] == -1).all()
        else:
            assert list(q_rows[i]) == [qs[i] + k for k in range(length)]
            assert list(r_rows[i]) == [rs[best[i]] + k for k in range(length)]


def test_frame_precision_counts_right_pairs_over_queries_with_a_positive():
    positives = np.zeros((4, 6), bool)
    positives[0, [0, 1]] = positives[1, 2] = positives[2, 3] = True  # query 3 has none
    gt = GroundTruth(sp.csr_array(positives))
    q = np.array([[0, 1], [2, 3], [-1, -1]])
    r = np.array([[1, 5], [3, 3], [-1, -1]])
    expected = [positives[a, b] for a, b in zip(q.ravel(), r.ravel()) if a >= 0 and positives[a].any()]
    assert frame_precision(q, r, gt) == np.mean(expected) == 2 / 3


def test_adaptive_correspondences_at_unit_steps_are_the_windows():
    rng = np.random.default_rng(1)
    q, r = torch.from_numpy(rng.standard_normal((30, 8))), torch.from_numpy(rng.standard_normal((50, 8)))
    q_seg, r_seg = np.r_[np.zeros(15, int), np.ones(15, int)], np.r_[np.zeros(30, int), np.ones(20, int)]
    spec = SequenceSpec(5)
    best = rng.integers(0, 50, 30)
    r_starts = window_starts(r_seg, 5, spec.offset, "drop")
    best[r_starts[best] < 0] = -1
    got = adaptive_correspondences(q, r, best, spec, AdaptiveScorer(1, 1), q_seg, r_seg)
    expected = window_correspondences(best, spec, q_seg, r_seg)
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])


@settings(max_examples=examples(40), deadline=None)
@given(seed=st.integers(0, 9999), k=st.integers(1, 8), exclusion=st.integers(0, 4))
def test_uniqueness_margins_equal_a_plain_loop(seed, k, exclusion):
    from seqvpr.sequences.topk import uniqueness_margins

    rng = np.random.default_rng(seed)
    indices = np.stack([rng.permutation(30)[:k] for _ in range(6)])
    distances = np.sort(rng.random((6, k)), axis=1) - 0.5  # contrast-enhanced distances may be negative
    indices[5] = -1
    distances[5] = np.inf
    got = uniqueness_margins(indices, distances, exclusion)
    for i in range(5):
        others = [distances[i, j] for j in range(1, k) if abs(indices[i, j] - indices[i, 0]) > exclusion]
        second = others[0] if others else distances[i, -1]
        assert got[i] == distances[i, 0] - second
    assert got[5] == np.inf


@settings(max_examples=examples(25), deadline=None)
@given(seed=st.integers(0, 9999), length=st.integers(2, 7), boundary=st.sampled_from(["drop", "shift"]),
       which=st.sampled_from(["kernel", "contrast", "hybrid"]))
def test_trajectory_correspondences_follow_the_trajectory_that_scored_the_match(seed, length, boundary, which):
    """The pairs are one of the searched straight trajectories, and their (enhanced) mean distance is the match's
    own distance: the winning trajectory, recomputed by a plain mean over the full matrix."""
    from seqvpr.sequences.matching import frame_distances, sequence_topk
    from seqvpr.sequences.seqslam import ContrastScorer, HybridScorer, enhance_contrast, velocity_grid
    from seqvpr.sequences.correspondences import trajectory_correspondences
    from seqvpr.sequences.windows import velocity_steps

    rng = np.random.default_rng(seed)
    r = torch.from_numpy(rng.standard_normal((90, 8)))
    q = r[20:60] + 0.7 * torch.from_numpy(rng.standard_normal((40, 8)))
    q_seg, r_seg = np.r_[np.zeros(25, int), np.ones(15, int)], np.sort(rng.integers(0, 3, 90))
    spec = SequenceSpec(length, boundary=boundary, velocities=(0.7, 1.0, 1.4))
    scorer = {"kernel": None, "contrast": ContrastScorer(6), "hybrid": ContrastScorer(6, HybridScorer())}[which]
    top = sequence_topk(q, r, spec, 1, q_seg, r_seg, scorer=scorer)
    q_rows, r_rows = trajectory_correspondences(q, r, top.indices[:, 0], spec, scorer, q_seg, r_seg)
    d = frame_distances(q, r)
    matrix = (d if scorer is None else enhance_contrast(d, r_seg, 6)).numpy()
    velocities = velocity_grid(spec) if which == "hybrid" else spec.velocities
    shapes = {tuple(velocity_steps(length, v)) for v in velocities}
    matched = np.flatnonzero(np.isfinite(top.distances[:, 0]))
    assert len(matched) and np.array_equal(np.flatnonzero(q_rows[:, 0] >= 0), matched)
    for i in matched:
        assert tuple(r_rows[i] - r_rows[i, 0]) in shapes  # a straight trajectory of the search
        assert len(set(r_seg[r_rows[i]])) == 1  # inside one segment
        assert boundary == "shift" or r_rows[i, spec.offset] == top.indices[i, 0]  # through the match's frame
        mean = matrix[q_rows[i], r_rows[i]].mean()
        np.testing.assert_allclose(mean, top.distances[i, 0], rtol=1e-6, atol=1e-9)
