"""Sharding any matcher whose scores are per window: each shard (a reference of its own, overlapping its
neighbours) is matched over the rows it owns and the parts merge into the whole reference's answer, offline
(``topk``) or a frame at a time (``stream``). Under ``torchrun`` each rank takes its shards and rank 0 merges (the
others get None); alone, one process takes them all.

A shard's top-K over the rows it owns, merged with the others' by the one tie rule (``merge_topks``), is the whole
reference's top-K: a row among the whole's best is among its shard's, which has fewer rivals. That holds when every
window anchored at an owned row lies inside the shard: the matcher's span at most the overlap plus one.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from seqvpr.data.reference import Reference
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.matchers.base import Matcher, WrappedMatcher
from seqvpr.matchers.stream import elapsed_ms
from seqvpr.results import MatchResult, Scored, TopK
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.topk import merge_topks, uniqueness_ratio


class ShardRange(Protocol):
    """Where a shard lies in the whole reference: its first row and the rows it owns, ``[own_first, own_last)``."""

    first: int
    own_first: int
    own_last: int


class ShardedReference(Protocol):
    """A reference split into overlapping shards: their ranges, each one opened as a reference, the whole's frame
    table (what a result reports)."""

    folder: Any
    count: int
    overlap: int
    shards: Sequence[ShardRange]

    def open_shard(self, number: int) -> Reference: ...

    def as_map(self) -> Reference:
        """The whole reference, its rows read through the shards (what a step over all of it reads)."""
        ...

    def __len__(self) -> int: ...

    @property
    def frames(self) -> Traversal: ...


@dataclass(frozen=True)
class ShardMatch:
    """One shard's part of a match: its top-K in whole-reference rows, and its top-1 pairs (query rows,
    whole-reference rows) when the matcher makes its own (adaptive paths, winning trajectories)."""

    number: int
    topk: TopK
    pairs: tuple[np.ndarray, np.ndarray] | None


def shard_numbers(shards: int, rank: int, world: int) -> list[int]:
    """The shards rank ``rank`` of ``world`` matches: every world-th one from its rank (all of them alone)."""
    return list(range(rank, shards, world))


SHARDABLE_FAMILIES = ("matching", "retrieval")  # per-window scores: a shard's top-K over its own rows is exact
WHOLE_REFERENCE_SEARCHES = ("seqslam-cone", "seqslam-hybrid")  # they use each frame's best match over the whole


def check_shardable(matcher: Any) -> None:
    """A matcher whose per-window scores a shard can compute from the rows it holds (its windows' span is checked
    against a sharded reference's overlap when it is matched, ``check_overlap``)."""
    search = getattr(getattr(matcher, "search", None), "search", None)
    if search in WHOLE_REFERENCE_SEARCHES:
        raise SettingError(f"{{method}} {matcher.method} votes with each query frame's best match over the whole map, "
                          "which no shard sees; match the unsharded map")
    if matcher.family not in SHARDABLE_FAMILIES:
        raise SettingError(f"{{method}} {matcher.method} scores whole paths or shortlists over the whole map; a sharded "
                          f"map is matched by sequence matching or sequence descriptors "
                          f"({', '.join(SHARDABLE_FAMILIES)} methods)")


def is_sharded(reference: Any) -> bool:
    """Whether a reference is split into shards (a ``ShardedReference``), each matched on its own."""
    return hasattr(reference, "shards") and hasattr(reference, "open_shard")


def check_overlap(matcher: Any, sharded: ShardedReference) -> None:
    """The matcher's windows (its span: adaptive paths, SeqSLAM's contrast neighbourhood) must fit the overlap."""
    span = matcher.span()
    if span - 1 > sharded.overlap:
        raise SettingError(f"{sharded.folder}: its shards overlap by {sharded.overlap} frames, so windows may span "
                          f"at most {sharded.overlap + 1}; this match needs {span} (shard it again with "
                          f"{{overlap}} {span - 1})")


def owned_rows(rows: np.ndarray, record: ShardRange) -> tuple[np.ndarray, np.ndarray]:
    """A shard's rows as whole-reference rows (-1 kept) and which of them the shard owns."""
    whole = np.where(rows >= 0, rows + record.first, -1)
    return whole, (whole >= record.own_first) & (whole < record.own_last)


def owned_topk(topk: TopK, record: ShardRange, k: int) -> TopK:
    """A shard's top-K (shard rows) as whole-reference rows, keeping only the rows the shard owns, best ``k``."""
    rows, owned = owned_rows(topk.indices, record)
    order = np.argsort(~owned, axis=1, kind="stable")[:, :k]  # owned first, in their rank order
    kept_rows = np.take_along_axis(np.where(owned, rows, -1), order, 1)
    kept = np.take_along_axis(np.where(owned, topk.distances, np.inf), order, 1)
    return TopK(_pad(kept_rows, k, -1), _pad(kept, k, np.inf), topk.has_window)


def _pad(values: np.ndarray, k: int, fill) -> np.ndarray:
    if values.shape[1] >= k:
        return values
    return np.concatenate([values, np.full((len(values), k - values.shape[1]), fill, dtype=values.dtype)], 1)


def no_match(query: Traversal, settings: MatchSettings) -> TopK:
    """No reference row for any query (a shard too short for a window)."""
    from seqvpr.sequences.windows import window_starts

    spec = settings.sequence
    has_window = window_starts(query.segment_ids, spec.length, spec.offset, spec.boundary) >= 0
    return TopK(np.full((len(query), settings.k), -1), np.full((len(query), settings.k), np.inf), has_window)


class Sharded(WrappedMatcher):
    """``matcher`` over a ``ShardedReference``, each shard by the rank that holds it (``world``: the distributed
    run, or the current one). Only a matcher whose scores are per window is sharded (``check_shardable``)."""

    def __init__(self, matcher: Matcher, world: Any = None) -> None:
        from seqvpr import distributed

        check_shardable(matcher)
        super().__init__(matcher)
        self.world = world or distributed.current()

    def with_settings(self, settings: MatchSettings) -> Sharded:
        return Sharded(self.matcher.with_settings(settings), self.world)

    def topk(self, sharded: ShardedReference, query: Traversal) -> MatchResult | None:
        """The whole reference's match on rank 0 (None on the others)."""
        from seqvpr import distributed

        check_overlap(self.matcher, sharded)
        numbers = shard_numbers(len(sharded.shards), self.world.rank, self.world.size)
        parts = distributed.gather_to_root(lambda: [self.match_shard(sharded, n, query) for n in numbers], self.world)
        if parts is None:
            return None
        return merge_shard_matches(sharded, [p for rank_parts in parts for p in rank_parts], query, self.settings)

    def match_shard(self, sharded: ShardedReference, number: int, query: Traversal) -> ShardMatch:
        """One shard's top-K over the rows it owns, with its top-1 pairs where the matcher makes its own; a shard
        whose segments are all shorter than a window gives nothing."""
        from seqvpr.sequences.matching import max_span
        from seqvpr.sequences.windows import window_starts

        record, shard, spec = sharded.shards[number], sharded.open_shard(number), self.settings.sequence
        if not (window_starts(shard.segment_ids, max_span(spec), 0, spec.boundary) >= 0).any():
            return ShardMatch(number, no_match(query, self.settings), None)
        result = self.matcher.topk(shard, query)
        pairs = None
        if result.correspondences is not None:
            pairs = (result.correspondences[0], owned_rows(result.correspondences[1], record)[0])
        return ShardMatch(number, owned_topk(result.topk, record, self.settings.k), pairs)

    def rerank(self, sharded: ShardedReference, query: Traversal, candidates: TopK, k: int | None = None
               ) -> MatchResult | None:
        """Candidates in whole-reference rows re-ranked by the matcher, each shard the ones it owns, merged on
        rank 0 (None on the others)."""
        from seqvpr import distributed

        k = self.settings.k if k is None else k
        numbers = shard_numbers(len(sharded.shards), self.world.rank, self.world.size)
        tops = distributed.gather_to_root(lambda: [self.rerank_shard(sharded, n, query, candidates, k)
                                                   for n in numbers], self.world)
        if tops is None:
            return None
        width = min(k, candidates.indices.shape[1])  # as re-ranking keeps: no more than the candidates
        top = merge_topks([part for rank_parts in tops for part in rank_parts], width)
        return MatchResult(sharded.frames, query, top, self.settings)

    def rerank_shard(self, sharded: ShardedReference, number: int, query: Traversal, candidates: TopK,
                     k: int) -> TopK:
        """The candidates shard ``number`` owns re-ranked over its rows: their top-K in whole-reference rows."""
        record, rows = sharded.shards[number], candidates.indices
        owned = (rows >= record.own_first) & (rows < record.own_last)
        local = TopK(np.where(owned, rows - record.first, -1), candidates.distances, candidates.has_window)
        return owned_topk(self.matcher.rerank(sharded.open_shard(number), query, local, k).topk, record, k)

    def stream(self, sharded: ShardedReference, exclusion: int = 10) -> ShardedStepper:
        """The matcher's stepper over each of this rank's shards, merged on rank 0 a frame at a time."""
        check_overlap(self.matcher, sharded)
        return ShardedStepper(self.matcher, sharded, self.world, exclusion)


def merge_shard_matches(sharded: ShardedReference, parts: Sequence[ShardMatch], query: Traversal,
                        settings: MatchSettings) -> MatchResult:
    """The whole reference's match from every shard's: top-K merged, each query's pairs from the shard owning its
    top-1."""
    parts = sorted(parts, key=lambda part: part.number)
    top = merge_topks([p.topk for p in parts], settings.k)
    pairs = None
    made = [p.pairs for p in parts if p.pairs is not None]  # a shard too short for any window made none
    if made:
        none = np.full_like(made[0][0], -1)
        q_stack = np.stack([none if p.pairs is None else p.pairs[0] for p in parts])
        r_stack = np.stack([none if p.pairs is None else p.pairs[1] for p in parts])
        owner = np.searchsorted([r.own_last for r in sharded.shards], np.maximum(top.indices[:, 0], 0), side="right")
        q_rows, r_rows = q_stack[owner, np.arange(len(owner))], r_stack[owner, np.arange(len(owner))]
        matched = (top.indices[:, 0] >= 0)[:, None]
        pairs = (np.where(matched, q_rows, -1), np.where(matched, r_rows, -1))
    return MatchResult(sharded.frames, query, top, settings, correspondences=pairs)


class ShardedStepper:
    """Each of this rank's shards stepped by the matcher's own stepper, asked for enough rows that its best
    ``max(k, 2 * exclusion + 2)`` owned ones are among them; rank 0 merges them and scores the merged list, which
    is the whole reference's stepper's answer (the best window outside the best's exclusion zone is among each
    shard's first 2 * exclusion + 2). Other ranks get None for every frame. Its state is spread over the ranks:
    it saves none."""

    def __init__(self, matcher: Any, sharded: ShardedReference, world: Any, exclusion: int = 10) -> None:
        self.world, self.k, self.exclusion = world, matcher.settings.k, exclusion
        self.keep = max(self.k, 2 * exclusion + 2)
        self.parts = []
        for number in shard_numbers(len(sharded.shards), world.rank, world.size):
            record, shard = sharded.shards[number], sharded.open_shard(number)
            borrowed = len(shard) - (record.own_last - record.own_first)  # rows it holds but does not own
            inner = matcher.with_settings(replace(matcher.settings, k=self.keep + borrowed))
            self.parts.append((inner.stream(shard, exclusion), record))

    def reset(self) -> None:
        for stepper, _ in self.parts:
            stepper.reset()

    def push(self, frame) -> Scored | None:
        from seqvpr import distributed

        found, warming, distance_ms, sequence_ms = [], False, 0.0, 0.0
        for stepper, record in self.parts:
            scored = stepper.push(frame)
            if scored is None:
                warming = True
                continue
            rows, owned = owned_rows(scored.indices, record)
            found.append((rows[owned][: self.keep], scored.distances[owned][: self.keep]))
            distance_ms, sequence_ms = distance_ms + scored.distance_ms, sequence_ms + scored.sequence_ms
        if warming:  # every rank has seen the same frames: all warm up together, no message needed
            return None
        started = time.perf_counter()
        gathered = distributed.gather_to_root(lambda: found, self.world)
        if gathered is None:
            return None
        found = [part for rank_parts in gathered for part in rank_parts]
        merged = merge_topks([TopK(r[None], v[None], np.ones(1, bool)) for r, v in found], len(found) * self.keep)
        rows, values = merged.indices[0], merged.distances[0]
        score = uniqueness_ratio(rows, values, self.exclusion)
        return Scored(rows[: self.k], values[: self.k], score, distance_ms, sequence_ms + elapsed_ms(started))

    def state(self) -> dict[str, np.ndarray]:
        raise SeqvprError("a localiser over a sharded map under torchrun keeps no state to save")

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        raise SeqvprError("a localiser over a sharded map under torchrun takes no saved state")
