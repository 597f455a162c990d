"""Per-frame correspondences of sequence matches: which reference frame each frame of a query's window was matched
to by its best (top-1) match, so frame-level correctness can be measured (CaseVPR's image-level correspondence
precision), which Recall@K over whole windows cannot show.

A constant-velocity match pairs query frame k of the window with frame k of the reference window (the kernel's
windows, boundaries and segments); a search over several straight trajectories (a velocity sweep, SeqSLAM's
trajectory and hybrid searches) pairs them along the trajectory that scored the match; an adaptive match along its
best path (``adaptive.adaptive_path``). OpenSeqSLAM2's cone counts votes over many trajectories and pairs none.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from seqvpr.sequences.adaptive import AdaptiveScorer, adaptive_path
from seqvpr.sequences.matching import frame_distances, max_span, reference_rows, sequence_rows
from seqvpr.sequences.windows import SequenceSpec, velocity_steps, window_frames, window_starts


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
        stretch = reference_rows(reference, slice(lo, hi), query)
        d = frame_distances(query[torch.as_tensor(frames)], stretch).cpu().numpy()
        q_rows[i] = frames
        r_rows[i] = adaptive_path(d, j - lo, spec.offset, scorer, r_seg[lo:hi]) + lo
    return q_rows, r_rows


def trajectory_velocities(scorer, spec: SequenceSpec) -> tuple[float, ...] | None:
    """The straight trajectories a window scorer chooses among (None: it pairs no frames, as the cone)."""
    if scorer is None:
        return tuple(spec.velocities)
    velocities = getattr(scorer, "trajectory_velocities", None)
    return velocities(spec) if velocities is not None else None


def trajectory_correspondences(query: torch.Tensor, reference, best: np.ndarray, spec: SequenceSpec, scorer,
                               query_segments: np.ndarray, reference_segments: np.ndarray,
                               memory_budget: int | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Query rows and reference rows [n_query, L] along the straight trajectory that gave each query's top-1 match
    its distance: each of the scorer's velocities is scored again at the match, on the reference stretch around
    it, and the best one's frames are the pairs (-1 where a query has no match). None for a scorer that pairs no
    frames. A scorer that needs the whole traversals (hybrid) is prepared once, as the match prepared it."""
    velocities = trajectory_velocities(scorer, spec)
    if velocities is None:
        return None
    q_seg, r_seg = np.asarray(query_segments), np.asarray(reference_segments)
    if scorer is None:  # the kernel's own mean distance: every query at once
        return kernel_trajectories(query, reference, best, spec, q_seg, r_seg)
    if hasattr(scorer, "prepare"):
        scorer = scorer.prepare(query, reference, q_seg, r_seg, memory_budget)
    q_starts = window_starts(q_seg, spec.length, spec.offset, spec.boundary)
    halo = scorer.span(spec) if scorer is not None else max_span(spec)
    starts = {v: window_starts(r_seg, int(velocity_steps(spec.length, v)[-1]) + 1,
                               int(velocity_steps(spec.length, v)[spec.offset]), spec.boundary) for v in velocities}
    q_rows = np.full((len(best), spec.length), -1, dtype=np.int64)
    r_rows = np.full_like(q_rows, -1)
    for i in np.flatnonzero((q_starts >= 0) & (best >= 0)):
        j = int(best[i])
        lo, hi = max(0, j - halo), min(len(r_seg), j + halo + 1)
        frames = window_frames(q_starts[i : i + 1], spec.length)[0]
        stretch = reference_rows(reference, slice(lo, hi), query)
        d = frame_distances(query[torch.as_tensor(frames)], stretch)
        score = scorer.locate(frames, lo) if hasattr(scorer, "locate") else (scorer or sequence_rows)
        scores = [float(score(d, np.array([spec.offset]), np.array([0]), r_seg[lo:hi],
                              replace(spec, velocities=(v,)), inplace=False)[0, j - lo]) for v in velocities]
        chosen = velocities[int(np.argmin(scores))]
        if not np.isfinite(min(scores)) or starts[chosen][j] < 0:
            continue
        q_rows[i] = frames
        r_rows[i] = starts[chosen][j] + velocity_steps(spec.length, chosen)
    return q_rows, r_rows


def kernel_trajectories(query: torch.Tensor, reference, best: np.ndarray, spec: SequenceSpec, query_segments: np.ndarray,
                        reference_segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``trajectory_correspondences`` for the kernel's constant-velocity means, vectorised over the queries: each
    velocity's trajectory through each query's match is scored by its mean frame distance and the first best kept
    (a per-query loop cost many times the matching it followed). Reference rows are read for a block of queries at
    a time (a saved map's rows are never read whole)."""
    q_starts = window_starts(query_segments, spec.length, spec.offset, spec.boundary)
    matched = np.flatnonzero((q_starts >= 0) & (best >= 0))
    frames = window_frames(q_starts[matched], spec.length)  # [m, L]
    trajectories = []
    for velocity in spec.velocities:
        steps = velocity_steps(spec.length, velocity)
        starts = window_starts(reference_segments, int(steps[-1]) + 1, int(steps[spec.offset]), spec.boundary)
        start = starts[best[matched]]
        trajectories.append(np.where(start[:, None] >= 0, start[:, None] + steps[None, :], -1))
    paths = np.stack(trajectories, 1)  # [m, V, L]
    block = max(1, 2**22 // (len(spec.velocities) * spec.length * query.shape[1]))
    scores = np.concatenate([_trajectory_means(query, reference, frames[b : b + block], paths[b : b + block])
                             for b in range(0, len(matched), block)] or [np.zeros((0, len(spec.velocities)))])
    chosen = scores.argmin(1)
    found = np.isfinite(scores[np.arange(len(matched)), chosen])
    q_rows = np.full((len(best), spec.length), -1, dtype=np.int64)
    r_rows = np.full_like(q_rows, -1)
    q_rows[matched[found]] = frames[found]
    r_rows[matched[found]] = paths[np.arange(len(matched)), chosen][found]
    return q_rows, r_rows


def _trajectory_means(query: torch.Tensor, reference, frames: np.ndarray, paths: np.ndarray) -> np.ndarray:
    """Mean Euclidean frame distance [b, V] of each query window ``frames`` [b, L] along each trajectory ``paths``
    [b, V, L] of reference rows (+inf where a trajectory is -1: it has no window there)."""
    at = np.maximum(paths, 0)
    needed, where = np.unique(at, return_inverse=True)
    rows = reference[torch.as_tensor(needed)] if isinstance(reference, torch.Tensor) else reference[needed]
    rows = torch.as_tensor(np.asarray(rows) if not isinstance(rows, torch.Tensor) else rows, dtype=query.dtype)
    pairs = query[torch.as_tensor(frames)][:, None, :, :] - rows[torch.as_tensor(where.reshape(at.shape))]
    means = pairs.square().sum(-1).sqrt().mean(-1).numpy()
    return np.where(paths[:, :, 0] >= 0, means, np.inf)
