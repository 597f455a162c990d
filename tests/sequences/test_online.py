"""Incremental causal sequence matching against the plain-loop oracle, frame by frame, over random shapes,
segments and restarts."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.errors import SeqvprError
from seqvpr.sequences.online import DiagonalSums
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
        got = sums.push(np.linalg.norm(r - q[i], axis=1))
        if got is None:
            assert np.isinf(expected[i]).all()
            continue
        assert (np.isinf(got) == np.isinf(expected[i])).all()
        finite = np.isfinite(got)
        np.testing.assert_allclose(got[finite], expected[i][finite], rtol=1e-12)


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
