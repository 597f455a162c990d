"""Hierarchical matching (HVPR, CaseVPR): a retrieval matcher's shortlist of N reference windows per query,
re-ranked by a sequence matcher (exact sequence distance, or adaptive inside each candidate's stretch)."""

from __future__ import annotations

from dataclasses import replace
from collections.abc import Callable, Mapping
from typing import Any

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.matchers.base import Matcher
from seqvpr.results import MatchResult
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.progress import ProgressFactory
from seqvpr.matchers.sequence import SequenceMatcher

HVPR_SHORTLIST = 20  # HVPR's default shortlist length (the top N re-ranked)


class HierarchicalMatcher(Matcher):
    """``shortlist`` proposes ``depth`` candidates a query (at least K), ``rerank`` orders them; K from ``rerank``."""

    family = "hierarchical"

    def __init__(self, shortlist: Matcher, rerank: SequenceMatcher, depth: int = HVPR_SHORTLIST) -> None:
        super().__init__(rerank.settings, shortlist.progress)
        self.shortlist, self.reranker, self.depth = shortlist, rerank, depth

    @classmethod
    def from_method(cls, method: Any, settings: MatchSettings, models: Mapping[str, Any], build: Callable[..., Matcher],
                    progress: ProgressFactory | None = None, **conf: Any) -> HierarchicalMatcher:
        """The ``proposer`` retrieval method of ``conf`` (SeqNet's when a SeqNet model is given, else SeqGeM) with
        the models it takes, its top ``rerank`` N (default 20) re-ranked by the method's sequence search."""
        from seqvpr.matchers.rows import frame_transform
        from seqvpr.matchers.sequence import search_of

        first = conf.get("proposer") or ("seqnet" if "seqnet" in models else "seqgem")
        proposer = build(first, settings, models, progress=progress, index=conf.get("index") or "flat",
                         accepted_only=True)
        if proposer.family != "retrieval":
            raise SeqvprError(f"hvpr: the shortlist must be a retrieval method, got {first!r}")
        reranker = SequenceMatcher(settings, search_of(method, conf), frame_transform(models))
        return cls(proposer, reranker, conf.get("rerank") or HVPR_SHORTLIST)

    def own_settings(self) -> dict[str, Any]:
        return {"shortlist": self.shortlist.own_settings(), "depth": self.depth, **self.reranker.own_settings()}

    def span(self) -> int:
        return max(self.shortlist.span(), self.reranker.span())

    def topk(self, reference: Reference, query: Traversal) -> MatchResult:
        proposer = self.shortlist
        candidates = proposer.with_settings(replace(proposer.settings, k=max(self.depth, proposer.settings.k))
                                            ).topk(reference, query)
        return self.reranker.rerank(reference, query, candidates.topk)
