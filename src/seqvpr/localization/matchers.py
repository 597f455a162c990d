"""The per-frame step of each localisation method: a new query frame's descriptor in, the K best map frames, their
distances and a score out (None while warming up), with the time spent measuring distances and stepping.

- ``ExactMatcher``: one distance pass over the map, then ``DiagonalSums`` (exact causal sequence matching).
- ``ShortlistMatcher``: the map's faiss index gives candidates (the window's and the H frames before it, carried
  forward), re-ranked by exact sequence distance; cost independent of the map's size.
- ``FilterMatcher``: one distance pass, then the topological filter.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import torch

from seqvpr.errors import SeqvprError
from seqvpr.maps.files import SavedMap
from seqvpr.sequences.filter import FilterSettings, TopologicalFilter, map_distance_scale
from seqvpr.sequences.matching import distances_to_reference, reference_squared_norms
from seqvpr.sequences.online import DiagonalSums
from seqvpr.sequences.topk import best_k, best_of, uniqueness
from seqvpr.sequences.windows import window_starts


@dataclass(frozen=True)
class Scored:
    """One frame's answer: map rows and distances (ascending), the score (higher: surer), milliseconds spent."""

    indices: np.ndarray
    distances: np.ndarray
    score: float
    distance_ms: float
    sequence_ms: float


def elapsed_ms(since: float) -> float:
    return (time.perf_counter() - since) * 1e3


class FullMapPass:
    """One distance pass per frame over every map frame, with the map's squared norms computed once."""

    def __init__(self, rows, norms: np.ndarray | None = None) -> None:
        self.rows = rows
        self.norms = reference_squared_norms(rows) if norms is None else norms

    def measure(self, query: torch.Tensor) -> tuple[np.ndarray, float]:
        """The frame's distances to every map frame [N], and the milliseconds they took."""
        started = time.perf_counter()
        return distances_to_reference(query[None], self.rows, self.norms)[0], elapsed_ms(started)


class ExactMatcher(FullMapPass):
    """Exact causal sequence matching of the last L frames against every map frame, incrementally."""

    def __init__(self, rows, segments: np.ndarray, length: int, k: int, exclusion: int, norms: np.ndarray | None = None):
        super().__init__(rows, norms)
        self.k, self.exclusion = k, exclusion
        self.sums = DiagonalSums(segments, length)

    def reset(self) -> None:
        self.sums.reset()

    def push(self, query: torch.Tensor) -> Scored | None:
        distances, distance_ms = self.measure(query)
        measured = time.perf_counter()
        means = self.sums.push(distances)
        if means is None:
            return None
        indices, values = best_k(means, max(self.k, 2 * self.exclusion + 2))  # holds the best other place
        score = uniqueness(indices, values, self.exclusion)
        return Scored(indices[: self.k], values[: self.k], score, distance_ms, elapsed_ms(measured))

    def state(self) -> dict[str, np.ndarray]:
        return self.sums.state()

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.sums.load_state(state)


class ShortlistMatcher:
    """Candidates from the map's frame index (S per frame, over the window and ``history`` frames before it),
    re-ranked by exact causal sequence distance."""

    def __init__(self, saved: SavedMap, index, length: int, k: int, exclusion: int, shortlist: int, history: int):
        self.saved, self.index, self.length, self.k, self.exclusion = saved, index, length, k, exclusion
        self.shortlist, self.history = min(shortlist, max(index.ntotal, 1)), history  # more finds nothing more
        self.frames: deque[torch.Tensor] = deque(maxlen=length)
        self.found: deque[np.ndarray] = deque(maxlen=length + history)
        self.window_exists = window_starts(saved.frames.segment_ids, length, length - 1, "drop") >= 0

    def reset(self) -> None:
        self.frames.clear()
        self.found.clear()

    def push(self, query: torch.Tensor) -> Scored | None:
        from seqvpr.maps.index import search_frames

        started = time.perf_counter()
        vector = query.numpy()[None]
        self.found.appendleft(search_frames(self.index, vector, self.shortlist)[0][0])
        self.frames.append(query)
        measured = time.perf_counter()
        if len(self.frames) < self.length:
            return None
        indices, values = self._rerank(self._candidates())
        if not len(indices):  # no candidate window: nothing to name (scored as a miss)
            indices, values = np.full(1, -1, np.int64), np.full(1, np.inf)
        score = uniqueness(indices, values, self.exclusion)
        return Scored(indices[: self.k], values[: self.k], score, (measured - started) * 1e3, elapsed_ms(measured))

    def _candidates(self) -> np.ndarray:
        return found_candidates(self.found, self.saved.info.count)

    def _rerank(self, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Candidates with a window, ascending by exact causal sequence distance (ties: lower row)."""
        candidates = candidates[self.window_exists[candidates]]
        values = window_distances(self.saved.descriptors, self.frames, candidates - (self.length - 1))
        return best_of(candidates, values)

    def state(self) -> dict[str, np.ndarray]:
        width = self.shortlist
        found = np.array(list(self.found), np.int64).reshape(-1, width)
        frames = torch.stack(list(self.frames)).numpy() if self.frames else np.zeros((0, self.saved.info.dim), np.float32)
        return {"found": found, "frames": frames}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        if state["found"].shape[1:] != (self.shortlist,):
            raise SeqvprError(f"saved shortlist holds {state['found'].shape[1:]} neighbours, this one {self.shortlist}")
        self.reset()
        self.found.extend(state["found"])
        self.frames.extend(torch.from_numpy(row) for row in state["frames"])


def found_candidates(found, count: int) -> np.ndarray:
    """Map frames ending a candidate window: each neighbour of the frame ``lag`` frames ago (``found[lag]``),
    ``lag`` ahead, once each, on the map."""
    rows = [neighbours[neighbours >= 0] + lag for lag, neighbours in enumerate(found)]
    candidates = np.unique(np.concatenate(rows))
    return candidates[candidates < count]


def window_distances(descriptors, frames, starts: np.ndarray) -> np.ndarray:
    """Mean order-aligned distances between the query ``frames`` (the last L, oldest first) and the map windows
    from ``starts``: a gather of (L + H) S x L rows at most, too few for a parallel kernel (whose threads would only
    contend with faiss's)."""
    if not len(starts):  # no candidate window (here): nothing to read
        return np.zeros(0)
    window = torch.stack(list(frames)).numpy()
    length = len(window)
    rows = starts[:, None] + np.arange(length)[None, :]
    gathered = np.asarray(descriptors[rows.ravel()], np.float32).reshape(len(starts), length, -1)
    return np.linalg.norm(gathered - window[None], axis=2).mean(axis=1).astype(np.float64)


class FilterMatcher(FullMapPass):
    """The topological filter, one distance pass per frame; its likelihood scale calibrated on the map."""

    def __init__(self, rows, segments: np.ndarray, k: int, settings: FilterSettings, seed: int = 0):
        super().__init__(rows)
        self.k = k
        self.filter = TopologicalFilter(segments, map_distance_scale(rows, self.norms, settings, seed=seed), settings)

    def reset(self) -> None:
        self.filter.reset()

    def push(self, query: torch.Tensor) -> Scored | None:
        distances, distance_ms = self.measure(query)
        measured = time.perf_counter()
        self.filter.step(distances.astype(np.float64))
        mass = self.filter.mass()
        indices, values = best_k(1.0 - mass, self.k)
        return Scored(indices, values, float(mass[indices[0]]), distance_ms, elapsed_ms(measured))

    def state(self) -> dict[str, np.ndarray]:
        return self.filter.state()

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.filter.load_state(state)
