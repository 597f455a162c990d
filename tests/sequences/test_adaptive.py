"""The adaptive matcher against a plain loop over every path, the kernel it generalises, and its blocked top-K."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from seqvpr.sequences.adaptive import AdaptiveScorer, adaptive_path
from seqvpr.sequences.matching import frame_distances, sequence_distance_rows, sequence_topk
from seqvpr.sequences.windows import SequenceSpec, window_starts
from tests.helpers import examples


def brute_force(d: np.ndarray, q_start: int, length: int, anchor: int, steps: range, seg: np.ndarray) -> np.ndarray:
    """Every step sequence, every anchor column: the mean distance of the best path through each reference."""
    n = d.shape[1]
    best = np.full(n, np.inf)
    for moves in itertools.product(steps, repeat=length - 1):
        offsets = np.concatenate([[0], np.cumsum(moves)]).astype(np.int64)
        for first in range(n):
            path = first + offsets
            if path[-1] >= n or len(set(seg[path])) != 1:
                continue
            cost = np.mean([d[q_start + k, path[k]] for k in range(length)])
            best[path[anchor]] = min(best[path[anchor]], cost)
    return best


def random_case(seed: int, n_q: int, n_r: int, breaks: bool):
    rng = np.random.default_rng(seed)
    q = torch.from_numpy(rng.standard_normal((n_q, 6)).astype(np.float64))
    r = torch.from_numpy(rng.standard_normal((n_r, 6)).astype(np.float64))
    q_seg = np.sort(rng.integers(0, 2, n_q)) if breaks else np.zeros(n_q, np.int64)
    r_seg = np.sort(rng.integers(0, 3, n_r)) if breaks else np.zeros(n_r, np.int64)
    return q, r, q_seg, r_seg


@settings(max_examples=examples(40), deadline=None)
@given(seed=st.integers(0, 10_000), n_q=st.integers(3, 9), n_r=st.integers(3, 12), length=st.integers(1, 4),
       align=st.sampled_from(["centered", "causal"]), low=st.integers(0, 1), extra=st.integers(0, 2),
       breaks=st.booleans())
def test_adaptive_equals_every_path_by_a_plain_loop(seed, n_q, n_r, length, align, low, extra, breaks):
    q, r, q_seg, r_seg = random_case(seed, n_q, n_r, breaks)
    spec = SequenceSpec(length, align)
    scorer = AdaptiveScorer(low, low + extra)
    starts = window_starts(q_seg, length, spec.offset, "drop")
    valid = starts[starts >= 0]
    if len(valid) == 0:
        return
    got = sequence_distance_rows(q, r, spec, valid, r_seg, scorer=scorer).numpy()
    d = frame_distances(q, r).numpy()
    for row, start in enumerate(valid):
        expected = brute_force(d, int(start), length, spec.offset, range(low, low + extra + 1), r_seg)
        np.testing.assert_allclose(got[row], expected, rtol=1e-9, atol=1e-12)


@settings(max_examples=examples(25), deadline=None)
@given(seed=st.integers(0, 10_000), length=st.integers(1, 6), align=st.sampled_from(["centered", "causal"]),
       breaks=st.booleans())
def test_unit_steps_are_the_constant_velocity_kernel(seed, length, align, breaks):
    q, r, q_seg, r_seg = random_case(seed, 14, 20, breaks)
    spec = SequenceSpec(length, align)
    starts = window_starts(q_seg, length, spec.offset, "drop")
    valid = starts[starts >= 0]
    if len(valid) == 0:
        return
    kernel = sequence_distance_rows(q, r, spec, valid, r_seg).numpy()
    adaptive = sequence_distance_rows(q, r, spec, valid, r_seg, scorer=AdaptiveScorer(1, 1)).numpy()
    np.testing.assert_allclose(adaptive, kernel, rtol=1e-9)


def test_blocked_top_k_equals_the_whole_matrix():
    q, r, q_seg, r_seg = random_case(3, 60, 300, True)
    spec, scorer = SequenceSpec(5), AdaptiveScorer(0, 2)
    whole = sequence_topk(q, r, spec, 10, q_seg, r_seg, scorer=scorer)
    blocked = sequence_topk(q, r, spec, 10, q_seg, r_seg, scorer=scorer, chunk=17)
    np.testing.assert_array_equal(blocked.indices, whole.indices)
    np.testing.assert_allclose(blocked.distances, whole.distances)


def test_the_path_of_a_match_costs_its_distance_and_keeps_its_steps():
    q, r, q_seg, r_seg = random_case(5, 30, 80, True)
    spec, scorer = SequenceSpec(7), AdaptiveScorer(0, 2)
    top = sequence_topk(q, r, spec, 1, q_seg, r_seg, scorer=scorer)
    d = frame_distances(q, r).numpy()
    starts = window_starts(q_seg, 7, spec.offset, "drop")
    for i in np.flatnonzero(starts >= 0):
        j = int(top.indices[i, 0])
        path = adaptive_path(d[starts[i]: starts[i] + 7], j, spec.offset, scorer, r_seg)
        assert path[spec.offset] == j and set(np.diff(path)) <= {0, 1, 2} and len(set(r_seg[path])) == 1
        cost = np.mean(d[starts[i] + np.arange(7), path])
        assert abs(cost - top.distances[i, 0]) < 1e-9


def test_re_ranking_every_reference_frame_is_the_exhaustive_adaptive_match():
    from seqvpr.sequences.adaptive import adaptive_rerank
    from seqvpr.sequences.matching import TopK

    q, r, q_seg, r_seg = random_case(7, 25, 60, True)
    spec, scorer = SequenceSpec(5), AdaptiveScorer(1, 2)
    whole = sequence_topk(q, r, spec, 6, q_seg, r_seg, scorer=scorer)
    everything = TopK(np.tile(np.arange(60), (25, 1)), np.zeros((25, 60)), np.ones(25, bool))
    reranked = adaptive_rerank(q, r, everything, spec, scorer, q_seg, r_seg, k=6)
    np.testing.assert_array_equal(reranked.indices, whole.indices)
    np.testing.assert_allclose(reranked.distances, whole.distances, rtol=1e-9)


@pytest.mark.parametrize("method", ["adaptive", "casevpr"])
def test_a_window_of_one_frame_is_single_image_matching(method):
    """At L = 1 no frame lies on either side of the anchor: the adaptive search (alone, or re-ranking CaseVPR's
    shortlist) is the frame distance itself, as single-image matching ranks it (was an IndexError)."""
    import seqvpr
    from seqvpr.synthetic.routes import generate_route

    reference, query = generate_route(n_frames=90, dim=8, seed=4)
    single = seqvpr.match(reference, query, "single", k=5).topk
    found = seqvpr.match(reference, query, method, seq_len=1, k=5, rerank=90 if method == "casevpr" else 0).topk
    np.testing.assert_array_equal(found.indices[:, 0], single.indices[:, 0])
    np.testing.assert_allclose(found.distances[:, 0], single.distances[:, 0], rtol=1e-5)
