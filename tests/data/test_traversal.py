"""Segments of a traversal: removed frames and gaps in frame numbers or time start new ones."""

import numpy as np
import pytest

from seqvpr.data.traversal import Traversal, segments_from_gaps
from tests.helpers import raises_one_line


def test_select_starts_new_segment_at_removed_frames():
    t = Traversal.from_descriptors(np.zeros((10, 2)))
    kept = t.select(np.array([0, 1, 2, 5, 6, 9]))
    assert list(kept.segment_ids) == [0, 0, 0, 1, 1, 2]
    assert list(kept.frame_index) == [0, 1, 2, 5, 6, 9]


def test_segments_from_gaps():
    ids = segments_from_gaps(frame_numbers=np.array([10, 20, 30, 50, 60]), max_frame_step=10)
    assert list(ids) == [0, 0, 0, 1, 1]
    ids = segments_from_gaps(timestamps=np.array([0, 1, 2, 10, 11.0]), max_time_gap=3)
    assert list(ids) == [0, 0, 0, 1, 1]


@pytest.mark.parametrize("bad", [np.nan, np.inf, 1e300, -2e8])
def test_a_position_that_is_no_place_is_one_line(bad):
    positions = np.zeros((3, 2))
    positions[1, 0] = bad
    raises_one_line("position of frame 1 is not finite or beyond 1e+08 m", Traversal.from_descriptors,
                    np.ones((3, 4), np.float32), positions=positions)
