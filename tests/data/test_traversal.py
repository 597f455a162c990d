"""Segments of a traversal: removed frames and gaps in frame numbers or time start new ones."""

import numpy as np

from seqvpr.data.traversal import Traversal, segments_from_gaps


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
