"""The localiser's per-frame step over a sharded map under ``torchrun``: each rank matches its shards and rank 0
merges, so the stream is the one-process localiser's over the unsharded map, frame by frame.

- ``ShardedExactMatcher``: exact causal sequence matching (``DiagonalStepper``), each shard over the rows it owns.
- ``ShardedShortlistMatcher``: the shortlist (``ShortlistStepper``): each rank searches its shards' indexes, every
  rank merges the nearest rows, re-ranks the candidates its shards own, and rank 0 merges the re-ranked ones.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np
import torch

from seqvpr.errors import SeqvprError
from seqvpr.matchers.stream import FullPass, Scored, elapsed_ms, found_candidates, window_distances
from seqvpr.sequences.online import DiagonalSums
from seqvpr.sequences.topk import TopK, best_k, best_of, merge_topks, uniqueness
from seqvpr.sequences.windows import window_starts


class _Stateless:
    """A sharded localiser keeps no state to save (its state is spread over the ranks)."""

    def state(self) -> dict[str, np.ndarray]:
        raise SeqvprError("a localiser over a sharded map under torchrun keeps no state to save")

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        raise SeqvprError("a localiser over a sharded map under torchrun takes no saved state")


class ShardedExactMatcher(_Stateless):
    """Exact causal sequence matching over a sharded map, one rank per shard (or several): each rank keeps, over the
    frames its shards own, the best ``max(k, 2 * exclusion + 2)`` windows, and rank 0 merges them. That is the
    unsharded matcher's answer: the best window outside the exclusion zone of the best, which the score needs, is
    among each shard's first 2 * exclusion + 2. Other ranks get None for every frame (rank 0 reports)."""

    def __init__(self, sharded, world, length: int, k: int, exclusion: int) -> None:
        from seqvpr.maps.shards import shard_numbers

        self.world, self.k, self.exclusion = world, k, exclusion
        self.keep = max(k, 2 * exclusion + 2)
        self.parts = []
        for number in shard_numbers(len(sharded.shards), world.rank, world.size):
            shard, record = sharded.open_shard(number), sharded.shards[number]
            owned = np.zeros(shard.info.count, dtype=bool)
            owned[record.own_first - record.first : record.own_last - record.first] = True
            self.parts.append((FullPass(shard.descriptors), DiagonalSums(shard.frames.segment_ids, length), owned,
                               record.first))

    def reset(self) -> None:
        for _, sums, _, _ in self.parts:
            sums.reset()

    def push(self, query: torch.Tensor) -> Scored | None:
        from seqvpr import distributed

        found, warming, distance_ms = [], False, 0.0
        for full, sums, owned, first in self.parts:
            distances, spent = full.measure(query)
            distance_ms += spent
            means = sums.push(distances)
            if means is None:
                warming = True
                continue
            rows, values = best_k(np.where(owned, means, np.inf), self.keep)
            found.append((np.where(rows >= 0, rows + first, -1), values))
        if warming:  # every rank has seen the same frames: all warm up together, no message needed
            return None
        started = time.perf_counter()
        gathered = distributed.gather_to_root(lambda: found, self.world)
        if gathered is None:
            return None
        found = [part for rank_parts in gathered for part in rank_parts]
        merged = merge_topks([TopK(r[None], v[None], np.ones(1, bool)) for r, v in found], len(found) * self.keep)
        rows, values = merged.indices[0], merged.distances[0]
        score = uniqueness(rows, values, self.exclusion)
        return Scored(rows[: self.k], values[: self.k], score, distance_ms, elapsed_ms(started))  # sequence: sums, gather and merge


class ShardedShortlistMatcher(_Stateless):
    """``ShortlistStepper`` over a sharded map: each rank searches its shards' indexes for the frame's ``shortlist``
    nearest owned rows, every rank merges them (the whole map's nearest, with flat indexes), re-ranks the candidate
    windows its shards own, and rank 0 merges those. Other ranks get None for every frame."""

    def __init__(self, sharded, world, length: int, k: int, exclusion: int, shortlist: int, history: int,
                 nprobe: int) -> None:
        from seqvpr.maps.index import open_frame_index
        from seqvpr.maps.shards import shard_index_over, shard_numbers

        self.world, self.length, self.k, self.exclusion = world, length, k, exclusion
        self.shortlist, self.count = min(shortlist, max(sharded.count, 1)), sharded.count  # more finds nothing more
        self.frames: deque[torch.Tensor] = deque(maxlen=length)
        self.found: deque[np.ndarray] = deque(maxlen=length + history)
        for number in range(len(sharded.shards)):  # all, on every rank: each fails alike, none waits for another
            if shard_index_over(sharded, shard := sharded.open_shard(number)) != "frames":
                raise SeqvprError(f"--shortlist needs an index over {shard.folder}'s frames: seqvpr map index "
                                  f"{sharded.folder} --index SPEC")
        self.parts = []
        for number in shard_numbers(len(sharded.shards), world.rank, world.size):
            shard, record = sharded.open_shard(number), sharded.shards[number]
            ends = window_starts(shard.frames.segment_ids, length, length - 1, "drop") >= 0
            self.parts.append((shard, open_frame_index(shard, nprobe), record, ends))

    def reset(self) -> None:
        self.frames.clear()
        self.found.clear()

    def push(self, query: torch.Tensor) -> Scored | None:
        from seqvpr import distributed

        started = time.perf_counter()
        nearest = distributed.gather_everywhere(lambda: self._nearest(query.numpy()[None]), self.world)
        parts = [TopK(rows[None], values[None], np.ones(1, bool)) for rank_parts in nearest for rows, values in rank_parts]
        self.found.appendleft(merge_topks(parts, self.shortlist).indices[0])  # the whole map's nearest
        self.frames.append(query)
        measured = time.perf_counter()
        if len(self.frames) < self.length:  # every rank has seen the same frames: all warm up together
            return None
        candidates = found_candidates(self.found, self.count)
        gathered = distributed.gather_to_root(lambda: self._rerank_owned(candidates), self.world)
        if gathered is None:
            return None
        rows = np.concatenate([r for r, _ in gathered])
        values = np.concatenate([v for _, v in gathered])
        indices, values = best_of(rows, values)
        if not len(indices):  # no candidate window: nothing to name (scored as a miss)
            indices, values = np.full(1, -1, np.int64), np.full(1, np.inf)
        score = uniqueness(indices, values, self.exclusion)
        return Scored(indices[: self.k], values[: self.k], score, (measured - started) * 1e3, elapsed_ms(measured))

    def _nearest(self, vector: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """This rank's shards' nearest owned rows of the frame (whole-map rows, distances), ``shortlist`` each."""
        from seqvpr.maps.index import search_frames

        found = []
        for _, index, record, _ in self.parts:
            rows, distances = search_frames(index, vector, self.shortlist)
            rows = np.where(rows[0] >= 0, rows[0] + record.first, -1)
            owned = (rows >= record.own_first) & (rows < record.own_last)
            found.append((rows[owned], distances[0][owned]))
        return found

    def _rerank_owned(self, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The candidates this rank's shards own that end a window, with their exact sequence distances."""
        rows, values = [np.zeros(0, np.int64)], [np.zeros(0)]
        for shard, _, record, ends in self.parts:
            mine = candidates[(candidates >= record.own_first) & (candidates < record.own_last)]
            mine = mine[ends[mine - record.first]]
            rows.append(mine)
            values.append(window_distances(shard.descriptors, self.frames, mine - record.first - (self.length - 1)))
        return np.concatenate(rows), np.concatenate(values)
