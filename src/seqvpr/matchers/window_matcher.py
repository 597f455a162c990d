"""A matcher written as one distance between windows: a subclass writes ``distances(reference_windows,
query_window)`` and the base does every search (all reference windows, blocked; a shortlist's candidates; the
windows a stepper names), so a new window distance runs offline, streaming, shortlisted and sharded unchanged."""

from __future__ import annotations

from abc import abstractmethod

import numpy as np
import torch

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.matchers.base import Matcher
from seqvpr.results import MatchResult, TopK
from seqvpr.matchers.rows import check_dimensions, query_rows, kernel_rows
from seqvpr.sequences.windows import window_frames, window_starts


class WindowMatcher(Matcher):
    """Top-K reference windows per query window by a distance a subclass defines over windows of L frames (both
    sides' segments respected, the settings' alignment and boundary). ``block`` bounds the reference windows
    gathered at once (``memory_budget`` bytes)."""

    family = "matching"

    @abstractmethod
    def distances(self, reference_windows: torch.Tensor, query_window: torch.Tensor) -> torch.Tensor:
        """Distances [C] between the reference windows [C, L, D] and one query window [L, D] (lower: nearer)."""

    def topk(self, reference: Reference, query: Traversal) -> MatchResult:
        rows, qry = kernel_rows(reference, self.settings), query_rows(query, self.settings)
        check_dimensions(reference, query, rows, qry)
        spec, k = self.settings.sequence, self.settings.k
        r_starts = window_starts(reference.segment_ids, spec.length, spec.offset, spec.boundary)
        anchors = np.flatnonzero(r_starts >= 0)
        candidates = np.broadcast_to(anchors, (len(query), len(anchors)))
        return self.rerank(reference, query, TopK(candidates, np.zeros(candidates.shape), np.ones(len(query), bool)),
                           k)

    def rerank(self, reference: Reference, query: Traversal, candidates: TopK, k: int | None = None) -> MatchResult:
        """The candidates' reference windows (anchor rows, -1 for none) re-ordered by the distance, best K kept
        (the one re-ranking, ``sequences.rerank.rerank_candidates``)."""
        from seqvpr.sequences.rerank import rerank_candidates

        rows, qry = kernel_rows(reference, self.settings), query_rows(query, self.settings)
        spec, k = self.settings.sequence, self.settings.k if k is None else k
        q_starts = window_starts(query.segment_ids, spec.length, spec.offset, spec.boundary)
        r_starts = window_starts(reference.segment_ids, spec.length, spec.offset, spec.boundary)

        def window_distances(chosen: np.ndarray, anchors: np.ndarray) -> np.ndarray:
            (row,), (picked,) = chosen, anchors
            starts = np.where(picked >= 0, r_starts[np.maximum(picked, 0)], -1)
            window = qry[int(q_starts[row]) : int(q_starts[row]) + spec.length]
            values = np.full(len(picked), np.inf)
            values[starts >= 0] = self.window_distances(rows, window, starts[starts >= 0])
            return values[None]

        top = rerank_candidates(candidates, q_starts >= 0, k, window_distances, tick=self.tick(len(query)))
        return MatchResult(reference.frames, query, top, self.settings)

    def window_distances(self, rows, window: torch.Tensor | np.ndarray, starts: np.ndarray) -> np.ndarray:
        """The distances of the query ``window`` [L, D] to the reference windows from ``starts``, gathered a block
        at a time within the memory budget."""
        window = torch.as_tensor(np.asarray(window, np.float32)) if not torch.is_tensor(window) else window.float()
        length, dim = window.shape
        budget = self.settings.memory_budget or 256 * 1024**2
        block = max(1, budget // max(1, length * dim * 4 * 2))
        out = np.empty(len(starts))
        for begin in range(0, len(starts), block):
            frames = window_frames(starts[begin : begin + block], length)
            gathered = rows[frames.ravel()]
            gathered = torch.as_tensor(np.asarray(gathered, np.float32)) if not torch.is_tensor(gathered) \
                else gathered.float()
            with torch.no_grad():
                found = self.distances(gathered.reshape(len(frames), length, dim), window)
            out[begin : begin + block] = found.double().cpu().numpy()
        return out
