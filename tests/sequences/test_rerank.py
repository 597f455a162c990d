"""HVPR re-ranking: exact sequence distances over a shortlist, against the kernel and a plain-loop oracle."""

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.sequences.rerank import rerank
from seqvpr.sequences.matching import TopK, sequence_topk
from seqvpr.sequences.windows import SequenceSpec
from tests.helpers import examples, raises_one_line
from tests.oracles import sequence_distances


def unit_rows(rng, n, dim):
    x = torch.as_tensor(rng.normal(size=(n, dim)), dtype=torch.float64)
    return torch.nn.functional.normalize(x, dim=1)


def whole_reference(n_q, n_r):
    return TopK(np.tile(np.arange(n_r), (n_q, 1)), np.zeros((n_q, n_r)), np.ones(n_q, dtype=bool))


@settings(max_examples=examples(25), deadline=None)
@given(seed=st.integers(0, 10_000), length=st.integers(1, 6), boundary=st.sampled_from(["drop", "shift"]),
       align=st.sampled_from(["centered", "causal"]))
def test_whole_reference_shortlist_equals_exhaustive_sequence_matching(seed, length, boundary, align):
    rng = np.random.default_rng(seed)
    query, reference = unit_rows(rng, 30, 8), unit_rows(rng, 40, 8)
    q_seg = np.repeat([0, 1], [12, 18])
    r_seg = np.repeat([0, 1, 2], [9, 21, 10])
    spec = SequenceSpec(length, align, boundary)
    exhaustive = sequence_topk(query, reference, spec, 5, q_seg, r_seg)
    hvpr = rerank(query, reference, whole_reference(30, 40), spec, q_seg, r_seg, k=5)
    assert np.array_equal(hvpr.has_window, exhaustive.has_window)
    assert np.allclose(hvpr.distances, exhaustive.distances, atol=1e-9)  # the same sorted distances (inf == inf)
    full = sequence_distances(query.numpy(), reference.numpy(), length, align, boundary, q_seg, r_seg)
    for q in np.flatnonzero(hvpr.has_window):  # each returned frame is at its listed distance (ties may reorder)
        found = hvpr.indices[q] >= 0
        assert np.allclose(full[q, hvpr.indices[q, found]], hvpr.distances[q, found], atol=1e-9)
        assert np.array_equal(found, exhaustive.indices[q] >= 0)


def test_partial_shortlist_is_reordered_by_the_plain_loop_distance():
    rng = np.random.default_rng(4)
    query, reference = unit_rows(rng, 20, 6), unit_rows(rng, 25, 6)
    spec = SequenceSpec(3)
    shortlist = TopK(rng.integers(0, 25, size=(20, 7)), np.zeros((20, 7)), np.ones(20, dtype=bool))
    shortlist.indices[3, 2] = -1  # fewer candidates for one query
    out = rerank(query, reference, shortlist, spec)
    full = sequence_distances(query.numpy(), reference.numpy(), 3)  # oracle matrix, +inf without a window
    for q in range(20):
        if not np.isfinite(full[q]).any():
            assert not out.has_window[q] and (out.indices[q] == -1).all()
            continue
        cands = [c for c in shortlist.indices[q] if c >= 0]
        expected = sorted(((full[q, c], c) for c in cands if np.isfinite(full[q, c])), key=lambda t: t[0])
        got = [(d, i) for d, i in zip(out.distances[q], out.indices[q]) if i >= 0]
        assert [i for _, i in got] == [c for _, c in expected]
        assert np.allclose([d for d, _ in got], [d for d, _ in expected])


def test_small_memory_budget_gives_the_same_result():
    rng = np.random.default_rng(1)
    query, reference = unit_rows(rng, 15, 5), unit_rows(rng, 18, 5)
    spec = SequenceSpec(4, boundary="shift")
    big = rerank(query, reference, whole_reference(15, 18), spec, k=3)
    small = rerank(query, reference, whole_reference(15, 18), spec, k=3, memory_budget=1)
    assert np.array_equal(big.indices, small.indices) and np.allclose(big.distances, small.distances)


def test_bad_input_is_one_line():
    rng = np.random.default_rng(0)
    query, reference = unit_rows(rng, 5, 3), unit_rows(rng, 6, 3)
    raises_one_line("velocities 1", rerank, query, reference, whole_reference(5, 6), SequenceSpec(3, velocities=(0.8, 1.0)))
    raises_one_line("query has 5 frames", rerank, query, reference, whole_reference(4, 6), SequenceSpec(3))


def test_equal_distances_rank_the_lower_reference_row_first_whatever_the_candidate_order():
    rng = np.random.default_rng(3)
    query, reference = unit_rows(rng, 6, 4), unit_rows(rng, 12, 4)
    reference[7:10] = reference[2:5]  # the windows at rows 3 and 8 are the same frames: equal distances
    spec = SequenceSpec(3)
    for candidates in ([8, 3, 5], [3, 8, 5], [5, 8, 3]):
        shortlist = TopK(np.tile(candidates, (6, 1)), np.zeros((6, 3)), np.ones(6, dtype=bool))
        top = rerank(query, reference, shortlist, spec)
        for row in top.indices[1:-1]:  # queries with a window
            assert list(row).index(3) < list(row).index(8)  # as the kernel, and a sharded map's merge, order ties


class Rows:
    """Rows that are neither a tensor nor an array (coded rows, rows read through shards): indexed by row lists."""

    def __init__(self, array: np.ndarray) -> None:
        self.array, self.shape = array, array.shape

    def __getitem__(self, rows):
        return self.array[rows]


@settings(max_examples=examples(30), deadline=None)
@given(st.integers(1, 6), st.integers(1, 40), st.integers(0, 2**31 - 1))
def test_the_candidate_form_is_the_plain_loop_for_every_container_and_batch_size(length, candidates, seed):
    """``candidate_distances`` (the sequence family's candidate form, what re-ranking and the streaming shortlist
    score with) against the plain loop; a tensor, an array and any other rows give the same numbers, bit for bit,
    whether the compiled pass runs serially (few windows) or in parallel (many)."""
    from seqvpr.sequences import _fused
    from seqvpr.sequences.rerank import candidate_distances
    from tests.oracles import window_distance

    rng = np.random.default_rng(seed)
    query, reference = rng.normal(size=(12, 5)).astype(np.float32), rng.normal(size=(60, 5)).astype(np.float32)
    q_starts = rng.integers(0, 12 - length + 1, 3)
    r_starts = np.where(rng.random((3, candidates)) < 0.2, -1, rng.integers(0, 60 - length + 1, (3, candidates)))
    found = candidate_distances(torch.from_numpy(query), torch.from_numpy(reference), q_starts, r_starts, length)
    for i, c in np.ndindex(r_starts.shape):
        if r_starts[i, c] < 0:
            assert found[i, c] == np.inf
        else:
            expected = window_distance(query[q_starts[i]:q_starts[i] + length],
                                       reference[r_starts[i, c]:r_starts[i, c] + length])
            assert abs(found[i, c] - expected) < 1e-5
    for rows in (reference, Rows(reference)):
        np.testing.assert_array_equal(candidate_distances(torch.from_numpy(query), rows, q_starts, r_starts, length),
                                      found)
    serial = _fused.SERIAL_WINDOWS
    try:
        _fused.SERIAL_WINDOWS = 0  # every size in parallel
        parallel = candidate_distances(torch.from_numpy(query), reference, q_starts, r_starts, length)
    finally:
        _fused.SERIAL_WINDOWS = serial
    np.testing.assert_array_equal(parallel, found)
