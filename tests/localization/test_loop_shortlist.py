"""Loop closures through a growing frame shortlist: each frame's neighbours are its nearest eligible earlier frames
whatever block it is searched in (a brute-force oracle), and with an exact index as wide as the drive the
shortlisted loops are the exhaustive ones."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from seqvpr.data.traversal import Traversal
from seqvpr.localization import loop_shortlist
from seqvpr.localization.loop_shortlist import GrowingIndex, blocks, check_shortlist_index
from seqvpr.localization.loops import LoopSettings, find_loops, make_drive
from tests.helpers import raises_one_line


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 80), st.integers(0, 10), st.integers(1, 12), st.integers(1, 20), st.integers(0, 2**31 - 1))
def test_each_frames_neighbours_are_its_nearest_eligible_frames_in_any_block(n, exclude, width, block, seed):
    rng = np.random.default_rng(seed)
    rows = rng.normal(size=(n, 5)).astype(np.float32)
    own = np.arange(n)  # a frame's eligible rows lie before it, and never shrink
    limits = np.maximum.accumulate(np.clip(own - exclude + rng.integers(-2, 3, n), 0, own))
    grown = GrowingIndex(check_shortlist_index("flat"), rows)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(loop_shortlist, "BLOCK", block)
        patch.setattr(loop_shortlist, "EXTRA", block // 2)
        spans = blocks(limits)
    assert [a for a, _ in spans] == sorted({a for a, _ in spans}) and spans[-1][1] == n
    found = np.concatenate([grown.nearest_eligible(a, b, limits, width) for a, b in spans])
    for i in range(n):
        distances = np.linalg.norm(rows[: limits[i]] - rows[i], axis=1)
        expected = np.argsort(distances, kind="stable")[:width]
        np.testing.assert_array_equal(np.sort(found[i][found[i] >= 0]), np.sort(expected))


@settings(max_examples=30, deadline=None)
@given(st.integers(2, 50), st.integers(1, 2), st.integers(1, 5), st.integers(0, 8), st.integers(0, 2**31 - 1))
def test_a_flat_shortlist_as_wide_as_the_drive_gives_the_exhaustive_loops(n, n_sessions, length, exclude, seed):
    rng = np.random.default_rng(seed)
    parts = [Traversal(f"s{s}", np.arange(n), np.sort(rng.integers(0, 2, n)).astype(np.int64),
                       rng.normal(size=(n, 6)).astype(np.float32), source=f"s{s}") for s in range(n_sessions)]
    drive = make_drive(parts)
    try:
        exhaustive = find_loops(drive, LoopSettings(seq_len=length, exclude=f"{exclude}f"))
    except Exception as error:  # L longer than every segment: the kernel's one line
        assert "longer than every" in str(error)
        return
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(loop_shortlist, "BLOCK", 7)
        patch.setattr(loop_shortlist, "EXTRA", 3)
        shortlisted = find_loops(drive, LoopSettings(seq_len=length, exclude=f"{exclude}f", shortlist=2 * n,
                                                     shortlist_index="flat"))
    np.testing.assert_array_equal(shortlisted.match, exhaustive.match)
    found = exhaustive.match >= 0
    np.testing.assert_allclose(shortlisted.distance[found], exhaustive.distance[found], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(shortlisted.score, exhaustive.score, atol=1e-5)
    np.testing.assert_array_equal(shortlisted.accepted, exhaustive.accepted)


def test_a_narrow_hnsw_shortlist_finds_the_revisit():
    rng = np.random.default_rng(3)
    places = rng.normal(size=(300, 32))
    rows = np.concatenate([places, places[50:250] + 0.05 * rng.normal(size=(200, 32))]).astype(np.float32)
    drive = make_drive([Traversal("run", np.arange(500), np.zeros(500, np.int64), rows, source="run")])
    loops = find_loops(drive, LoopSettings(seq_len=5, exclude="50f", shortlist=5))
    revisit = np.arange(304, 500)  # frames 300..499 revisit 50..249; from the 5th on the whole window does
    np.testing.assert_array_equal(loops.match[revisit], revisit - 250)


def test_an_index_that_must_be_trained_is_refused():
    raises_one_line("grows its index", LoopSettings, shortlist=5, shortlist_index="ivf:16")
    raises_one_line("shortlist", LoopSettings, shortlist=-1)
