"""Re-ranking a shortlist, written once: each query's candidate reference windows scored by a window distance's
candidate form and the best K kept by the tie rule (``rerank_candidates``). The sequence family's candidate form
(``candidate_distances``: the kernel's mean of order-aligned frame distances between a query window and given
reference windows) and its re-ranking (``rerank``: HVPR's exact re-ranking of a cheap shortlist) live here, with
the candidates a frame shortlist places (``frame_shortlist``). With the whole reference as the shortlist,
re-ranking equals exhaustive sequence matching.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from seqvpr.errors import SeqvprError
from seqvpr.results import TopK
from seqvpr.sequences.matching import aligned_sequence_distances
from seqvpr.sequences.topk import best_of
from seqvpr.sequences.windows import SequenceSpec, window_frames, window_starts


def rerank_candidates(candidates: TopK, query_has_window: np.ndarray, k: int | None,
                      distances_of: Callable[[np.ndarray, np.ndarray], np.ndarray], batch: int = 1,
                      tick: Callable[[int], None] | None = None) -> TopK:
    """The candidates [n_query, C] (reference anchor rows, -1 for none) of each query that has a window, scored by
    ``distances_of(query_rows [b], anchors [b, C]) -> [b, C]`` (+inf where no window exists) ``batch`` queries at a
    time, the best ``k`` kept by the tie rule (``best_of``); queries without a window keep none."""
    picked_all = candidates.indices
    keep = picked_all.shape[1] if k is None else min(k, picked_all.shape[1])
    indices = np.full((len(picked_all), keep), -1, dtype=np.int64)
    distances = np.full((len(picked_all), keep), np.inf, dtype=np.float64)
    has_window = query_has_window & candidates.has_window
    rows = np.flatnonzero(has_window)
    for begin in range(0, len(rows), batch):
        chosen = rows[begin : begin + batch]
        picked = picked_all[chosen]
        indices[chosen], distances[chosen] = best_of(picked, distances_of(chosen, picked), keep)
        if tick:
            tick(len(chosen))
    return TopK(indices, distances, has_window)


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
    per_query = max(1, shortlist.indices.shape[1] * spec.length * query.shape[1] * query.element_size())

    def sequence_distances(rows: np.ndarray, anchors: np.ndarray) -> np.ndarray:
        starts = np.where(anchors >= 0, r_starts[np.maximum(anchors, 0)], -1)
        found = candidate_distances(query, reference, q_starts[rows], starts, spec.length)
        found[starts < 0] = np.inf
        return found

    return rerank_candidates(shortlist, q_starts >= 0, k, sequence_distances, max(1, memory_budget // per_query))


def candidate_distances(
    query: torch.Tensor, reference, q_starts: np.ndarray, r_starts: np.ndarray, length: int
) -> np.ndarray:
    """The sequence family's candidate form: distances [b, C] between each query window (rows from
    ``q_starts[i]``) and its candidate reference windows (rows from ``r_starts[i, c]``; -1: +inf), the mean of
    order-aligned frame distances. On CPU one compiled pass (float64 sums) whatever holds the rows: a tensor or an
    array is read in place, any other rows (coded, read through shards) are gathered first, so every container gives
    the same numbers; on another device, a gather of the windows there."""
    on_cpu = query.device.type == "cpu" and not query.requires_grad
    if isinstance(reference, torch.Tensor):
        if on_cpu and reference.device.type == "cpu" and reference.dtype in (torch.float32, torch.float64):
            return _compiled_distances(query, reference.numpy(), q_starts, r_starts, length)
        return _gathered_distances(query, reference, q_starts, r_starts, length)
    if on_cpu and isinstance(reference, np.ndarray) and reference.dtype in (np.float32, np.float64):
        return _compiled_distances(query, reference, q_starts, r_starts, length)
    windows = window_frames(np.maximum(r_starts, 0).reshape(-1), length).reshape(-1)  # rows any reference takes
    rows = np.asarray(reference[windows], dtype=np.float32)
    if not on_cpu:
        return _gathered_distances(query, torch.from_numpy(rows).to(query.device), q_starts,
                                   _laid_out(r_starts, length), length)
    return _compiled_distances(query, rows, q_starts, _laid_out(r_starts, length), length)


def _laid_out(r_starts: np.ndarray, length: int) -> np.ndarray:
    """The starts of the candidate windows once their rows are gathered one window after another (-1 kept)."""
    laid = (np.arange(r_starts.size, dtype=np.int64) * length).reshape(r_starts.shape)
    return np.where(r_starts >= 0, laid, -1)


def _compiled_distances(query: torch.Tensor, reference: np.ndarray, q_starts, r_starts, length: int) -> np.ndarray:
    from seqvpr.sequences._fused import window_distances

    return window_distances(query.numpy(), reference, q_starts, r_starts, length)


def _gathered_distances(query: torch.Tensor, reference: torch.Tensor, q_starts, r_starts, length: int) -> np.ndarray:
    """The windows gathered on the query's device and compared there (a GPU, or gradients)."""
    q_windows = query[torch.as_tensor(window_frames(q_starts, length), device=query.device)]  # [b, L, D]
    r_frames = window_frames(np.maximum(r_starts, 0).reshape(-1), length).reshape(*r_starts.shape, length)
    r_windows = reference[torch.as_tensor(r_frames, device=reference.device)].to(query.device, query.dtype)
    return aligned_sequence_distances(q_windows[:, None], r_windows).double().cpu().numpy()


def frame_shortlist(
    neighbors: np.ndarray,
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
    length, width = spec.length, neighbors.shape[1]
    positions = np.arange(-history, length)
    frames = np.maximum(starts, 0)[:, None] + positions[None, :]  # [n, H + L]
    usable = frames >= 0
    if history:
        segments = np.zeros(len(neighbors), np.int64) if query_segments is None else np.asarray(query_segments)
        own = segments[np.maximum(starts, 0)]
        usable &= segments[np.maximum(frames, 0)] == own[:, None]
    found = neighbors[np.maximum(frames, 0)]  # [n, H + L, S]
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
