"""Incremental causal sequence matching against the plain-loop oracle, frame by frame, over random shapes,
segments and restarts."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.errors import SeqvprError
from seqvpr.sequences.online import DiagonalSums
from seqvpr.sequences.topk import best_k
from tests import oracles
from tests.helpers import examples, raises_one_line


@st.composite
def streams(draw):
    n_q, n_r, dim, length = draw(st.integers(1, 20)), draw(st.integers(1, 20)), draw(st.integers(1, 4)), draw(st.integers(1, 6))
    q_seg = np.cumsum([0] + draw(st.lists(st.booleans(), min_size=n_q - 1, max_size=n_q - 1)))
    r_seg = np.cumsum([0] + draw(st.lists(st.booleans(), min_size=n_r - 1, max_size=n_r - 1)))
    rng = np.random.default_rng(draw(st.integers(0, 2**31 - 1)))
    return rng.normal(size=(n_q, dim)), rng.normal(size=(n_r, dim)), length, q_seg, r_seg


@settings(max_examples=examples(150), deadline=None)
@given(streams())
def test_running_sums_equal_causal_windows_frame_by_frame(stream):
    q, r, length, q_seg, r_seg = stream
    expected = oracles.sequence_distances(q, r, length, "causal", "drop", q_seg, r_seg)
    sums = DiagonalSums(r_seg, length)
    for i in range(len(q)):
        if i and q_seg[i] != q_seg[i - 1]:
            sums.reset()  # a query segment break is a restart
        got = sums.push(np.linalg.norm(r - q[i], axis=1).astype(np.float32))  # measured distances are float32
        if got is None:
            assert np.isinf(expected[i]).all()
            continue
        assert (np.isinf(got) == np.isinf(expected[i])).all()
        finite = np.isfinite(got)
        np.testing.assert_allclose(got[finite], expected[i][finite], rtol=1e-6)


def diagonal_loop(rows: list[np.ndarray], length: int, exists: np.ndarray) -> np.ndarray:
    """The plain loop: each window's float32 terms summed oldest first in float64, then divided by L (what the
    running partial sums gave, bit for bit)."""
    out = np.full(len(exists), np.inf)
    for r in np.flatnonzero(exists):
        total = np.float64(0.0)
        for j in range(length - 1, -1, -1):
            total += np.float64(rows[-1 - j][r - j])
        out[r] = total / length
    return out


@settings(max_examples=examples(100), deadline=None)
@given(st.integers(1, 7), st.integers(1, 9000), st.integers(1, 40), st.integers(0, 2**31 - 1), st.booleans())
def test_ring_means_and_topk_equal_the_plain_loop_bit_for_bit(length, n, k, seed, ties):
    """Means from the ring equal the plain float64 loop exactly (across blocks of rows), and the fused top-K is
    ``best_k`` over them: the same rows, distances and tie rule (ties drawn from a few values)."""
    rng = np.random.default_rng(seed)
    segments = np.cumsum(rng.random(n) < 0.01)
    sums, fused = DiagonalSums(segments, length), DiagonalSums(segments, length)
    rows = []
    for _ in range(length + 2):
        row = (rng.integers(0, 3, n) if ties else rng.random(n) * 2).astype(np.float32)
        rows.append(row)
        means = sums.push(row)
        top = fused.push_topk(row, k)
        if means is None:
            assert top is None
            continue
        np.testing.assert_array_equal(means, diagonal_loop(rows, length, sums.window_exists))
        indices, distances = best_k(means, k)
        np.testing.assert_array_equal(top[0], indices)
        np.testing.assert_array_equal(top[1], distances)


def test_the_topk_splits_over_threads_as_one_scan(monkeypatch):
    """A map large enough to split over threads ranks its windows as one scan does (ties across the split)."""
    from seqvpr.sequences import _fused

    rng = np.random.default_rng(3)
    n = 4 * _fused.PART_ROWS + 17
    rows = [rng.integers(0, 4, n).astype(np.float32) for _ in range(3)]
    split, whole = DiagonalSums(np.zeros(n), 3), DiagonalSums(np.zeros(n), 3)
    monkeypatch.setattr(_fused.numba, "get_num_threads", lambda: 3)
    for row in rows:
        top = split.push_topk(row, 50)
    monkeypatch.setattr(_fused.numba, "get_num_threads", lambda: 1)
    for row in rows:
        one = whole.push_topk(row, 50)
    np.testing.assert_array_equal(top[0], one[0])
    np.testing.assert_array_equal(top[0], best_k(diagonal_loop(rows, 3, whole.window_exists), 50)[0])


def test_saved_sums_go_on_where_they_stopped():
    rng = np.random.default_rng(0)
    rows = rng.random((9, 30))
    whole, half = DiagonalSums(np.zeros(30), 4), DiagonalSums(np.zeros(30), 4)
    for row in rows[:5]:
        whole.push(row), half.push(row)
    resumed = DiagonalSums(np.zeros(30), 4)
    resumed.load_state(half.state())
    for row in rows[5:]:
        np.testing.assert_array_equal(whole.push(row), resumed.push(row))
    raises_one_line("this map and L need", DiagonalSums(np.zeros(30), 3).load_state, half.state())
    raises_one_line("older seqvpr", DiagonalSums(np.zeros(30), 4).load_state, {"partial": rows[:4], "count": 5})
    raises_one_line("expected distances to the 30", whole.push, np.zeros(29))


def test_a_window_longer_than_any_reference_segment_never_matches():
    sums = DiagonalSums(np.array([0, 0, 1, 1]), 3)
    for _ in range(3):
        out = sums.push(np.ones(4))
    assert np.isinf(out).all()
    try:
        DiagonalSums(np.zeros(3), 0)
    except SeqvprError as error:
        assert "positive" in str(error)


@settings(max_examples=examples(60), deadline=None)
@given(st.integers(1, 6), st.integers(1, 9000), st.integers(1, 40), st.integers(1, 40), st.integers(0, 2**31 - 1))
def test_pushed_dot_products_become_the_distances_and_rank_as_the_distances_would(length, n, k, dim, seed):
    """A frame's dot products measured into the ring and pushed with its row and the rows' norms leave the ring
    holding what ``frame_distances_`` makes of them, and rank as those distances pushed do, bit for bit."""
    import torch

    from seqvpr.sequences._fused import frame_distances_
    from seqvpr.sequences.frame_pass import FrameRow, ReferenceBlocks

    rng = np.random.default_rng(seed)
    reference = rng.standard_normal((n, dim)).astype(np.float32)
    blocks = ReferenceBlocks(reference, columns=max(1, n // 3))  # several blocks where n allows
    segments = np.cumsum(rng.random(n) < 0.01)
    dots, measured = DiagonalSums(segments, length), DiagonalSums(segments, length)
    for _ in range(length + 2):
        frame = FrameRow.of(rng.standard_normal(dim))
        blocks.dots_into(frame.row, torch.from_numpy(dots.next_row())[None])
        distances = dots.next_row().copy()
        frame_distances_(distances, frame.numbers, blocks.norms)
        got, expected = dots.push_dots_topk(frame.numbers, blocks.norms, k), measured.push_topk(distances, k)
        np.testing.assert_array_equal(dots.ring, measured.ring)
        if expected is None:
            assert got is None
            continue
        np.testing.assert_array_equal(got[0], expected[0])
        np.testing.assert_array_equal(got[1], expected[1])


def test_pushed_dot_products_split_over_threads_as_one_scan(monkeypatch):
    """Dot products turned into distances part by part, over threads, rank as one scan of the distances does."""
    from seqvpr.sequences import _fused

    rng = np.random.default_rng(4)
    n, dim = 4 * _fused.PART_ROWS + 17, 3
    query, norms = rng.standard_normal(dim).astype(np.float32), rng.random(n).astype(np.float32) + 1
    rows = [rng.integers(-2, 2, n).astype(np.float32) for _ in range(3)]
    split, whole = DiagonalSums(np.zeros(n), 3), DiagonalSums(np.zeros(n), 3)
    monkeypatch.setattr(_fused.numba, "get_num_threads", lambda: 3)
    for row in rows:
        split.next_row()[:] = row
        top = split.push_dots_topk(query, norms, 50)
    for row in rows:
        distances = row.copy()
        _fused.frame_distances_(distances, query, norms)
        one = whole.push_topk(distances, 50)
    np.testing.assert_array_equal(split.ring, whole.ring)
    np.testing.assert_array_equal(top[0], one[0])
    np.testing.assert_array_equal(top[1], one[1])
