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
