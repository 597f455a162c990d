"""Frame sequence matching: the mean of order-aligned frame distances over windows of L frames, by the blocked
kernel, with a window scorer chosen by settings: the kernel's constant velocity (several velocities: SeqSLAM's
trajectory search), adaptive steps, or SeqSLAM's contrast enhancement, cone and hybrid searches. An optional
learned per-frame transform (SeqMatchNet) is applied to both sides first, here only."""

from __future__ import annotations

from dataclasses import dataclass, replace
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.progress import ProgressFactory
from seqvpr.matchers.base import Matcher
from seqvpr.results import MatchResult, TopK
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.matchers.rows import (
    check_dimensions, frame_transform, kernel_rows, query_rows, transform_pair,
)

if TYPE_CHECKING:
    from seqvpr.matchers.stream import Stepper
    from seqvpr.models.seqmatchnet import FrameTransform

Search = Literal["velocity", "adaptive", "seqslam", "seqslam-cone", "seqslam-hybrid"]
SEARCHES = ("velocity", "adaptive", "seqslam", "seqslam-cone", "seqslam-hybrid")


@dataclass(frozen=True)
class SequenceSearch:
    """How a window is scored: ``search`` (constant ``velocity`` along the spec's velocities; ``adaptive`` steps;
    SeqSLAM's contrast-enhanced trajectories, cone or hybrid), adaptive ``steps`` (MIN, MAX reference frames a query
    frame) and SeqSLAM's ``contrast_window`` (reference frames each distance is standardised against)."""

    search: Search = "velocity"
    steps: tuple[int, int] = (1, 2)
    contrast_window: int = 10

    def __post_init__(self) -> None:
        from seqvpr.sequences.windows import check_steps

        if self.search not in SEARCHES:
            raise SeqvprError(f"sequence search {self.search!r} is not known (choose from: {', '.join(SEARCHES)})")
        object.__setattr__(self, "steps", check_steps(self.steps))

    def scorer(self):
        """The window scorer: None for the kernel's constant velocity, else the search's."""
        if self.search == "adaptive":
            from seqvpr.sequences.adaptive import AdaptiveScorer

            return AdaptiveScorer(*self.steps)
        if self.search == "velocity":
            return None
        from seqvpr.sequences.seqslam import ConeScorer, ContrastScorer, HybridScorer

        if self.search == "seqslam-cone":  # it counts votes: the enhanced distances would go unread
            return ConeScorer()
        return ContrastScorer(self.contrast_window, HybridScorer() if self.search == "seqslam-hybrid" else None)


class SequenceMatcher(Matcher):
    """Top-K reference windows per query window by sequence distance (windows respect both sides' segments); a
    saved map's rows are read chunk by chunk as stored."""

    family = "matching"

    def __init__(self, settings: MatchSettings, search: SequenceSearch = SequenceSearch(),
                 transform: FrameTransform | None = None, progress: ProgressFactory | None = None) -> None:
        super().__init__(settings, progress)
        self.search, self.transform = search, transform
        self.scorer = search.scorer()

    @classmethod
    def from_method(cls, method: Any, settings: MatchSettings, models: Mapping[str, Any], build: Callable[..., Matcher],
                    progress: ProgressFactory | None = None, **conf: Any) -> SequenceMatcher:
        """The method's search with ``steps`` and ``contrast_window`` from ``conf``, through a SeqMatchNet model's
        transform when one is given."""
        return cls(settings, search_of(method, conf), frame_transform(models), progress)

    def own_settings(self) -> dict[str, Any]:
        return {"search": self.search.search, "steps": list(self.search.steps),
                "contrast_window": self.search.contrast_window}

    def span(self) -> int:
        from seqvpr.sequences.matching import max_span

        spec = self.settings.sequence
        return self.scorer.span(spec) if self.scorer is not None else max_span(spec)

    def transformed(self, reference: Reference, query: Traversal) -> tuple[Reference, Traversal]:
        """Both sides through the learned per-frame transform, when there is one."""
        return transform_pair(reference, query, self.transform, self.settings.device)

    def topk(self, reference: Reference, query: Traversal) -> MatchResult:
        from seqvpr.sequences.matching import sequence_topk

        reference, query = self.transformed(reference, query)
        settings = self.settings
        ref, qry = kernel_rows(reference, settings), query_rows(query, settings)
        check_dimensions(reference, query, ref, qry)
        tick = self.tick(len(query))
        topk = sequence_topk(qry, ref, settings.sequence, settings.k, query.segment_ids, reference.segment_ids,
                             memory_budget=settings.memory_budget, progress=tick, scorer=self.scorer)
        pairs = top1_pairs(qry, ref, topk, settings, self.scorer, query.segment_ids, reference.segment_ids)
        return MatchResult(reference.frames, query, topk, settings, correspondences=pairs)

    def rerank(self, reference: Reference, query: Traversal, candidates: TopK, k: int | None = None) -> MatchResult:
        """The candidates' reference windows re-ordered by this matcher's distance (exact sequence distance, or
        adaptive inside each candidate's stretch), best K kept, with the per-frame pairs of the top-1 matches."""
        from seqvpr.sequences.adaptive import AdaptiveScorer, adaptive_rerank
        from seqvpr.sequences.rerank import rerank

        reference, query = self.transformed(reference, query)
        settings = self.settings if k is None else replace(self.settings, k=k)
        ref, qry = kernel_rows(reference, settings), query_rows(query, settings)
        if isinstance(ref, np.ndarray):
            ref = torch.from_numpy(ref)  # a view of the map: the re-ranking reads only the candidates' rows
        q_seg, r_seg = query.segment_ids, reference.segment_ids
        if isinstance(self.scorer, AdaptiveScorer):
            top = adaptive_rerank(qry, ref, candidates, settings.sequence, self.scorer, q_seg, r_seg, settings.k)
        else:
            top = rerank(qry, ref, candidates, settings.sequence, q_seg, r_seg, k=settings.k)
        pairs = top1_pairs(qry, ref, top, settings, self.scorer, q_seg, r_seg)
        return MatchResult(reference.frames, query, top, settings, correspondences=pairs)

    def window_distances(self, rows, window, starts: np.ndarray) -> np.ndarray:
        """Mean order-aligned frame distances of the window [L, D] to the reference windows from ``starts``: the
        family's candidate form (``sequences.rerank.candidate_distances``), as re-ranking computes them."""
        from seqvpr.sequences.rerank import candidate_distances

        if not len(starts):  # no candidate window: nothing to read
            return np.zeros(0)
        window = torch.as_tensor(np.asarray(window, np.float32))
        return candidate_distances(window, rows, np.zeros(1, np.int64), np.asarray(starts)[None], len(window))[0]

    def stream(self, reference: Reference, exclusion: int = 10) -> Stepper:
        """Exact causal matching by running diagonal sums for the constant-velocity search at slope 1; any other
        search recomputes the last window at each frame."""
        from seqvpr.matchers.stream import DiagonalStepper

        if self.scorer is None and tuple(self.settings.sequence.velocities) == (1.0,):
            return DiagonalStepper(self, reference, exclusion)
        return super().stream(reference, exclusion)


def search_of(method: Any, conf: Mapping[str, Any]) -> SequenceSearch:
    """A method's window search with the steps and contrast window ``conf`` gives (defaults otherwise)."""
    defaults = SequenceSearch()
    return SequenceSearch(method.search, tuple(conf.get("steps") or defaults.steps),
                          int(conf.get("contrast_window") or defaults.contrast_window))


def top1_pairs(qry: torch.Tensor, ref, topk: TopK, settings: MatchSettings, scorer, q_seg: np.ndarray,
               r_seg: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The matcher's own per-frame pairs of the top-1 matches: the adaptive path, or the straight trajectory that
    won (any velocity search); None where the windows' slope-1 alignment is the answer (``match_correspondences``)
    or the matcher pairs no frames (the cone)."""
    from seqvpr.sequences.adaptive import AdaptiveScorer
    from seqvpr.sequences.correspondences import (
        adaptive_correspondences, trajectory_correspondences, trajectory_velocities,
    )

    best = topk.indices[:, 0]
    if isinstance(scorer, AdaptiveScorer):
        return adaptive_correspondences(qry, ref, best, settings.sequence, scorer, q_seg, r_seg)
    velocities = trajectory_velocities(scorer, settings.sequence)
    if velocities is None or tuple(velocities) == tuple(settings.sequence.velocities) == (1.0,):
        return None
    return trajectory_correspondences(qry, ref, best, settings.sequence, scorer, q_seg, r_seg, settings.memory_budget)
