"""Recall@K, PR curve and ground truth against plain loops and brute force."""

import numpy as np
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.data.ground_truth import GroundTruth, Radius, ground_truth_within_radius, parse_radius
from seqvpr.data.traversal import Traversal
from seqvpr.evaluation.metrics import evaluate, pr_curve
from tests import oracles
from tests.helpers import examples


def random_gt(rng, n_q, n_r, density):
    dense = rng.random((n_q, n_r)) < density
    return GroundTruth(sp.csr_array(dense)), dense


@settings(max_examples=examples(80), deadline=None)
@given(st.integers(1, 30), st.integers(1, 30), st.integers(1, 8), st.floats(0.0, 0.4), st.integers(0, 10**6))
def test_recall_matches_loop(n_q, n_r, k, density, seed):
    rng = np.random.default_rng(seed)
    gt, dense = random_gt(rng, n_q, n_r, density)
    k = min(k, n_r)
    preds = np.stack([rng.permutation(n_r)[:k] for _ in range(n_q)])
    preds[rng.random(preds.shape) < 0.1] = -1
    result = evaluate(preds, np.zeros(preds.shape), np.ones(n_q, bool), gt, ks=(1, 2, 5, 10))
    positives = [set(np.flatnonzero(row)) for row in dense]
    expected = oracles.recall_at_k(preds.tolist(), positives, (1, 2, 5, 10))
    for key in (1, 2, 5, 10):
        if np.isnan(expected[key]):
            assert np.isnan(result.recall[key])
        else:
            assert abs(result.recall[key] - expected[key]) < 1e-12
    assert result.queries_evaluated == sum(1 for p in positives if p)


def test_no_positive_policy_counts_misses():
    gt = GroundTruth(sp.csr_array(np.array([[1, 0], [0, 0]], dtype=bool)))
    preds = np.array([[0], [1]])
    excluded = evaluate(preds, np.zeros((2, 1)), np.ones(2, bool), gt, ks=(1,))
    missed = evaluate(preds, np.zeros((2, 1)), np.ones(2, bool), gt, ks=(1,), no_positive="miss")
    assert excluded.recall[1] == 1.0 and excluded.excluded_no_positive == 1
    assert missed.recall[1] == 0.5 and missed.queries_evaluated == 2


def test_queries_without_window_are_not_scored():
    gt = GroundTruth(sp.csr_array(np.eye(3, dtype=bool)))
    preds = np.array([[0], [-1], [2]])
    result = evaluate(preds, np.array([[0.1], [np.inf], [0.2]]), np.array([True, False, True]), gt, ks=(1,))
    assert result.queries_evaluated == 2 and result.excluded_no_window == 1 and result.recall[1] == 1.0


@settings(max_examples=examples(60), deadline=None)
@given(st.lists(st.tuples(st.integers(0, 5), st.booleans()), min_size=1, max_size=40), st.integers(0, 10))
def test_pr_curve_matches_threshold_loop(matches, extra_positive):
    dist = np.array([m[0] for m in matches], dtype=float)
    ok = np.array([m[1] for m in matches])
    n_pos = len(matches) + extra_positive
    curve = pr_curve(dist, ok, n_pos)
    for threshold, precision, recall in zip(curve.thresholds, curve.precision, curve.recall):
        accepted = dist <= threshold
        assert abs(precision - ok[accepted].sum() / accepted.sum()) < 1e-12
        assert abs(recall - ok[accepted].sum() / n_pos) < 1e-12
    assert list(curve.thresholds) == sorted(set(dist.tolist()))


def test_pr_perfect_ranking():
    curve = pr_curve(np.array([0.1, 0.2, 0.3, 0.4]), np.array([True, True, False, False]), 4)
    assert curve.recall_at_100_precision == 0.5
    assert abs(curve.auc - 0.5) < 1e-12


@settings(max_examples=examples(60), deadline=None)
@given(st.integers(1, 40), st.integers(1, 40), st.floats(0.0, 20.0), st.integers(0, 10**6))
def test_metric_radius_matches_brute_force(n_q, n_r, radius, seed):
    rng = np.random.default_rng(seed)
    q = Traversal.from_descriptors(np.zeros((n_q, 1)), positions=rng.uniform(0, 50, (n_q, 2)))
    r = Traversal.from_descriptors(np.zeros((n_r, 1)), positions=rng.uniform(0, 50, (n_r, 2)))
    gt = ground_truth_within_radius(q, r, Radius(radius, "m"))
    brute = np.linalg.norm(q.positions[:, None] - r.positions[None], axis=2) <= radius
    assert (gt.positives.toarray() == brute).all()


@settings(max_examples=examples(60), deadline=None)
@given(st.lists(st.integers(0, 60), min_size=1, max_size=30), st.lists(st.integers(0, 60), min_size=1, max_size=30), st.integers(0, 4))
def test_frame_radius_matches_brute_force(q_frames, r_frames, radius):
    q = Traversal.from_descriptors(np.zeros((len(q_frames), 1)))
    r = Traversal.from_descriptors(np.zeros((len(r_frames), 1)))
    q = Traversal(q.name, np.array(q_frames), q.segment_ids, q.descriptors)
    r = Traversal(r.name, np.array(r_frames), r.segment_ids, r.descriptors)
    gt = ground_truth_within_radius(q, r, Radius(radius, "frames"))
    brute = np.abs(np.array(q_frames)[:, None] - np.array(r_frames)[None]) <= radius
    assert (gt.positives.toarray() == brute).all()


def test_parse_radius():
    assert parse_radius("25m") == Radius(25.0, "m")
    assert parse_radius("25") == Radius(25.0, "m")
    assert parse_radius("2f") == Radius(2.0, "frames")
    assert parse_radius("2 frames") == Radius(2.0, "frames")


def test_restrict_maps_source_indices():
    dense = np.arange(30).reshape(5, 6) % 4 == 0
    gt = GroundTruth(sp.csr_array(dense)).restrict(np.array([1, 3]), np.array([0, 2, 5]))
    assert (gt.positives.toarray() == dense[[1, 3]][:, [0, 2, 5]]).all()
