"""Retrieval by one sequence descriptor per window (smoothing, Delta, concatenation, SeqGeM, a trained SeqNet or
JIST's SeqGeM) searched with a faiss index: the compact alternative to frame sequence matching.

Same name as ``seqvpr.sequences.retrieval``: retrieval as a family's matcher; the faiss search there."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.matchers.base import Matcher
from seqvpr.results import MatchResult
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.matchers.rows import check_dimensions, query_rows, whole_rows
from seqvpr.progress import ProgressFactory


class RetrievalMatcher(Matcher):
    """Each side's windows pooled by ``pooling`` (``model``: a learned pooling, SeqNet or JIST's SeqGeM), the
    query's searched among the reference's by a faiss index of ``index`` kind (flat: exact; hnsw)."""

    family = "retrieval"

    def __init__(self, settings: MatchSettings, pooling: str, model: torch.nn.Module | None = None,
                 index: str = "flat", progress: ProgressFactory | None = None) -> None:
        super().__init__(settings, progress)
        if pooling == "seqgem-signed":  # SeqGeM keeping negative parts
            from seqvpr.sequences.descriptors import SeqGeM

            pooling, model = "seqgem", model or SeqGeM(mode="signed")
        self.pooling, self.model, self.index = pooling, model, index

    @classmethod
    def from_method(cls, method: Any, settings: MatchSettings, models: Mapping[str, Any], build: Callable[..., Matcher],
                    progress: ProgressFactory | None = None, **conf: Any) -> Matcher:
        """The method's pooling (its model's, for SeqNet and JIST) with ``conf``'s ``index`` kind; with ``rerank`` N
        > 0, its top N re-ranked by exact sequence distance (HVPR)."""
        matcher = cls(settings, method.pooling, pooling_module(method, models), conf.get("index") or "flat", progress)
        if not conf.get("rerank"):
            return matcher
        from seqvpr.matchers.hierarchical import HierarchicalMatcher
        from seqvpr.matchers.rows import frame_transform
        from seqvpr.matchers.sequence import SequenceMatcher

        return HierarchicalMatcher(matcher, SequenceMatcher(settings, transform=frame_transform(models)), conf["rerank"])

    def own_settings(self) -> dict[str, Any]:
        return {"pooling": self.pooling, "index": self.index}

    def topk(self, reference: Reference, query: Traversal) -> MatchResult:
        from seqvpr.sequences.descriptors import sequence_descriptors
        from seqvpr.sequences.retrieval import retrieve

        settings = self.settings
        ref, qry = whole_rows(reference, settings), query_rows(query, settings)
        check_dimensions(reference, query, ref, qry)
        spec, device = settings.sequence, settings.device
        ref_vectors = sequence_descriptors(ref, reference.segment_ids, spec, self.pooling, self.model, device=device)
        qry_vectors = sequence_descriptors(qry, query.segment_ids, spec, self.pooling, self.model, device=device)
        top = retrieve(qry_vectors, ref_vectors, settings.k, kind=self.index)
        return MatchResult(reference.frames, query, top, settings)


def pooling_module(method: Any, models: Mapping[str, Any]) -> torch.nn.Module | None:
    """The learned pooling a retrieval method uses: SeqNet itself, JIST's SeqGeM, or none."""
    if method.needs == "seqnet":
        return models["seqnet"].module
    if method.needs == "jist":
        return models["jist"].module.sequence_pool
    return None


class IndexedRetrieval(Matcher):
    """Retrieval by sequence descriptors a reference's own index already holds (a saved map indexed over this
    method's windows): the query's windows pooled as the index says and searched in it. ``open_index`` gives the
    index of the reference matched (each shard of a sharded map has its own) as ``Neighbours``."""

    family = "retrieval"

    def __init__(self, settings: MatchSettings, open_index: Callable[[Reference], Any]) -> None:
        super().__init__(settings)
        self.open_index = open_index

    def topk(self, reference: Reference, query: Traversal) -> MatchResult:
        import numpy as np

        from seqvpr.sequences.matching import unit_rows

        rows = unit_rows(torch.as_tensor(np.asarray(query.descriptors, dtype=np.float32)))
        index = self.open_index(reference)
        top = index.search(rows, query.segment_ids, min(self.settings.k, index.vectors))
        return MatchResult(reference.frames, query, top, self.settings)
