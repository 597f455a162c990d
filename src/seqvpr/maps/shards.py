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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.io import atomic_folder, temporary_folder
from seqvpr.maps.files import (
    SHARDS_FILE, SHARDS_FORMAT, SHARDS_VERSION, ShardedMap, ShardRecord, map_table, open_map, open_sharded_map,
    write_map_rows,
)
from seqvpr.sequences.topk import TopK, merge_topks

if TYPE_CHECKING:
    from seqvpr.maps.files import SavedMap
    from seqvpr.maps.match import PreparedQuery
    from seqvpr.pipeline import MatchResult

DEFAULT_OVERLAP = 63  # windows of up to 64 frames (any velocity) are never cut
SHARDABLE_FAMILIES = ("matching", "retrieval")  # per-window scores: a shard's top-K over its own frames is exact
WHOLE_MAP_SEARCHES = ("seqslam-cone", "seqslam-hybrid")  # they use each frame's best match over the whole map


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
    last, inside a temporary folder renamed when complete). A map with an index gives each shard one like it."""
    if overlap < 0:
        raise SeqvprError(f"--overlap must be 0 or more frames, got {overlap}")
    saved = open_map(source)
    records = []
    with atomic_folder(out, SHARDS_FILE) as tmp:
        for number, (lo, a, b, hi) in enumerate(shard_ranges(saved.info.count, shards, overlap)):
            folder = f"shard-{number:03d}"
            shard = {"number": number, "of": shards, "first": lo, "own": [a, b], "count": saved.info.count,
                     "map": saved.info.identity}
            written = write_map_rows(saved, lo, hi, tmp / folder, shard)
            _index_like(saved, tmp / folder)
            records.append(ShardRecord(folder, lo, a, b, written.identity))
        description = {"format": SHARDS_FORMAT, "version": SHARDS_VERSION, "count": saved.info.count,
                       "overlap": overlap, "source": str(source), "shards": [r.__dict__ for r in records],
                       "map": saved.info.to_json()}
        (tmp / SHARDS_FILE).write_text(json.dumps(description, indent=2))
    return open_sharded_map(out)


def build_sharded(build: Callable[[Path], object], out: str | Path, shards: int,
                  overlap: int = DEFAULT_OVERLAP) -> ShardedMap:
    """A map made by ``build(folder)`` (and indexed there, if it does) written straight as ``shards`` shards under
    ``out``: built in a temporary folder beside ``out``, sharded, then removed, failed or not."""
    import shutil

    target = Path(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    whole = temporary_folder(target.parent / f"{target.name}.whole")
    try:
        shutil.rmtree(whole)  # the map writer makes its own folder
        build(whole)
        return shard_map(whole, target, shards, overlap)
    finally:
        shutil.rmtree(whole, ignore_errors=True)


def index_shards(sharded: ShardedMap, spec, seed: int = 0, progress=None, windows: int = 0,
                 method: str = "smoothing", model_folder: str | Path | None = None) -> list[dict[str, Any]] | None:
    """Each shard's own faiss index (``add_index``, as for one map), for shortlisted matching of the sharded map;
    under ``torchrun`` each rank builds its shards'. The records of all, in shard order, on rank 0 (None elsewhere)."""
    from seqvpr import distributed
    from seqvpr.maps.index import add_index

    world = distributed.current()
    numbers = shard_numbers(len(sharded.shards), world.rank, world.size)
    built = distributed.gather_to_root(lambda: [(n, add_index(sharded.open_shard(n), spec, seed, progress, windows,
                                                              method, model_folder)) for n in numbers], world)
    return None if built is None else [record for _, record in sorted(p for part in built for p in part)]


def _index_like(source: SavedMap, shard_folder: Path) -> None:
    """Give a new shard an index like its source map's (same spec, vectors, seed and SeqNet), over its own rows."""
    from seqvpr.maps.index import add_index, parse_index_spec

    record = source.info.index
    if not record:
        return
    over = record["over"]
    method, windows = ("smoothing", 0) if over == "frames" else (over.split(":")[0], int(over.split(":")[1]))
    add_index(open_map(shard_folder), parse_index_spec(record["spec"]), int(record.get("seed", 0)), None, windows,
              method, (record.get("model") or {}).get("folder"))


def check_shardable(method: str, settings, sharded: ShardedMap, search: Mapping[str, Any] | None = None) -> None:
    """A method whose per-window scores a shard can compute from the rows it holds: the frames its windows cover
    (its matcher's span: adaptive paths, SeqSLAM's contrast neighbourhood) fit in the shards' overlap."""
    from seqvpr.methods import build_matcher, get_method

    record = get_method(method)
    if record.search in WHOLE_MAP_SEARCHES:
        raise SeqvprError(f"--method {method} votes with each query frame's best match over the whole map, which no "
                          "shard sees; match the unsharded map")
    family = record.family
    if family not in SHARDABLE_FAMILIES:
        raise SeqvprError(f"--method {method} scores whole paths or shortlists over the whole map; a sharded map "
                          f"is matched by sequence matching or sequence descriptors "
                          f"({', '.join(SHARDABLE_FAMILIES)} methods)")
    span = build_matcher(method, settings, {}, **(search or {})).span()
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


def shard_numbers(shards: int, rank: int, world: int) -> list[int]:
    """The shards rank ``rank`` of ``world`` matches: every world-th one from its rank (all of them alone)."""
    return list(range(rank, shards, world))


def match_sharded_map(sharded: ShardedMap, query: Traversal, method: str, settings,
                      models: Mapping[str, Any] | None = None, progress=None, *, shortlist: int = 0,
                      history: int = 0, nprobe: int = 16, search: Mapping[str, Any] | None = None,
                      **extraction: Any) -> MatchResult | None:
    """Match ``query`` against every shard: under ``torchrun`` each rank its own shards, merged on rank 0 (other
    ranks get None); alone, all shards in turn. The result equals matching the unsharded map (shortlisted: with
    flat indexes; each shard's own approximate index otherwise). ``search``: the method's own settings (steps,
    contrast window)."""
    from seqvpr import distributed
    from seqvpr.maps.match import prepare_query

    check_shardable(method, settings, sharded, search)
    world = distributed.current()
    numbers = shard_numbers(len(sharded.shards), world.rank, world.size)
    prepared = distributed.everywhere(  # described once a rank, as the shards' (shared) description says
        lambda: prepare_query(sharded.open_shard(0), query, method, settings, models, 0, progress, **extraction))
    if shortlist:
        return shortlist_sharded_map(sharded, numbers, prepared, settings, shortlist, history, nprobe)
    parts = distributed.gather_to_root(lambda: match_shards(sharded, numbers, prepared, settings, progress, search), world)
    if parts is None:
        return None
    return merge_shard_matches(sharded, [p for rank_parts in parts for p in rank_parts], prepared.frames, settings)


def match_shards(sharded: ShardedMap, numbers: Sequence[int], prepared: PreparedQuery, settings,
                 progress=None, search: Mapping[str, Any] | None = None) -> list[ShardMatch]:
    """The top-K, in whole-map rows over owned frames, of each shard in ``numbers`` against the prepared query (a
    row in the whole map's top-K is in its shard's, which has fewer rivals), with the per-frame pairs of its top-1 matches where the method makes its own; a shard whose segments are all
    shorter than a window contributes nothing."""
    from seqvpr.maps.match import match_prepared
    from seqvpr.sequences.matching import max_span
    from seqvpr.sequences.windows import window_starts

    spec, query = settings.sequence, prepared.frames
    parts = []
    for number in numbers:
        record, shard = sharded.shards[number], sharded.open_shard(number)
        if not (window_starts(shard.frames.segment_ids, max_span(spec), 0, spec.boundary) >= 0).any():
            parts.append(ShardMatch(number, _no_match(query, settings), None))
            continue
        result = match_prepared(shard, prepared, settings, progress=progress, search=search)
        pairs = None if result.correspondences is None else (
            result.correspondences[0], np.where(result.correspondences[1] >= 0, result.correspondences[1] + record.first, -1))
        parts.append(ShardMatch(number, owned_topk(result.topk, record, settings.k), pairs))
    return parts


def _no_match(query: Traversal, settings) -> TopK:
    from seqvpr.sequences.windows import window_starts

    spec = settings.sequence
    has_window = window_starts(query.segment_ids, spec.length, spec.offset, spec.boundary) >= 0
    return TopK(np.full((len(query), settings.k), -1), np.full((len(query), settings.k), np.inf), has_window)


def shortlist_sharded_map(sharded: ShardedMap, numbers: Sequence[int], prepared: PreparedQuery, settings,
                          shortlist: int, history: int, nprobe: int) -> MatchResult | None:
    """Shortlisted matching of a sharded map: each rank searches its shards' indexes, rank 0 merges the nearest
    ``shortlist`` rows a query frame (or window) into the candidates and sends them out, each rank re-ranks the
    candidates its shards own, and rank 0 merges the top-K. With flat indexes this is the unsharded shortlist."""
    from seqvpr import distributed
    from seqvpr.maps.match import shortlist_candidates, shortlist_query, shortlist_size
    from seqvpr.pipeline import MatchResult

    frames = prepared.frames
    query, settings = shortlist_query(frames, prepared.method, settings)
    over = distributed.everywhere(lambda: _shards_index(sharded, prepared, history))  # every shard checked
    shortlist, history = shortlist_size(shortlist, history, sharded.count, len(frames), settings)
    shards = {n: sharded.open_shard(n) for n in numbers}
    found = distributed.gather_to_root(
        lambda: [_shard_neighbours(shards[n], sharded.shards[n], query, frames, shortlist, nprobe) for n in numbers])

    def candidates() -> TopK:
        merged = merge_topks([part for rank_parts in found for part in rank_parts], shortlist)  # type: ignore[union-attr]
        return shortlist_candidates(merged, over, frames.segment_ids, settings.sequence, sharded.count, history)

    shortlisted = distributed.broadcast_from_root(candidates)
    tops = distributed.gather_to_root(
        lambda: [_shard_rerank(shards[n], sharded.shards[n], query, shortlisted, settings, frames) for n in numbers])
    if tops is None:
        return None
    width = min(settings.k, shortlisted.indices.shape[1])  # as re-ranking keeps: no more than the candidates
    top = merge_topks([part for rank_parts in tops for part in rank_parts], width)
    return MatchResult(map_table(sharded), frames, top, settings, shortlist=shortlisted)


def _shards_index(sharded: ShardedMap, prepared: PreparedQuery, history: int) -> str:
    """What every shard's index holds (the same for all, checked); a shard without one is a one-line error."""
    from seqvpr.maps.match import check_shortlist

    over = set()
    for number in range(len(sharded.shards)):
        shard = sharded.open_shard(number)
        check_shortlist(shard, prepared.method, prepared.models)
        over.add(shard_index_over(sharded, shard, history))
    if len(over) > 1:
        raise SeqvprError(f"{sharded.folder}: its shards' indexes hold different vectors ({', '.join(sorted(over))}): "
                          f"seqvpr map index {sharded.folder} --index SPEC indexes them all alike")
    return over.pop()


def shard_index_over(sharded: ShardedMap, shard: SavedMap, history: int = 0) -> str:
    """What a shard's index holds (``index_over``); a shard without one is a one-line error naming the command
    that indexes every shard."""
    from seqvpr.maps.match import index_over

    if not shard.info.index:
        raise SeqvprError(f"{shard.folder} has no index: index every shard with seqvpr map index {sharded.folder} "
                          "--index SPEC")
    return index_over(shard, history)


def _shard_neighbours(shard: SavedMap, record: ShardRecord, query, frames: Traversal, width: int,
                      nprobe: int) -> TopK:
    """A shard's ``width`` nearest owned rows of each query frame or window, in whole-map rows (a row among the
    whole map's nearest is among its shard's, which are fewer)."""
    from seqvpr.maps.match import index_neighbours

    found = index_neighbours(shard, query, frames.segment_ids, width, nprobe)
    return owned_topk(found, record, width)


def _shard_rerank(shard: SavedMap, record: ShardRecord, query, candidates: TopK, settings, frames: Traversal) -> TopK:
    """The candidates a shard owns re-ranked over its rows: their top-K in whole-map rows."""
    from seqvpr.maps.match import rerank_candidates

    rows = candidates.indices
    owned = (rows >= record.own_first) & (rows < record.own_last)
    local = TopK(np.where(owned, rows - record.first, -1), candidates.distances, candidates.has_window)
    return owned_topk(rerank_candidates(shard, query, local, settings, frames.segment_ids), record, settings.k)


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
