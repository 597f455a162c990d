"""What a match answers, kept low so that every layer reads it (evaluation never imports the matchers): the top-K
of every query (``TopK``), a whole match (``MatchResult``) and one streamed frame's answer (``Scored``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from seqvpr.data.traversal import Traversal
    from seqvpr.sequences.match_settings import MatchSettings


@dataclass(frozen=True)
class TopK:
    """The K best references per query: indices (-1 where fewer exist) and sequence distances (+inf there)."""

    indices: np.ndarray
    distances: np.ndarray
    has_window: np.ndarray


@dataclass(frozen=True)
class MatchResult:
    """Top-K reference rows per query row, with the traversals they index."""

    reference: Traversal
    query: Traversal
    topk: TopK
    settings: MatchSettings
    shortlist: TopK | None = None  # the candidates a shortlisted match re-ranked (None: exhaustive)
    #: per-frame correspondences of the top-1 matches, (query rows, reference rows) [n_query, L], when the matcher
    #: is not the constant-velocity window alignment (adaptive); None: the windows' own alignment
    correspondences: tuple[np.ndarray, np.ndarray] | None = None


@dataclass(frozen=True)
class Scored:
    """One frame's answer: reference rows and distances (ascending), the score (higher: surer), milliseconds spent
    measuring distances and stepping."""

    indices: np.ndarray
    distances: np.ndarray
    score: float
    distance_ms: float
    sequence_ms: float
