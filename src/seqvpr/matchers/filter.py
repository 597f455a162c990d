"""The topological filter (an HMM forward pass over reference frames), offline over a whole query or one frame at
a time: stops and speed changes are its transitions, distances its likelihoods (scale calibrated on the
reference). Distances in its top-K are 1 - belief mass.

Same name as ``seqvpr.sequences.filter``: the filter as a family's matcher; its algorithm there."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.matchers.base import Matcher
from seqvpr.results import MatchResult
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.matchers.rows import check_dimensions, kernel_rows, query_rows
from seqvpr.progress import ProgressFactory
from seqvpr.sequences.filter import FilterSettings

if TYPE_CHECKING:
    from seqvpr.matchers.stream import Stepper


class FilterMatcher(Matcher):
    """The filter run forward over the query (one frame a query; ``seed`` draws the calibration's sample frames)."""

    family = "filter"

    def __init__(self, settings: MatchSettings, filter_settings: FilterSettings = FilterSettings(), seed: int = 0,
                 transform=None, progress: ProgressFactory | None = None) -> None:
        super().__init__(settings, progress)
        self.filter_settings, self.seed, self.transform = filter_settings, seed, transform

    @classmethod
    def from_method(cls, method: Any, settings: MatchSettings, models: Mapping[str, Any], build: Callable[..., Matcher],
                    progress: ProgressFactory | None = None, **conf: Any) -> FilterMatcher:
        """The filter with ``conf``'s ``filter`` settings and ``seed``, through a SeqMatchNet model's transform."""
        from seqvpr.matchers.rows import frame_transform

        return cls(settings, conf.get("filter") or FilterSettings(), int(conf.get("seed") or 0),
                   frame_transform(models), progress)

    def own_settings(self) -> dict[str, Any]:
        return {"filter": self.filter_settings.as_dict(), "seed": self.seed}

    def span(self) -> int:
        return 1

    def topk(self, reference: Reference, query: Traversal) -> MatchResult:
        from seqvpr.matchers.rows import transform_pair
        from seqvpr.sequences.filter import TopologicalFilter, filter_topk, map_distance_scale
        from seqvpr.sequences.matching import reference_squared_norms

        reference, query = transform_pair(reference, query, self.transform, self.settings.device)
        ref, qry = kernel_rows(reference, self.settings), query_rows(query, self.settings)
        check_dimensions(reference, query, ref, qry)
        norms = reference_squared_norms(ref)
        scale = map_distance_scale(ref, norms, self.filter_settings, seed=self.seed)
        topological = TopologicalFilter(reference.segment_ids, scale, self.filter_settings)
        top = filter_topk(qry, ref, norms, topological, self.settings.k, query.segment_ids)
        return MatchResult(reference.frames, query, top, self.settings)

    def stream(self, reference: Reference, exclusion: int = 10) -> Stepper:
        from seqvpr.matchers.stream import FilterStepper

        return FilterStepper(self, reference)
