"""A sharded map's shards' indexes searched as one: each rank searches its shards for their nearest owned rows and
every rank merges all of them (with flat indexes, the whole map's nearest), the shortlist of a sharded map."""

from __future__ import annotations

import numpy as np

from seqvpr.errors import SeqvprError, SettingError
from seqvpr.maps.files import SavedMap, ShardedMap
from seqvpr.matchers.sharded import shard_numbers
from seqvpr.results import TopK


class ShardedNeighbors:
    """The shards' indexes as one shortlist ``Neighbours``: each rank searches its shards for their nearest owned
    rows, and every rank merges all of them (the whole map's nearest, with flat indexes). Every shard must have an
    index over the same vectors (checked on every rank, so each fails alike)."""

    def __init__(self, sharded: ShardedMap, world=None, nprobe: int = 16, history: int = 0) -> None:
        from seqvpr import distributed
        from seqvpr.maps.index import IndexNeighbors

        world = world or distributed.current()
        self.over, self.vectors, self.world = shards_index_over(sharded, history), sharded.count, world
        self.parts = [(sharded.shards[n], IndexNeighbors(sharded.open_shard(n), nprobe))
                      for n in shard_numbers(len(sharded.shards), world.rank, world.size)]

    def search(self, rows, segments: np.ndarray, width: int) -> TopK:
        """The ``width`` nearest rows of the whole map, in whole-map rows (a row among the whole map's nearest is
        among its shard's, which are fewer)."""
        from seqvpr import distributed
        from seqvpr.matchers.sharded import owned_topk
        from seqvpr.sequences.topk import merge_topks

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
        raise SettingError(f"{{history}} needs an index over frames; {shard.folder}'s is over {over}")
    return over
