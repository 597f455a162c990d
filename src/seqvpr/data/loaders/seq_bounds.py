"""seqBounds files (seqNet / SeqMatchNet / MSLS ``seqBoundsFiles/*_seqBounds.txt``): one ``start end`` row per
frame, the [start, end) of the sequence the frame belongs to. Each sequence becomes a segment, so no window ever
spans two sequences."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from seqvpr.errors import SeqvprError


def load_seq_bounds(path: str | Path, n_frames: int) -> np.ndarray:
    """Segment ids [n_frames] from a seqBounds file whose rows are the frames' ``start end``; one line on any fault."""
    path = Path(path)
    if not path.exists():
        raise SeqvprError(f"{path}: seqBounds file not found")
    from seqvpr.arrays import check_regular_file

    check_regular_file(path, "a seqBounds file")
    if path.stat().st_size == 0:
        raise SeqvprError(f"{path}: the seqBounds file is empty; expected {n_frames} rows (one per frame) of 'start end'")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # a file of only blank lines: its shape is refused below
            bounds = np.loadtxt(path, ndmin=2)
    except ValueError as error:
        raise SeqvprError(f"{path}: not a seqBounds file of 'start end' rows ({error})") from None
    if bounds.shape != (n_frames, 2):
        raise SeqvprError(f"{path}: {bounds.shape[0]} rows of {bounds.shape[1]} values; expected {n_frames} rows "
                          "(one per frame) of 'start end'")
    if not np.array_equal(bounds, np.round(bounds)):
        raise SeqvprError(f"{path}: start and end must be whole frame numbers")
    starts, ends = bounds[:, 0].astype(np.int64), bounds[:, 1].astype(np.int64)
    rows = np.arange(n_frames)
    bad = np.flatnonzero((starts > rows) | (ends <= rows) | (ends > n_frames))
    if len(bad):
        i = int(bad[0])
        raise SeqvprError(f"{path}: line {i + 1}: frame {i} is not inside its sequence [{starts[i]}, {ends[i]})")
    return np.unique(starts, return_inverse=True)[1].astype(np.int64)


def seq_bounds_rows(segment_ids: np.ndarray) -> np.ndarray:
    """The seqBounds rows [n, 2] of a traversal's segments (what ``load_seq_bounds`` reads back)."""
    from seqvpr.sequences.windows import segment_bounds

    start, end = segment_bounds(np.asarray(segment_ids))
    return np.stack([start, end], axis=1)
