"""Shortlisting any matcher that scores single windows: a nearest-neighbour search (``Neighbours``: a saved map's
faiss index, a sharded map's indexes merged, a brute-force search in a test) proposes candidate windows, and the
matcher re-ranks only those, offline (``topk``) or a frame at a time (``stream``)."""

from __future__ import annotations

from dataclasses import replace
from typing import Protocol

import numpy as np
import torch

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SettingError
from seqvpr.matchers.base import Matcher, WrappedMatcher
from seqvpr.results import MatchResult, TopK
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.matchers.rows import query_rows


class Neighbors(Protocol):
    """The nearest reference rows of query rows: ``over`` is what the search holds vectors of (``frames``, or
    ``METHOD:L`` windows, whose search pools the query's windows itself), ``vectors`` how many it holds."""

    over: str
    vectors: int

    def search(self, rows: torch.Tensor, segments: np.ndarray, width: int) -> TopK:
        """The ``width`` nearest reference rows of each query row (or window), -1 / +inf where none."""
        ...


class Shortlisted(WrappedMatcher):
    """``matcher`` over the candidates ``neighbours`` proposes: each query frame's ``shortlist`` S nearest
    reference frames place candidate windows (with the ``history`` H frames before each window, up to (L + H) x S
    a query; an index over windows: each window's own S nearest), re-ranked by the matcher's window distance. Only
    a frame-matching matcher re-ranks such candidates, and only over the rows the search holds (no transform)."""

    def __init__(self, matcher: Matcher, neighbors: Neighbors, shortlist: int, history: int = 0) -> None:
        check_shortlistable(matcher)
        if history and neighbors.over != "frames":
            raise SettingError(f"{{history}} needs an index over frames; this one is over {neighbors.over}")
        super().__init__(matcher)
        self.neighbors, self.shortlist, self.history = neighbors, shortlist, history

    def with_settings(self, settings: MatchSettings) -> Shortlisted:
        return Shortlisted(self.matcher.with_settings(settings), self.neighbors, self.shortlist, self.history)

    def topk(self, reference: Reference, query: Traversal) -> MatchResult | None:
        from seqvpr.sequences.rerank import frame_shortlist
        from seqvpr.sequences.windows import window_starts

        settings = self.settings
        rows = query_rows(query, replace(settings, device="cpu", dtype="float32"))
        shortlist, history = shortlist_size(self.shortlist, self.history, self.neighbors.vectors, len(query),
                                            settings)
        found = self.neighbors.search(rows, query.segment_ids, shortlist)
        spec, segments = settings.sequence, query.segment_ids
        starts = window_starts(segments, spec.length, spec.offset, spec.boundary)
        if self.neighbors.over == "frames":
            candidates = frame_shortlist(found.indices, starts, spec, len(reference), history=history,
                                         query_segments=segments)
        else:
            candidates = TopK(found.indices, found.distances, starts >= 0)
        result = self.matcher.rerank(reference, query, candidates)
        return None if result is None else replace(result, shortlist=candidates)  # None: another rank's

    def stream(self, reference: Reference, exclusion: int = 10):
        """The shortlist a frame at a time (``ShortlistStepper``): its cost independent of the reference's size."""
        from seqvpr.matchers.stream import ShortlistStepper

        if self.neighbors.over != "frames":
            raise SettingError(f"a {{shortlist}} a frame at a time needs an index over frames; this one is over "
                              f"{self.neighbors.over}")
        from seqvpr.matchers.sharded import is_sharded

        whole = reference.as_map() if is_sharded(reference) else reference  # a window's rows, read through its shards
        return ShortlistStepper(self.matcher, whole, self.neighbors, self.shortlist, self.history, exclusion)


def check_shortlistable(matcher: Matcher) -> None:
    """A shortlist's candidates are re-ranked by a frame-matching matcher's window distance, over the rows the
    search holds (so no transform of them at match time)."""
    if matcher.family != "matching":
        raise SettingError(f"{{shortlist}} applies to the frame-matching methods (single, matching, seqmatchnet), "
                           f"not {{method}} {matcher.method}")
    if getattr(matcher, "transform", None) is not None:
        raise SettingError("{shortlist} with a SeqMatchNet model needs a map built through it: the index holds "
                           "untransformed frames")


def shortlist_size(shortlist: int, history: int, vectors: int, n_query: int, settings: MatchSettings
                   ) -> tuple[int, int]:
    """The shortlist S and history H a search uses: S clipped to the index's ``vectors`` and H to the query's
    frames (more finds nothing more: the result is the same), then the candidate table, n_query x (L + H) x S rows,
    checked against ``settings.memory_budget`` before any search (one line naming the options)."""
    shortlist, history = min(shortlist, max(vectors, 1)), min(history, n_query)
    cost = n_query * (settings.sequence.length + history) * shortlist * 8 * 3  # neighbours, candidates, sorting
    if settings.memory_budget is not None and cost > settings.memory_budget:
        raise SettingError(f"{{shortlist}} {shortlist} with {{history}} {history} and {{seq_len}} "
                           f"{settings.sequence.length}: the candidates of {n_query} queries need {cost / 2**20:.0f} "
                           f"MiB, over the {{memory_budget}} of {settings.memory_budget / 2**20:.0f} MiB (lower them)")
    return shortlist, history


class ExactNeighbors:
    """Brute-force nearest reference frames (Euclidean, the tie rule's order): an exact stand-in for a flat index."""

    over = "frames"

    def __init__(self, rows) -> None:
        self.rows = torch.as_tensor(np.asarray(rows, np.float32))
        self.vectors = len(self.rows)

    def search(self, rows: torch.Tensor, segments: np.ndarray, width: int) -> TopK:
        from seqvpr.sequences.topk import best_of

        distances = torch.cdist(rows.float()[None], self.rows[None])[0].double().numpy()
        candidates = np.broadcast_to(np.arange(self.vectors), distances.shape)
        indices, values = best_of(candidates, distances, min(width, self.vectors))
        return TopK(indices, values, np.ones(len(rows), bool))
