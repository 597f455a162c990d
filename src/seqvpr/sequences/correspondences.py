"""Per-frame correspondences of sequence matches: which reference frame each frame of a query's window was matched
to by its best (top-1) match, so frame-level correctness can be measured (CaseVPR's image-level correspondence
precision), which Recall@K over whole windows cannot show.

A constant-velocity match pairs query frame k of the window with frame k of the reference window (the kernel's
windows, boundaries and segments); an adaptive match pairs them along its best path (``adaptive.adaptive_path``).
"""

from __future__ import annotations

import numpy as np
import torch

from seqvpr.sequences.adaptive import AdaptiveScorer, adaptive_path
from seqvpr.sequences.matching import frame_distances
from seqvpr.sequences.windows import SequenceSpec, window_frames, window_starts


def window_correspondences(best: np.ndarray, spec: SequenceSpec, query_segments: np.ndarray,
                           reference_segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Query rows and reference rows [n_query, L] of each query's top-1 constant-velocity (slope 1) match; -1
    where a query has no window or no match."""
    q_starts = window_starts(np.asarray(query_segments), spec.length, spec.offset, spec.boundary)
    r_starts = window_starts(np.asarray(reference_segments), spec.length, spec.offset, spec.boundary)
    matched = (q_starts >= 0) & (best >= 0)
    q_rows = np.full((len(best), spec.length), -1, dtype=np.int64)
    r_rows = np.full_like(q_rows, -1)
    q_rows[matched] = window_frames(q_starts[matched], spec.length)
    ref_start = r_starts[np.maximum(best, 0)]
    ok = matched & (ref_start >= 0)
    r_rows[ok] = window_frames(ref_start[ok], spec.length)
    q_rows[~ok] = -1
    return q_rows, r_rows


def adaptive_correspondences(query: torch.Tensor, reference, best: np.ndarray, spec: SequenceSpec,
                             scorer: AdaptiveScorer, query_segments: np.ndarray, reference_segments: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Query rows and reference rows [n_query, L] along each query's top-1 adaptive path (-1 where none): the
    window's frames against the reference stretch the path can reach around the match."""
    q_starts = window_starts(np.asarray(query_segments), spec.length, spec.offset, "drop")
    r_seg = np.asarray(reference_segments)
    q_rows = np.full((len(best), spec.length), -1, dtype=np.int64)
    r_rows = np.full_like(q_rows, -1)
    reach_before, reach_after = spec.offset * scorer.max_step, (spec.length - 1 - spec.offset) * scorer.max_step
    for i in np.flatnonzero((q_starts >= 0) & (best >= 0)):
        j = int(best[i])
        lo, hi = max(0, j - reach_before), min(len(r_seg), j + reach_after + 1)
        frames = window_frames(q_starts[i : i + 1], spec.length)[0]
        stretch = torch.as_tensor(np.asarray(reference[lo:hi]), dtype=query.dtype)
        d = frame_distances(query[torch.as_tensor(frames)], stretch).numpy()
        q_rows[i] = frames
        r_rows[i] = adaptive_path(d, j - lo, spec.offset, scorer, r_seg[lo:hi]) + lo
    return q_rows, r_rows
