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
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from dataclasses import replace

from seqvpr.identity import DigestWriter, combined_identity
from seqvpr.io import atomic_folder, atomic_write
from seqvpr.maps.codes import SIDE_FILES, fit_encoder, parse_storage, stored_shape
from seqvpr.maps.files import (
    DESCRIPTORS_FILE, INFO_FILE, SHARDS_FILE, SHARDS_FORMAT, SHARDS_VERSION, MapInfo, MapSource, ShardedMap,
    ShardRecord, completed_info, open_map, open_sharded_map, write_frame_table, write_map, write_map_rows,
)
from seqvpr.matchers.sharded import check_overlap, shard_numbers
from seqvpr.sequences.topk import TopK, merge_topks

if TYPE_CHECKING:
    from seqvpr.maps.files import SavedMap
    from seqvpr.matchers.base import MatchResult

DEFAULT_OVERLAP = 63  # windows of up to 64 frames (any velocity) are never cut
SHARDABLE_FAMILIES = ("matching", "retrieval")  # per-window scores: a shard's top-K over its own frames is exact
WHOLE_MAP_SEARCHES = ("seqslam-cone", "seqslam-hybrid")  # they use each frame's best match over the whole map


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
        write_shards_file(tmp, records, overlap, saved.info, str(source))
    return open_sharded_map(out)


def write_sharded_map(out: str | Path, frames: Traversal, info: MapInfo, shards: int,
                      overlap: int = DEFAULT_OVERLAP, indexed: Callable[[ShardedMap], object] | None = None) -> ShardedMap:
    """``frames`` (rows read a chunk at a time: a memory map or lazy rows) written straight as ``shards`` shard maps
    under ``out``, never as the whole map first: one encoder fitted to all rows (sq8's range, pq's codebooks), so
    each shard stores the codes the whole map would; the whole map's identity composed from the digests its files
    would have (``whole_map_digests``). The same shards, bit for bit, as ``shard_map`` of the whole map. ``indexed``
    (e.g. ``index_shards``) runs before the sharded map replaces anything at ``out``: committed as one."""
    if overlap < 0:
        raise SeqvprError(f"--overlap must be 0 or more frames, got {overlap}")
    assert frames.descriptors is not None
    ranges = shard_ranges(len(frames), shards, overlap)
    parse_storage(info.dtype, frames.descriptors.shape[1])  # an unknown storage fails before any work
    fitted = fit_encoder(frames.descriptors, info.dtype)
    whole = completed_info(frames, info)
    with atomic_folder(out, SHARDS_FILE) as tmp:
        folders = [f"shard-{number:03d}" for number in range(shards)]
        for number, (folder, (lo, a, b, hi)) in enumerate(zip(folders, ranges)):
            shard = {"number": number, "of": shards, "first": lo, "own": [a, b], "count": len(frames), "map": None}
            part = replace(whole, count=hi - lo, sources=range_sources(whole.sources, lo, hi), shard=shard)
            write_map(tmp / folder, frame_range(frames, lo, hi), part, fitted)
        digests = whole_map_digests([tmp / f for f in folders], ranges, frames, whole, fitted[1])
        whole = replace(whole, files=digests, identity=combined_identity(digests))
        records = [ShardRecord(folder, lo, a, b, name_whole_map(tmp / folder, whole.identity))
                   for folder, (lo, a, b, hi) in zip(folders, ranges)]
        write_shards_file(tmp, records, overlap, whole, source="")
        if indexed is not None:
            indexed(open_sharded_map(tmp))
    return open_sharded_map(out)


def write_shards_file(folder: Path, records: list[ShardRecord], overlap: int, whole: MapInfo, source: str) -> None:
    """``shards.json``: the shards, the overlap and the whole map's ``map.json`` (written last: it marks the
    sharded map complete)."""
    description = {"format": SHARDS_FORMAT, "version": SHARDS_VERSION, "count": whole.count, "overlap": overlap,
                   "source": source, "shards": [r.__dict__ for r in records], "map": whole.to_json()}
    (folder / SHARDS_FILE).write_text(json.dumps(description, indent=2))


class RowRange:
    """Rows ``[lo, hi)`` of rows read by slices (a memory map, lazy rows), read by slices like an array."""

    ndim = 2

    def __init__(self, rows: Any, lo: int, hi: int) -> None:
        self.rows, self.lo = rows, lo
        self.shape, self.dtype = (hi - lo, int(rows.shape[1])), rows.dtype

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: slice) -> np.ndarray:
        start, stop, _ = key.indices(len(self))
        return np.asarray(self.rows[self.lo + start : self.lo + stop])


def frame_range(frames: Traversal, lo: int, hi: int) -> Traversal:
    """Frames ``[lo, hi)`` as a shard stores them: segment ids, names and every column as the whole map has them,
    the rows read through ``frames``' own (``RowRange``)."""
    names = frames.image_names()
    cut = lambda values: None if values is None else values[lo:hi]  # noqa: E731
    return replace(frames, frame_index=frames.frame_index[lo:hi], segment_ids=frames.segment_ids[lo:hi],
                   descriptors=RowRange(frames.descriptors, lo, hi), image_paths=cut(frames.image_paths),
                   positions=cut(frames.positions), timestamps=cut(frames.timestamps), headings=cut(frames.headings),
                   names=None if names is None else tuple(names[lo:hi]), stored=None)


def range_sources(sources: tuple[MapSource, ...], lo: int, hi: int) -> tuple[MapSource, ...]:
    """The ``sources`` records of rows ``[lo, hi)``: each source they hold, its rows counted from ``lo``."""
    kept = [(s, max(s.first, lo), min(s.first + s.frames, hi)) for s in sources]
    return tuple(MapSource(s.source, s.name, a - lo, b - a) for s, a, b in kept if b > a)


def whole_map_digests(folders: list[Path], ranges, frames: Traversal, info: MapInfo, side) -> dict[str, str]:
    """The digest of every file the whole map would hold, without writing it: its descriptors' header and each
    shard's owned rows as the shards store them, its side file, and its per-frame table (``write_frame_table``
    into digests)."""
    from numpy.lib import format as npy

    shape, dtype = stored_shape(info.dtype, info.count, info.dim)
    rows = DigestWriter()
    npy.write_array_header_1_0(rows, {"descr": npy.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
                                      "shape": shape})
    row_bytes = np.dtype(dtype).itemsize * shape[1]
    for folder, (lo, a, b, _) in zip(folders, ranges):
        with open(folder / DESCRIPTORS_FILE, "rb") as handle:
            npy.read_magic(handle)
            npy.read_array_header_1_0(handle)
            handle.seek(handle.tell() + (a - lo) * row_bytes)
            for left in range((b - a) * row_bytes, 0, -(1 << 22)):
                rows.write(handle.read(min(left, 1 << 22)))
    digests = {DESCRIPTORS_FILE: rows.digest()}
    if side is not None:
        with DigestWriter() as writer:
            np.save(writer, side)
        digests[SIDE_FILES[parse_storage(info.dtype)[0]]] = writer.digest()
    writers: dict[str, DigestWriter] = {}
    write_frame_table(frames, info, frames.image_names(), lambda name: writers.setdefault(name, DigestWriter()))
    return {**digests, **{name: writer.digest() for name, writer in writers.items()}}


def name_whole_map(folder: Path, identity: str) -> str:
    """Record the whole map's identity in a shard's ``map.json`` (not one of the files its identity covers); the
    shard's own identity."""
    path = folder / INFO_FILE
    values = json.loads(path.read_text())
    values["shard"]["map"] = identity
    with atomic_write(path) as handle:
        handle.write(json.dumps(values, indent=2))
    return values["identity"]


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
