"""Graph matching (GISM-style): the cheapest whole path through the frame distances, moving MIN..MAX reference
frames a query frame, with a hidden node for jumps. It scores whole paths over the whole query: offline only.

Same name as ``seqvpr.sequences.graph``: graph matching as a family's matcher; its algorithm there."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SettingError
from seqvpr.matchers.base import Matcher
from seqvpr.results import MatchResult
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.matchers.rows import check_dimensions, query_rows
from seqvpr.progress import ProgressFactory

if TYPE_CHECKING:
    from seqvpr.matchers.stream import Stepper


class GraphMatcher(Matcher):
    """Top-K reference frames per query frame by the cheapest path through them; ``steps`` (MIN, MAX) bound a
    query frame's move."""

    family = "graph"

    def __init__(self, settings: MatchSettings, steps: tuple[int, int] = (1, 2), transform=None,
                 progress: ProgressFactory | None = None) -> None:
        super().__init__(settings, progress)
        self.steps, self.transform = steps, transform

    @classmethod
    def from_method(cls, method: Any, settings: MatchSettings, models: Mapping[str, Any], build: Callable[..., Matcher],
                    progress: ProgressFactory | None = None, **conf: Any) -> GraphMatcher:
        """The graph search with ``conf``'s ``steps``, through a SeqMatchNet model's transform."""
        from seqvpr.matchers.rows import frame_transform

        from seqvpr.sequences.windows import check_steps

        return cls(settings, check_steps(tuple(conf.get("steps") or (1, 2))), frame_transform(models), progress)

    def own_settings(self) -> dict[str, Any]:
        return {"steps": list(self.steps)}

    def topk(self, reference: Reference, query: Traversal) -> MatchResult:
        from seqvpr.matchers.rows import transform_pair
        from seqvpr.sequences.graph import GraphSettings, graph_topk

        reference, query = transform_pair(reference, query, self.transform, self.settings.device)
        settings = self.settings
        ref, qry = query_rows(reference, settings), query_rows(query, settings)
        check_dimensions(reference, query, ref, qry)
        chosen = GraphSettings(fanout=self.steps[1], min_step=self.steps[0])
        top = graph_topk(qry, ref, settings.k, query.segment_ids, reference.segment_ids, chosen,
                         settings.memory_budget)
        return MatchResult(reference.frames, query, top, settings)

    def stream(self, reference: Reference, exclusion: int = 10) -> Stepper:
        raise SettingError("{method} graph scores whole paths over the whole query: it matches offline only")
