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

from seqvpr.data.traversal import Traversal
from seqvpr.maps.files import ShardedMap
from seqvpr.matchers.sharded import shard_numbers

if TYPE_CHECKING:
    from seqvpr.results import MatchResult


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


def match_sharded_map(sharded: ShardedMap, query: Traversal, method: str, settings,
                      models: Mapping[str, Any] | None = None, progress=None, **options: Any) -> MatchResult | None:
    """Deprecated: ``seqvpr.maps.match_map`` takes a sharded map as it takes a map (kept for one release)."""
    import warnings

    from seqvpr.maps.match import match_map

    warnings.warn("seqvpr.maps.shards.match_sharded_map is deprecated: use seqvpr.maps.match_map", DeprecationWarning,
                  stacklevel=2)
    return match_map(sharded, query, method, settings, models, progress=progress, **options)
