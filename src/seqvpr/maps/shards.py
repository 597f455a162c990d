"""Sharded maps: one map split into N shards, each a map of its own that one process memory-maps and matches.

    SHARDED/shards.json    format, version, the whole map's frame count, overlap, per shard its folder, its first
                           row and the rows it owns ``[own_first, own_last)``, and the unsharded map's map.json
    SHARDED/shard-000/     a map (``files``) of rows ``[own_first - overlap, own_last + overlap)``, clipped to the
                           whole; its ``map.json`` says which shard it is

Shards own contiguous, equal runs of frames and overlap their neighbours by ``overlap`` frames on each side, so
every sequence window anchored at a frame a shard owns lies inside that shard while its span is at most
``overlap + 1`` frames: no window is cut at a shard edge. A shard's top-K over the frames it owns, merged with the
others' (distance, then the lower map row, as the kernel breaks ties), is the unsharded map's top-K. Under
``torchrun`` each rank matches its shards (``seqvpr.distributed``); without it one process matches them all.
``open_map`` opens a sharded map as the whole map too (``ShardedMap.as_map``), rows read through the shards, so
the localiser and every other map command take one in a single process.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.io import atomic_folder
from seqvpr.maps.files import (
    SHARDS_FILE, SHARDS_FORMAT, SHARDS_VERSION, ShardedMap, ShardRecord, map_table, open_map, open_sharded_map,
    write_map_rows,
)
from seqvpr.sequences.matching import TopK

if TYPE_CHECKING:
    from seqvpr.pipeline import MatchResult

DEFAULT_OVERLAP = 63  # windows of up to 64 frames (any velocity) are never cut
SHARDABLE_FAMILIES = ("matching", "retrieval")  # per-window scores: a shard's top-K over its own frames is exact
WHOLE_MAP_SCORERS = ("seqslam-cone", "seqslam-hybrid")  # they use each frame's best match over the whole map


@dataclass(frozen=True)
class ShardMatch:
    """One shard's part of a match: its top-K in whole-map rows, and its top-1 pairs (query rows, whole-map rows)
    when the method makes its own (adaptive paths, winning trajectories)."""

    number: int
    topk: TopK
    pairs: tuple[np.ndarray, np.ndarray] | None


def shard_ranges(count: int, shards: int, overlap: int) -> list[tuple[int, int, int, int]]:
    """``(first, own_first, own_last, last)`` of each of ``shards`` equal runs of ``count`` frames, ``overlap``
    frames past each end (clipped to the map)."""
    if not 1 <= shards <= count:
        raise SeqvprError(f"--shards must be between 1 and the map's {count} frames, got {shards}")
    bounds = [count * i // shards for i in range(shards + 1)]
    return [(max(0, a - overlap), a, b, min(count, b + overlap)) for a, b in zip(bounds, bounds[1:])]


def shard_map(source: str | Path, out: str | Path, shards: int, overlap: int = DEFAULT_OVERLAP) -> ShardedMap:
    """Split the map at ``source`` into ``shards`` shard maps under ``out`` (written atomically: ``shards.json``
    last, inside a temporary folder renamed when complete)."""
    if overlap < 0:
        raise SeqvprError(f"--overlap must be 0 or more frames, got {overlap}")
    saved = open_map(source)
    records = []
    with atomic_folder(out, SHARDS_FILE) as tmp:
        for number, (lo, a, b, hi) in enumerate(shard_ranges(saved.info.count, shards, overlap)):
            folder = f"shard-{number:03d}"
            write_map_rows(saved, lo, hi, tmp / folder, {"number": number, "of": shards, "first": lo,
                                                         "own": [a, b], "count": saved.info.count})
            records.append(ShardRecord(folder, lo, a, b))
        description = {"format": SHARDS_FORMAT, "version": SHARDS_VERSION, "count": saved.info.count,
                       "overlap": overlap, "source": str(source), "shards": [r.__dict__ for r in records],
                       "map": saved.info.to_json()}
        (tmp / SHARDS_FILE).write_text(json.dumps(description, indent=2))
    return open_sharded_map(out)


def check_shardable(method: str, span: int, sharded: ShardedMap) -> None:
    """A method whose per-window scores a shard can compute, on windows no longer than the shards overlap."""
    from seqvpr.methods import get_method

    record = get_method(method)
    if record.scorer in WHOLE_MAP_SCORERS:
        raise SeqvprError(f"--method {method} votes with each query frame's best match over the whole map, which no "
                          "shard sees; match the unsharded map")
    family = record.family
    if family not in SHARDABLE_FAMILIES:
        raise SeqvprError(f"--method {method} scores whole paths or shortlists over the whole map; a sharded map "
                          f"is matched by sequence matching or sequence descriptors "
                          f"({', '.join(SHARDABLE_FAMILIES)} methods)")
    if span - 1 > sharded.overlap:
        raise SeqvprError(f"{sharded.folder}: its shards overlap by {sharded.overlap} frames, so windows may span "
                          f"at most {sharded.overlap + 1}; this match needs {span} (shard it again with "
                          f"--overlap {span - 1})")


def owned_topk(result_topk: TopK, record: ShardRecord, k: int) -> TopK:
    """A shard's top-K (shard rows) as whole-map rows, keeping only the frames the shard owns, best ``k``."""
    rows = np.where(result_topk.indices >= 0, result_topk.indices + record.first, -1)
    owned = (rows >= record.own_first) & (rows < record.own_last)
    order = np.argsort(~owned, axis=1, kind="stable")[:, :k]  # owned first, in their rank order
    kept_rows = np.take_along_axis(np.where(owned, rows, -1), order, 1)
    kept = np.take_along_axis(np.where(owned, result_topk.distances, np.inf), order, 1)
    return TopK(_pad(kept_rows, k, -1), _pad(kept, k, np.inf), result_topk.has_window)


def _pad(values: np.ndarray, k: int, fill) -> np.ndarray:
    if values.shape[1] >= k:
        return values
    return np.concatenate([values, np.full((len(values), k - values.shape[1]), fill, dtype=values.dtype)], 1)


def merge_topks(parts: Sequence[TopK], k: int) -> TopK:
    """The best ``k`` of several top-K lists over disjoint rows: by distance, ties to the lower row (the kernel's
    order), so the merge of a sharded match is the unsharded one."""
    rows = np.concatenate([p.indices for p in parts], 1)
    distances = np.concatenate([p.distances for p in parts], 1)
    order = np.lexsort((np.where(rows >= 0, rows, np.iinfo(np.int64).max), distances), axis=1)[:, :k]
    picked, values = np.take_along_axis(rows, order, 1), np.take_along_axis(distances, order, 1)
    picked[~np.isfinite(values)] = -1
    return TopK(picked, values, parts[0].has_window)


def shard_numbers(shards: int, rank: int, world: int) -> list[int]:
    """The shards rank ``rank`` of ``world`` matches: every world-th one from its rank (all of them alone)."""
    return list(range(rank, shards, world))


def match_sharded_map(sharded: ShardedMap, query: Traversal, method: str, settings,
                      models: Mapping[str, Any] | None = None, progress=None, **extraction: Any) -> MatchResult | None:
    """Match ``query`` against every shard: under ``torchrun`` each rank its own shards, merged on rank 0 (other
    ranks get None); alone, all shards in turn. The result equals matching the unsharded map."""
    from seqvpr import distributed

    world = distributed.current()
    numbers = shard_numbers(len(sharded.shards), world.rank, world.size)
    parts = distributed.gather_to_root(
        lambda: match_shards(sharded, numbers, query, method, settings, models, progress, **extraction), world)
    if parts is None:
        return None
    return merge_shard_matches(sharded, [p for rank_parts in parts for p in rank_parts], query, settings)


def match_shards(sharded: ShardedMap, numbers: Sequence[int], query: Traversal, method: str, settings,
                 models: Mapping[str, Any] | None = None, progress=None, **extraction: Any) -> list[ShardMatch]:
    """The top-K, in whole-map rows over owned frames, of each shard in ``numbers`` against ``query``, with the
    per-frame pairs of its top-1 matches where the method makes its own; a shard whose segments are all shorter
    than a window contributes nothing."""
    from seqvpr.maps.match import match_map
    from seqvpr.sequences.matching import max_span
    from seqvpr.sequences.windows import window_starts

    spec = settings.sequence
    check_shardable(method, max_span(spec), sharded)
    parts = []
    for number in numbers:
        record, shard = sharded.shards[number], sharded.open_shard(number)
        if not (window_starts(shard.frames.segment_ids, max_span(spec), 0, spec.boundary) >= 0).any():
            has_window = window_starts(query.segment_ids, spec.length, spec.offset, spec.boundary) >= 0
            parts.append(ShardMatch(number, TopK(np.full((len(query), settings.k), -1),
                                         np.full((len(query), settings.k), np.inf), has_window), None))
            continue
        extra = shard.info.count - (record.own_last - record.own_first)  # overlap rows that may fill the top-K
        result = match_map(shard, query, method, replace(settings, k=settings.k + extra), models,
                           progress=progress, **extraction)
        pairs = None if result.correspondences is None else (
            result.correspondences[0], np.where(result.correspondences[1] >= 0, result.correspondences[1] + record.first, -1))
        parts.append(ShardMatch(number, owned_topk(result.topk, record, settings.k), pairs))
    return parts


def merge_shard_matches(sharded: ShardedMap, parts: Sequence[ShardMatch], query: Traversal, settings) -> MatchResult:
    """The whole map's match from every shard's: top-K merged, each query's pairs from the shard owning its top-1."""
    from seqvpr.pipeline import MatchResult

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
    return MatchResult(map_table(sharded), query, top, settings, correspondences=pairs)
