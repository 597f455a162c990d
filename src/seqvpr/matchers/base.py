"""What every matcher shares: the settings that decide any match, the result, the reference's and the query's rows
as the kernel reads them, and the base class whose subclasses each write one family's search.

A matcher is built once with its settings and models (``seqvpr.methods`` makes one from a method's name) and then
answers ``topk(reference, query)`` for a whole query, or ``stream(reference)`` for one frame at a time. The
reference is anything that follows ``seqvpr.data.reference.Reference``: a traversal, a saved map, a sharded map.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.matchers.rows import frame_row
from seqvpr.progress import ProgressFactory
from seqvpr.results import MatchResult
from seqvpr.sequences.match_settings import MatchSettings

if TYPE_CHECKING:
    from seqvpr.matchers.stream import Stepper
    from seqvpr.sequences.frame_pass import FrameRow



class Matcher(ABC):
    """One family's search. A subclass writes ``topk``; ``stream`` defaults to recomputing the last window at each
    frame (``seqvpr.matchers.stream.WindowStepper``), which a family with an incremental step replaces."""

    family = ""  # the family a method record names (``seqvpr.methods``)
    method = ""  # the method's name it was built for (``seqvpr.methods.build_matcher`` sets it; messages name it)

    def __init__(self, settings: MatchSettings, progress: ProgressFactory | None = None) -> None:
        self.settings, self.progress = settings, progress

    def tick(self, total: int, what: str = "match"):
        """A progress callback over ``total`` query frames, when the matcher was given a progress factory."""
        return self.progress(total, what) if self.progress else None

    @classmethod
    def from_method(cls, method: Any, settings: MatchSettings, models: Mapping[str, Any], build: Callable[..., Matcher],
                    progress: ProgressFactory | None = None, **conf: Any) -> Matcher:
        """The matcher a method's record asks for (``seqvpr.methods.build_matcher`` calls it with the record, the
        models by kind, itself as ``build`` for a matcher made of others, and the family's own settings in
        ``conf``, of which each family reads what it knows). By default: the settings alone."""
        return cls(settings, progress=progress)

    @abstractmethod
    def topk(self, reference: Reference, query: Traversal) -> MatchResult:
        """The K best reference rows of every query frame."""

    def stream(self, reference: Reference, exclusion: int = 10) -> Stepper:
        """A stepper over ``reference`` taking one query frame at a time (causal windows)."""
        from seqvpr.matchers.stream import WindowStepper

        return WindowStepper(self, reference, exclusion)

    def own_settings(self) -> dict[str, Any]:
        """The family's own settings, for a run's record (none by default)."""
        return {}

    def prepare_frame(self, frame, out: FrameRow | None = None) -> FrameRow:
        """One query frame's descriptor [D] as ``topk`` prepares a query's rows (float32, through the matcher's
        transform, normalised if asked), in ``out`` (reused frame after frame) or a fresh row: what a stepper's
        ``push`` takes."""
        return frame_row(frame, getattr(self, "transform", None), self.settings.normalize, out)

    def with_settings(self, settings: MatchSettings) -> Matcher:
        """The same matcher under other common settings (K, sequences)."""
        other = copy.copy(self)
        other.settings = settings
        return other

    def window_distances(self, rows, window, starts: np.ndarray) -> np.ndarray:
        """The distances of one query window [L, D] (prepared rows) to the reference windows of ``rows`` starting
        at ``starts``: what a shortlist's stepper re-ranks by. A family that scores no single window has none."""
        from seqvpr.errors import SeqvprError

        raise SeqvprError(f"{type(self).__name__} scores no single window, so it takes no shortlist")

    def span(self) -> int:
        """Reference frames one window may cover (what a shard's overlap must hold)."""
        from seqvpr.sequences.matching import max_span

        return max_span(self.settings.sequence)


class WrappedMatcher(Matcher):
    """A matcher around another (its shards, a shortlist): the inner matcher's settings, family, method, frame
    preparation, own settings, span and window distance are its own; a subclass writes how it searches and how it
    is rebuilt under other settings."""

    def __init__(self, matcher: Matcher) -> None:
        self.matcher = matcher
        self.family, self.method, self.progress = matcher.family, matcher.method, matcher.progress

    @property
    def settings(self) -> MatchSettings:  # type: ignore[override]
        return self.matcher.settings

    def prepare_frame(self, frame, out: FrameRow | None = None) -> FrameRow:
        return self.matcher.prepare_frame(frame, out)

    def own_settings(self) -> dict[str, Any]:
        return self.matcher.own_settings()

    def span(self) -> int:
        return self.matcher.span()

    def window_distances(self, rows, window, starts: np.ndarray) -> np.ndarray:
        """The inner matcher's: a window's distance does not depend on the shard or the search that found it."""
        return self.matcher.window_distances(rows, window, starts)

