"""Writing sharded maps (``seqvpr.maps.shards`` reads and matches them): a saved map cut into shards
(``shard_map``), or frames written straight as shards, never as the whole map first (``write_sharded_map``).
Each shard owns an equal run of rows and stores ``overlap`` rows of each neighbour besides (``shard_ranges``)."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SettingError
from seqvpr.identity import DigestWriter, combined_identity
from seqvpr.arrays import load_npy
from seqvpr.io import atomic_folder, atomic_write, check_output_apart
from seqvpr.maps.names import write_names
from seqvpr.maps.codes import SIDE_FILES, fit_encoder, parse_storage, stored_shape
from seqvpr.maps.files import (
    DESCRIPTORS_FILE, INFO_FILE, SHARDS_FILE, SHARDS_FORMAT, SHARDS_VERSION, MapInfo, MapSource, ShardedMap,
    ShardRecord, completed_info, open_map, open_sharded_map, write_frame_table, write_map, PER_FRAME_FILES, stored_rows,
    write_sealed_info,
)

if TYPE_CHECKING:
    from seqvpr.maps.files import SavedMap

DEFAULT_OVERLAP = 63  # windows of up to 64 frames (any velocity) are never cut


def shard_ranges(count: int, shards: int, overlap: int) -> list[tuple[int, int, int, int]]:
    """``(first, own_first, own_last, last)`` of each of ``shards`` equal runs of ``count`` frames, ``overlap``
    frames past each end (clipped to the map)."""
    if not 1 <= shards <= count:
        raise SettingError(f"{{shards}} must be between 1 and the map's {count} frames, got {shards}")
    bounds = [count * i // shards for i in range(shards + 1)]
    return [(max(0, a - overlap), a, b, min(count, b + overlap)) for a, b in zip(bounds, bounds[1:])]


def shard_map(source: str | Path, out: str | Path, shards: int, overlap: int = DEFAULT_OVERLAP) -> ShardedMap:
    """Split the map at ``source`` into ``shards`` shard maps under ``out`` (written atomically: ``shards.json``
    last, inside a temporary folder renamed when complete). A map with an index gives each shard one like it."""
    if overlap < 0:
        raise SettingError(f"{{overlap}} must be 0 or more frames, got {overlap}")
    check_output_apart(out, [source], "the sharded map")
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
        raise SettingError(f"{{overlap}} must be 0 or more frames, got {overlap}")
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
        written = open_sharded_map(tmp)
        for number in range(shards):  # what a reader will do, before the shards replace anything
            written.open_shard(number)
        if indexed is not None:
            indexed(written)
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
                   names=None if names is None else tuple(names[lo:hi]))


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


def write_map_rows(saved: SavedMap, lo: int, hi: int, folder: Path, shard: dict[str, Any]) -> MapInfo:
    """Rows ``[lo, hi)`` of an opened map as a map of their own in ``folder`` (which must not exist): every stored
    file sliced as stored (codes stay the same codes), the side files copied, ``map.json`` last with ``shard``
    (and its own digests and identity); its info returned."""
    import shutil

    folder.mkdir(parents=True)
    stored = stored_rows(saved.folder, saved.info)
    np.save(folder / DESCRIPTORS_FILE, np.ascontiguousarray(stored[lo:hi]))
    for name in SIDE_FILES.values():  # a frame index is not carried over: a shard is matched exactly
        if (saved.folder / name).is_file():
            shutil.copyfile(saved.folder / name, folder / name)
    rows = {}
    for name in PER_FRAME_FILES:
        if (saved.folder / name).is_file():
            rows[name] = load_npy(saved.folder / name)[lo:hi]
    kept, remapped = np.unique(rows["sources.npy"], return_inverse=True)
    rows["sources.npy"] = remapped.astype(np.int32)
    for name, values in rows.items():
        np.save(folder / name, values)
    if saved.frames.names is not None:
        write_names(saved.frames.names[lo:hi], lambda name: open(folder / name, "wb"))
    sources = tuple(MapSource(saved.info.sources[int(k)].source, saved.info.sources[int(k)].name,
                              int(np.argmax(remapped == i)), int(np.count_nonzero(remapped == i)))
                    for i, k in enumerate(kept))
    info = replace(saved.info, count=hi - lo, sources=sources, index=None, shard=shard)
    return write_sealed_info(folder, info)
