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
the localiser and every other map command take one in a single process. Writing them: ``seqvpr.maps.sharding``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.maps.files import ShardedMap
from seqvpr.matchers.sharded import check_overlap, shard_numbers
from seqvpr.sequences.topk import merge_topks
from seqvpr.results import TopK

if TYPE_CHECKING:
    from seqvpr.maps.files import SavedMap
    from seqvpr.results import MatchResult

SHARDABLE_FAMILIES = ("matching", "retrieval")  # per-window scores: a shard's top-K over its own frames is exact
WHOLE_MAP_SEARCHES = ("seqslam-cone", "seqslam-hybrid")  # they use each frame's best match over the whole map


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


def check_shardable(method: str, settings, sharded: ShardedMap, search: Mapping[str, Any] | None = None,
                    models: Mapping[str, Any] | None = None) -> None:
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
    check_overlap(build_matcher(method, settings, models, **(search or {})), sharded)


def match_sharded_map(sharded: ShardedMap, query: Traversal, method: str, settings,
                      models: Mapping[str, Any] | None = None, progress=None, *, shortlist: int = 0,
                      history: int = 0, nprobe: int = 16, search: Mapping[str, Any] | None = None,
                      **extraction: Any) -> MatchResult | None:
    """Match ``query`` against every shard: under ``torchrun`` each rank its own shards, merged on rank 0 (other
    ranks get None); alone, all shards in turn (``seqvpr.matchers.sharded.Sharded``). The result equals matching
    the unsharded map (shortlisted: the shards' nearest rows merged into one shortlist, each shard re-ranking the
    candidates it owns; with flat indexes the unsharded shortlist). ``search``: the method's own settings (steps,
    contrast window)."""
    from seqvpr import distributed
    from seqvpr.maps.match import check_shortlist, map_matcher, prepare_query
    from seqvpr.matchers.sharded import Sharded
    from seqvpr.matchers.shortlisted import Shortlisted

    check_shardable(method, settings, sharded, search, models)
    world = distributed.current()
    first = sharded.open_shard(0)
    prepared = distributed.everywhere(  # described once a rank, as the shards' (shared) description says
        lambda: prepare_query(first, query, method, settings, models, 0, progress, **extraction))
    if shortlist:
        distributed.everywhere(lambda: check_shortlist(first, prepared.method, prepared.models))
        neighbours = distributed.everywhere(lambda: ShardedNeighbours(sharded, world, nprobe, history))
        matcher = map_matcher(first, prepared, settings, progress=progress, search=search)
        return Shortlisted(Sharded(matcher, world), neighbours, shortlist, history).topk(sharded, prepared.frames)
    matcher = map_matcher(first, prepared, settings, progress=progress, search=search)
    return Sharded(matcher, world).topk(sharded, prepared.frames)


class ShardedNeighbours:
    """The shards' indexes as one shortlist ``Neighbours``: each rank searches its shards for their nearest owned
    rows, and every rank merges all of them (the whole map's nearest, with flat indexes). Every shard must have an
    index over the same vectors (checked on every rank, so each fails alike)."""

    def __init__(self, sharded: ShardedMap, world, nprobe: int = 16, history: int = 0) -> None:
        from seqvpr.maps.index import IndexNeighbours

        self.over, self.vectors, self.world = shards_index_over(sharded, history), sharded.count, world
        self.parts = [(sharded.shards[n], IndexNeighbours(sharded.open_shard(n), nprobe))
                      for n in shard_numbers(len(sharded.shards), world.rank, world.size)]

    def search(self, rows, segments: np.ndarray, width: int) -> TopK:
        """The ``width`` nearest rows of the whole map, in whole-map rows (a row among the whole map's nearest is
        among its shard's, which are fewer)."""
        from seqvpr import distributed
        from seqvpr.matchers.sharded import owned_topk

        found = distributed.gather_everywhere(
            lambda: [owned_topk(index.search(rows, segments, width), record, width) for record, index in self.parts],
            self.world)
        return merge_topks([part for rank_parts in found for part in rank_parts], width)


def shards_index_over(sharded: ShardedMap, history: int = 0) -> str:
    """What every shard's index holds (the same for all, checked); a shard without one is a one-line error."""
    over = {shard_index_over(sharded, sharded.open_shard(number), history) for number in range(len(sharded.shards))}
    if len(over) > 1:
        raise SeqvprError(f"{sharded.folder}: its shards' indexes hold different vectors ({', '.join(sorted(over))}): "
                          f"seqvpr map index {sharded.folder} --index SPEC indexes them all alike")
    return over.pop()


def shard_index_over(sharded: ShardedMap, shard: SavedMap, history: int = 0) -> str:
    """What a shard's index holds; a shard without one is a one-line error naming the command that indexes every
    shard, as is history over an index of windows."""
    if not shard.info.index:
        raise SeqvprError(f"{shard.folder} has no index: index every shard with seqvpr map index {sharded.folder} "
                          "--index SPEC")
    over = shard.info.index["over"]
    if history and over != "frames":
        raise SeqvprError(f"--shortlist-history needs an index over frames; {shard.folder}'s is over {over}")
    return over
