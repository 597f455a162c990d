"""Matching one query frame at a time: a ``Stepper`` takes each new frame's row (``Matcher.prepare_frame``: the
descriptor as ``topk`` prepares a query's rows, transformed and normalised, in a ``FrameRow``) and answers the K
best reference rows of the window that ends at it, with a score, or None while the first L frames come in.

- ``DiagonalStepper``: exact causal sequence matching by running diagonal sums (one distance pass a frame).
- ``FilterStepper``: the topological filter, one distance pass a frame.
- ``WindowStepper``: any matcher, by matching the last window's frames as a whole query (what its offline
  ``topk`` gives for a causal window, frame for frame).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import replace
from typing import Any, Protocol

import numpy as np
import torch

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.matchers.rows import matcher_rows, query_rows, transformed_reference
from seqvpr.sequences.frame_pass import FrameRow
from seqvpr.results import Scored
from seqvpr.sequences.topk import best_k, best_of, uniqueness_ratio




class Stepper(Protocol):
    """A matcher over one reference, a frame at a time; its state saves and restores (a restarted robot)."""

    def push(self, frame: FrameRow) -> Scored | None: ...

    def reset(self) -> None: ...

    def state(self) -> dict[str, np.ndarray]: ...

    def load_state(self, state: dict[str, np.ndarray]) -> None: ...


def elapsed_ms(since: float) -> float:
    return (time.perf_counter() - since) * 1e3


class FullPass:
    """One distance pass a frame over every reference row, the rows' squared norms computed once."""

    def __init__(self, rows) -> None:
        from seqvpr.sequences.frame_pass import ReferenceBlocks

        self.rows, self.blocks = rows, ReferenceBlocks(rows)
        self.norms = self.blocks.norms
        self.distances: np.ndarray | None = None  # made on the first measure, then reused

    def measure(self, frame: FrameRow) -> tuple[np.ndarray, float]:
        """The frame's distances to every reference row [N] (a buffer the next frame overwrites), and the
        milliseconds they took."""
        started = time.perf_counter()
        if self.distances is None:
            self.distances = np.empty(len(self.rows), dtype=np.float32)
        return self.blocks.distances_into(frame, self.distances), elapsed_ms(started)


class DiagonalStepper(FullPass):
    """Exact causal sequence matching of the last L frames against every reference row, incrementally: per frame
    one matrix product straight into the ring of distance rows, then one compiled pass that turns it into
    distances and ranks the windows."""

    def __init__(self, matcher: Any, reference: Reference, exclusion: int = 10) -> None:
        from seqvpr.sequences.online import DiagonalSums

        super().__init__(matcher_rows(matcher, reference))
        self.k, self.exclusion = matcher.settings.k, exclusion
        self.rank = max(self.k, 2 * exclusion + 2)  # enough for the score
        self.sums = DiagonalSums(reference.segment_ids, matcher.settings.sequence.length)
        self.targets = [torch.from_numpy(row)[None] for row in self.sums.ring]  # [1, N] views, made once

    def reset(self) -> None:
        self.sums.reset()

    def push(self, frame: FrameRow) -> Scored | None:
        started = time.perf_counter()
        self.blocks.dots_into(frame.row, self.targets[self.sums.next_slot()])  # the ring's next row
        measured = time.perf_counter()
        found = self.sums.push_dots_topk(frame.numbers, self.norms, self.rank)
        if found is None:
            return None
        indices, values = found
        score = uniqueness_ratio(indices, values, self.exclusion)
        return Scored(indices[: self.k], values[: self.k], score, (measured - started) * 1e3, elapsed_ms(measured))

    def state(self) -> dict[str, np.ndarray]:
        return self.sums.state()

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.sums.load_state(state)


class FilterStepper(FullPass):
    """The topological filter, one distance pass a frame; its likelihood scale calibrated on the reference."""

    def __init__(self, matcher: Any, reference: Reference) -> None:
        from seqvpr.sequences.filter import TopologicalFilter, map_distance_scale

        super().__init__(matcher_rows(matcher, reference))
        self.k, settings = matcher.settings.k, matcher.filter_settings
        scale = map_distance_scale(self.rows, self.norms, settings, seed=matcher.seed)
        self.filter = TopologicalFilter(reference.segment_ids, scale, settings)

    def reset(self) -> None:
        self.filter.reset()

    def push(self, frame: FrameRow) -> Scored | None:
        distances, distance_ms = self.measure(frame)
        measured = time.perf_counter()
        self.filter.step(distances.astype(np.float64))
        mass = self.filter.mass()
        indices, values = best_k(1.0 - mass, self.k)
        return Scored(indices, values, float(mass[indices[0]]), distance_ms, elapsed_ms(measured))

    def state(self) -> dict[str, np.ndarray]:
        return self.filter.state()

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.filter.load_state(state)


class WindowStepper:
    """Any matcher a frame at a time: the last L frames matched as a whole query with causal windows, the last
    frame's top-K kept (enough of it for the score). The reference is transformed and normalised once, as the
    frames come, and the inner matcher does neither again."""

    def __init__(self, matcher: Any, reference: Reference, exclusion: int = 10) -> None:
        settings = matcher.settings
        spec = replace(settings.sequence, align="causal", boundary="drop")
        self.matcher = matcher.with_settings(replace(settings, sequence=spec, k=max(settings.k, 2 * exclusion + 2),
                                                     normalize=False))
        if not reference.stored:
            reference = transformed_reference(matcher, reference)
            reference = reference.frames.with_descriptors(query_rows(reference, settings).cpu().numpy())
        if hasattr(self.matcher, "transform"):
            self.matcher.transform = None
        self.reference, self.k, self.exclusion = reference, settings.k, exclusion
        self.frames: deque[np.ndarray] = deque(maxlen=spec.length)

    def reset(self) -> None:
        self.frames.clear()

    def push(self, frame: FrameRow) -> Scored | None:
        started = time.perf_counter()
        self.frames.append(frame.numbers.copy())  # the frame's buffer is reused
        if len(self.frames) < self.frames.maxlen:
            return None
        window = Traversal.from_descriptors(np.stack(list(self.frames)), "window")
        top = self.matcher.topk(self.reference, window).topk
        indices, values = top.indices[-1], top.distances[-1]
        score = uniqueness_ratio(indices, values, self.exclusion)
        return Scored(indices[: self.k], values[: self.k], score, 0.0, elapsed_ms(started))

    def state(self) -> dict[str, np.ndarray]:
        return {"frames": np.stack(list(self.frames)) if self.frames else np.zeros((0, 0), np.float32)}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        frames = state["frames"]
        if len(frames) > self.frames.maxlen:
            raise SeqvprError(f"saved window holds {len(frames)} frames, this matcher keeps {self.frames.maxlen}")
        self.reset()
        self.frames.extend(frames)


class ShortlistStepper:
    """Candidates from a nearest-neighbour search (``seqvpr.matchers.shortlisted.Neighbours``: the S nearest
    reference rows of a frame), over the window and the ``history`` frames before it carried forward, re-ranked by
    the matcher's window distance; the cost is independent of the reference's size."""

    def __init__(self, matcher: Any, reference: Reference, neighbors: Any, shortlist: int, history: int = 0,
                 exclusion: int = 10) -> None:
        from seqvpr.matchers.rows import kernel_rows
        from seqvpr.sequences.windows import window_starts

        length = matcher.settings.sequence.length
        self.matcher, self.neighbors, self.length, self.k = matcher, neighbors, length, matcher.settings.k
        self.rows = kernel_rows(reference, matcher.settings)
        self.exclusion, self.count, self.dim = exclusion, len(reference), reference.dim
        self.shortlist = min(shortlist, max(neighbors.vectors, 1))  # more finds nothing more
        self.frames: deque[torch.Tensor] = deque(maxlen=length)
        self.found: deque[np.ndarray] = deque(maxlen=length + history)
        self.window_exists = window_starts(reference.segment_ids, length, length - 1, "drop") >= 0

    def reset(self) -> None:
        self.frames.clear()
        self.found.clear()

    def push(self, frame: FrameRow) -> Scored | None:
        started = time.perf_counter()
        self.found.appendleft(self.neighbors.search(frame.row, np.zeros(1, np.int64), self.shortlist).indices[0])
        self.frames.append(frame.vector.clone())  # the frame's buffer is reused
        measured = time.perf_counter()
        if len(self.frames) < self.length:
            return None
        candidates = found_candidates(self.found, self.count)
        candidates = candidates[self.window_exists[candidates]]
        window = torch.stack(list(self.frames)).numpy()
        values = self.matcher.window_distances(self.rows, window, candidates - (self.length - 1))
        indices, values = best_of(candidates, values)
        if not len(indices):  # no candidate window: nothing to name (scored as a miss)
            indices, values = np.full(1, -1, np.int64), np.full(1, np.inf)
        score = uniqueness_ratio(indices, values, self.exclusion)
        return Scored(indices[: self.k], values[: self.k], score, (measured - started) * 1e3, elapsed_ms(measured))

    def state(self) -> dict[str, np.ndarray]:
        found = np.array(list(self.found), np.int64).reshape(-1, self.shortlist)
        frames = torch.stack(list(self.frames)).numpy() if self.frames else np.zeros((0, self.dim), np.float32)
        return {"found": found, "frames": frames}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        if state["found"].shape[1:] != (self.shortlist,):
            raise SeqvprError(f"saved shortlist holds {state['found'].shape[1:]} neighbours, this one {self.shortlist}")
        self.reset()
        self.found.extend(state["found"])
        self.frames.extend(torch.from_numpy(row) for row in state["frames"])


def found_candidates(found, count: int) -> np.ndarray:
    """Reference rows ending a candidate window: each neighbour of the frame ``lag`` frames ago (``found[lag]``),
    ``lag`` ahead, once each, inside the reference."""
    rows = [neighbors[neighbors >= 0] + lag for lag, neighbors in enumerate(found)]
    candidates = np.unique(np.concatenate(rows))
    return candidates[candidates < count]
