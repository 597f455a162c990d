"""Hierarchical matching (HVPR): a cheap shortlist, then exact sequence re-ranking of the shortlisted frames.

The shortlist is any ``TopK`` over reference frames (for instance faiss over SeqNet S5 or SeqGeM sequence
descriptors); the re-ranking distance is the matching kernel's (mean of order-aligned frame distances between
the query's and the candidate's windows), over the descriptors given (e.g. SeqMatchNet-transformed frames).
With the whole reference as the shortlist it equals exhaustive sequence matching.
"""

from __future__ import annotations

import numpy as np
import torch

from seqvpr.errors import SeqvprError
from seqvpr.sequences.topk import best_of
from seqvpr.results import TopK
from seqvpr.sequences.matching import aligned_sequence_distances
from seqvpr.sequences.windows import SequenceSpec, window_frames, window_starts


def rerank(
    query: torch.Tensor,
    reference: torch.Tensor,
    shortlist: TopK,
    spec: SequenceSpec,
    query_segments: np.ndarray | None = None,
    reference_segments: np.ndarray | None = None,
    *,
    k: int | None = None,
    memory_budget: int = 256 * 1024**2,
) -> TopK:
    """The shortlisted reference frames of each query re-ordered by exact sequence distance; the best ``k`` kept.

    ``query`` and ``reference`` are frame descriptors [n, D] (normalised as the caller wants). Candidates whose
    reference window does not exist (segment ends) drop out; queries without a window keep none.
    """
    if any(v != 1.0 for v in spec.velocities):
        raise SeqvprError("re-ranking compares windows at one speed; use velocities 1")
    if shortlist.indices.shape[0] != len(query):
        raise SeqvprError(f"the shortlist has {shortlist.indices.shape[0]} query rows, the query has {len(query)} frames")
    n_q, n_r = len(query), len(reference)
    q_seg = np.zeros(n_q, np.int64) if query_segments is None else np.asarray(query_segments)
    r_seg = np.zeros(n_r, np.int64) if reference_segments is None else np.asarray(reference_segments)
    q_starts = window_starts(q_seg, spec.length, spec.offset, spec.boundary)
    r_starts = window_starts(r_seg, spec.length, spec.offset, spec.boundary)
    candidates = shortlist.indices
    keep = candidates.shape[1] if k is None else min(k, candidates.shape[1])
    indices = np.full((n_q, keep), -1, dtype=np.int64)
    distances = np.full((n_q, keep), np.inf, dtype=np.float64)
    has_window = (q_starts >= 0) & shortlist.has_window
    rows = np.flatnonzero(has_window)
    per_query = max(1, candidates.shape[1] * spec.length * query.shape[1] * query.element_size())
    step = max(1, memory_budget // per_query)
    for begin in range(0, len(rows), step):
        batch = rows[begin : begin + step]
        picked = candidates[batch]
        starts = np.where(picked >= 0, r_starts[np.maximum(picked, 0)], -1)
        valid = starts >= 0
        d = _candidate_distances(query, reference, q_starts[batch], starts, spec.length)
        d[~valid] = np.inf
        indices[batch], distances[batch] = best_of(picked, d, keep)
    return TopK(indices, distances, has_window)


def _candidate_distances(
    query: torch.Tensor, reference: torch.Tensor, q_starts: np.ndarray, r_starts: np.ndarray, length: int
) -> np.ndarray:
    """Sequence distances [b, K] between each query window and its candidate windows (start -1: +inf): one numba
    pass over the rows on CPU, a gather of the windows elsewhere."""
    tensor = isinstance(reference, torch.Tensor)
    if (tensor and query.device.type == "cpu" and reference.device.type == "cpu" and not query.requires_grad
            and reference.dtype in (torch.float32, torch.float64)):
        from seqvpr.sequences._fused import window_distances

        return window_distances(query.numpy(), reference.numpy(), q_starts, r_starts, length)
    q_windows = query[torch.as_tensor(window_frames(q_starts, length), device=query.device)]  # [b, L, D]
    r_frames = window_frames(np.maximum(r_starts, 0).reshape(-1), length).reshape(*r_starts.shape, length)
    gathered = reference[torch.as_tensor(r_frames, device=reference.device)] if tensor else reference[r_frames]
    r_windows = torch.as_tensor(gathered).to(query.device, query.dtype)
    return aligned_sequence_distances(q_windows[:, None], r_windows).double().cpu().numpy()


def frame_shortlist(
    neighbours: np.ndarray,
    query_starts: np.ndarray,
    spec: SequenceSpec,
    n_reference: int,
    *,
    history: int = 0,
    query_segments: np.ndarray | None = None,
) -> TopK:
    """Candidate reference frames of each query from the nearest reference frames of every frame of its window.

    ``neighbours`` [n_query, S] are the S nearest reference frames of each query frame (-1 for none). A reference
    frame r found for the k-th frame of the window starting at ``query_starts[i]`` places the candidate window
    there, so the candidate is the frame ``r - k + offset`` (slope 1). With ``history`` H the H query frames before
    the window (same segment) place candidates too (k = -1 .. -H): where the robot just was, carried forward. Each
    query gets the union (up to (L + H) * S, duplicates and frames off the reference dropped); -1 pads. Distances
    are not known.
    """
    starts = np.asarray(query_starts, dtype=np.int64)
    has_window = starts >= 0
    length, width = spec.length, neighbours.shape[1]
    positions = np.arange(-history, length)
    frames = np.maximum(starts, 0)[:, None] + positions[None, :]  # [n, H + L]
    usable = frames >= 0
    if history:
        segments = np.zeros(len(neighbours), np.int64) if query_segments is None else np.asarray(query_segments)
        own = segments[np.maximum(starts, 0)]
        usable &= segments[np.maximum(frames, 0)] == own[:, None]
    found = neighbours[np.maximum(frames, 0)]  # [n, H + L, S]
    shift = spec.offset - positions[None, :, None]
    keep = (found >= 0) & usable[:, :, None]
    candidates = np.where(keep, found + shift, -1).reshape(len(starts), (history + length) * width)
    candidates[(candidates < 0) | (candidates >= n_reference) | ~has_window[:, None]] = -1
    candidates.sort(axis=1)
    duplicate = np.zeros_like(candidates, dtype=bool)
    duplicate[:, 1:] = candidates[:, 1:] == candidates[:, :-1]
    candidates[duplicate] = -1
    candidates.sort(axis=1)  # -1s first, then the distinct candidates ascending
    candidates = candidates[:, ::-1].copy()  # distinct candidates first (descending), -1s last
    return TopK(candidates, np.zeros(candidates.shape), has_window)
