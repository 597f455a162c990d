"""A saved map: plain files in one folder, written atomically and opened memory-mapped.

    MAP/map.json          format, version, count, dimension, dtype, metric, normalisation, how the frames were
                          described (descriptor, settings, model kind and sha256), sources, library version, time
    MAP/descriptors.npy   [N, D] float32 or float16 frame descriptors, or uint8 codes (``sq8`` [N, D], ``pq:M``
                          [N, M]; memory-mappable; see ``codes``)
    MAP/quantizer.npy     ``sq8``: [2, D] float32 per-dimension offset and step (x = offset + step * code)
    MAP/pq_centroids.npy  ``pq:M``: [M, 256, D / M] float32 sub-centroids
    MAP/segments.npy      [N] int64 segment id (a window never spans two; each source has its own)
    MAP/sources.npy       [N] int32 row of map.json's ``sources`` each frame came from
    MAP/frame_index.npy   [N] int64 the frame's index in its source (survives --frames slicing)
    MAP/positions.npy     [N, 2] float64 easting, northing in metres (only when every source has positions), in
                          map.json's ``crs`` (``utm:32N``: they go back to latitude/longitude; ``local``)
    MAP/timestamps.npy    [N] float64 seconds (only when every source has them); likewise headings.npy (degrees)
    MAP/names.txt         one name per frame: its image path, or a bag frame's ``BAG:TOPIC@STAMP`` (only when
                          every source is images), with names_offsets.npy [N + 1] int64: each line's byte offset
                          (``names``: opened memory-mapped, a name decoded when asked for)

``map.json`` is written last, inside a temporary folder that is renamed to MAP when complete, so a half-built
map never carries the name. A sharded map (``shards.json`` beside ``shard-000/`` ... maps; ``seqvpr.maps.shards``
makes and matches them) is read here too, and ``open_map`` opens it as the whole map, rows read through its shards.

Same name as ``seqvpr.models.files``: the same concept (an artifact's folder on disk) for a map; a model's there.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from seqvpr.data.geo import LOCAL
from seqvpr.data.traversal import Traversal
from seqvpr.arrays import load_npy
from seqvpr import checks
from seqvpr.errors import SeqvprError, SeqvprWarning
from seqvpr.identity import check_digest, combined_identity, seal_files
from seqvpr.io import atomic_folder
from seqvpr.maps.codes import SIDE_FILES, decoded_rows, parse_storage, row_chunks, stored_shape, write_encoded
from seqvpr.maps.names import FramePaths, open_names, write_names
from seqvpr.maps.parts import is_plain_name, part_records, session_of_rows, stored_parts

MAP_FORMAT = "seqvpr-map"
MAP_VERSION = 2  # 2: map.json records each file's digest and the map's identity
GROWN_VERSION = 3  # 3: a map grown by ``map add``: its rows in parts, its sessions
READABLE_VERSIONS = (1, 2, 3)  # a version-1 map (no identity) still opens, unproven, with a warning
INFO_FILE = "map.json"
DESCRIPTORS_FILE = "descriptors.npy"
OPTIONAL_COLUMNS = ("positions", "timestamps", "headings")


@dataclass(frozen=True)
class MapSource:
    """One source of a map: what the user named, the traversal's name, and its rows ``[first, first + frames)``."""

    source: str
    name: str
    first: int
    frames: int


@dataclass(frozen=True)
class MapInfo:
    """``map.json``: everything needed to use the map without its sources, and to refuse a mismatched query."""

    count: int
    dim: int
    dtype: str
    normalized: bool
    description: dict[str, Any]
    sources: tuple[MapSource, ...]
    model: dict[str, Any] | None = None
    metric: str = "euclidean"
    format: str = MAP_FORMAT
    version: int = MAP_VERSION
    library_version: str = ""
    created: str = ""
    index: dict[str, Any] | None = None
    columns: tuple[str, ...] = field(default=())
    shard: dict[str, Any] | None = None  # in a sharded map: its number, and its rows of the whole (``shards``)
    crs: str | None = None  # the positions' coordinate system (``seqvpr.data.geo``); None: no positions
    identity: str | None = None  # the map's content identity: a hash of its row files' digests (``files``)
    files: dict[str, str] | None = None  # each data file's content digest (``seqvpr.identity``); index files too
    parts: tuple[tuple[str, int], ...] | None = None  # a grown map's row files and counts (``seqvpr.maps.parts``)
    sessions: tuple[dict[str, Any], ...] | None = None  # what each ``map add`` appended (``seqvpr.maps.grow``)

    def to_json(self) -> dict[str, Any]:
        values = asdict(self)
        values["sources"] = [asdict(s) for s in self.sources]
        return values


def write_map(folder: str | Path, frames: Traversal, info: MapInfo, fitted=None, thumbnails: bool = False) -> Path:
    """Write a map folder atomically: the rows checked (finite; unit length in a normalised map) before anything is
    written, the descriptors in ``info.dtype`` (read, encoded and written a chunk at a time: ``frames.descriptors``
    may be a memory map or lazy rows, never held whole; by ``fitted``, ``codes.fit_encoder``'s, when given), the
    per-frame table (``write_frame_table``), each file's digest and the map's identity in ``map.json``, written last;
    the folder is opened as a reader would before it replaces an old map, so a map that cannot be opened never takes
    the name. With ``thumbnails``, each frame's thumbnail is kept too (``seqvpr.maps.thumbnails``)."""
    assert frames.descriptors is not None
    parse_storage(info.dtype, frames.descriptors.shape[1])  # an unknown storage fails before anything is written
    check_rows(frames.descriptors, info.normalized, f"{folder}: the map's rows")
    names = frames.image_names()
    check_names(names, folder)
    info = completed_info(frames, info)
    with atomic_folder(folder, INFO_FILE) as tmp:
        side = write_encoded(tmp / DESCRIPTORS_FILE, frames.descriptors, info.dtype, fitted=fitted)  # by chunks
        if side is not None:
            np.save(tmp / SIDE_FILES[parse_storage(info.dtype)[0]], side)
        write_frame_table(frames, info, names, lambda name: open(tmp / name, "wb"))
        if thumbnails:
            from seqvpr.maps.thumbnails import write_map_thumbnails

            write_map_thumbnails(tmp, frames.image_paths)
        write_sealed_info(tmp, info)
        open_map(tmp)  # what a reader will do, before the map replaces anything
    return Path(folder)


def completed_info(frames: Traversal, info: MapInfo) -> MapInfo:
    """``info`` as ``map.json`` records it for ``frames``: this seqvpr's version, the time, the optional columns
    the frames have and their positions' ``crs`` (digests and identity come when the files are sealed)."""
    from seqvpr import __version__

    columns = tuple(c for c in OPTIONAL_COLUMNS if getattr(frames, c) is not None)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    return MapInfo(**{**info.__dict__, "library_version": __version__, "created": stamp, "columns": columns,
                      "crs": frames.crs, "version": MAP_VERSION})


def write_frame_table(frames: Traversal, info: MapInfo, names: Sequence[str] | None,
                      open_file: Callable[[str], Any]) -> None:
    """The per-frame files of a map (segments, source frame numbers, sources, ``info.columns``, names) each
    written to ``open_file(name)`` (a binary handle: a file, or a digest of the bytes a file would hold)."""
    arrays = {"segments.npy": frames.segment_ids.astype(np.int64), "frame_index.npy": frames.frame_index.astype(np.int64),
              "sources.npy": np.repeat(np.arange(len(info.sources), dtype=np.int32), [s.frames for s in info.sources])}
    arrays.update({f"{c}.npy": np.asarray(getattr(frames, c), dtype=np.float64) for c in info.columns})
    for name, values in arrays.items():
        with open_file(name) as handle:
            np.save(handle, values)
    if names is not None:
        write_names(names, open_file)


def write_sealed_info(folder: Path, info: MapInfo) -> MapInfo:
    """``map.json`` written last, recording the digest of every other file in ``folder`` and their identity."""
    files = seal_files(folder, sorted(p.name for p in folder.iterdir() if p.name != INFO_FILE))
    sealed = replace(info, files=files, identity=combined_identity(files), version=MAP_VERSION)
    (folder / INFO_FILE).write_text(json.dumps(sealed.to_json(), indent=2))
    return sealed


def check_rows(rows, normalized: bool, what: str) -> None:
    """Every row finite and, in a normalised map, of unit length: one line naming the first bad row otherwise (read a
    chunk at a time, ``codes.row_chunks``, so a memory-mapped million rows are never held)."""
    for start, block in row_chunks(rows):
        squares = np.einsum("ij,ij->i", block, block)  # NaN or inf for a row that is not finite (or huge)
        bad = ~np.isfinite(block).all(axis=1) if not np.isfinite(squares).all() else np.zeros(len(block), bool)
        if bad.any():
            raise SeqvprError(f"{what}: row {start + int(np.argmax(bad))} is not finite (NaN or inf)")
        if normalized:
            norms = np.sqrt(squares.astype(np.float64))
            off = (np.abs(norms - 1.0) > 1e-2) & (norms > 0)  # a zero row stays zero when normalised
            if off.any():
                row = int(np.argmax(off))
                raise SeqvprError(f"{what}: row {start + row} has length {norms[row]:.4g}, but the map is marked "
                                  "normalised (unit rows)")


def check_names(names: Sequence[str] | None, folder: str | Path) -> None:
    """Frame names fit ``names.txt`` (one per line): a name with a line separator is one line naming the frame."""
    for row, name in enumerate(names or ()):
        if len(name.splitlines()) != 1 or name != name.strip("\r\n"):
            raise SeqvprError(f"{folder}: frame {row}'s name {name[:60]!r} holds a line separator (or is empty); "
                              "names.txt keeps one name a line")


PER_FRAME_FILES = ("segments.npy", "frame_index.npy", "sources.npy", *(f"{c}.npy" for c in OPTIONAL_COLUMNS))


@dataclass(frozen=True)
class SavedMap:
    """An opened map: its info, its descriptors memory-mapped (never read whole) and its frames as a Traversal
    whose ``descriptors`` are that memory map (decoded on access for a coded map)."""

    folder: Path
    info: MapInfo
    frames: Traversal
    #: how its rows are read: as ``info.dtype`` stores them (None), or ``sharded``: through a sharded map's shards
    storage: str | None = None

    @property
    def descriptors(self) -> np.ndarray:
        assert self.frames.descriptors is not None
        return self.frames.descriptors

    # a saved map is a ``seqvpr.data.reference.Reference``: its frame table's
    name = property(lambda self: self.frames.name)
    source = property(lambda self: self.frames.source)
    segment_ids = property(lambda self: self.frames.segment_ids)
    stored = property(lambda self: self.storage or self.info.dtype)  # read a chunk at a time as stored
    plain_rows = property(lambda self: self.stored == "float32")  # a float32 array, read as it is (no decoding)
    dim = property(lambda self: self.info.dim)
    index = property(lambda self: self.info.index)

    @property
    def owned(self) -> slice:
        """All its rows; a shard's own, those past the overlap it shares with its neighbours."""
        if not self.info.shard:
            return slice(0, self.info.count)
        first, (own_first, own_last) = self.info.shard["first"], self.info.shard["own"]
        return slice(own_first - first, own_last - first)

    def __len__(self) -> int:
        return self.info.count

    def sessions_of_rows(self, rows: np.ndarray) -> list[str]:
        """The session each map row came in with (``seqvpr.maps.grow``; "" for -1)."""
        return session_of_rows(self.info, rows)


def read_map_info(folder: str | Path) -> MapInfo:
    """``map.json`` of a map folder, checked: a missing file, another format or an unknown version is one line."""
    folder = Path(folder)
    path = folder / INFO_FILE
    if not folder.is_dir():
        raise SeqvprError(f"{folder}: no such map folder")
    if not path.is_file():
        raise SeqvprError(f"{folder}: not a seqvpr map (no {INFO_FILE}; a half-built map has none)")
    try:
        values = json.loads(path.read_text())
        kind, version = values.get("format"), values.get("version")
    except (ValueError, AttributeError) as error:
        raise SeqvprError(f"{path}: malformed map description ({type(error).__name__}: {error})") from None
    if kind != MAP_FORMAT:
        raise SeqvprError(f"{path}: not a seqvpr map (format {kind!r})")
    if version not in READABLE_VERSIONS:
        raise SeqvprError(f"{path}: map format version {version!r} is not known (this seqvpr reads versions "
                          f"{', '.join(map(str, READABLE_VERSIONS))})")
    try:
        values["sources"] = tuple(MapSource(**s) for s in values["sources"])
        values["columns"] = tuple(values.get("columns", ()))
        if values.get("parts") is not None:
            values["parts"] = part_records(values["parts"], values.get("count"), path)
        values["sessions"] = None if values.get("sessions") is None else tuple(dict(v) for v in values["sessions"])
        info = MapInfo(**with_crs(values))
    except (TypeError, KeyError, AttributeError) as error:
        raise SeqvprError(f"{path}: malformed map description ({type(error).__name__}: {error})") from None
    check_manifest(info, path)
    return info


def check_manifest(info: MapInfo, path: Path) -> None:
    """``map.json`` is consistent: a version-2 map names its files' digests and their identity, and every file it
    names (its files, its index's) is a plain name inside the map folder."""
    if info.version >= 2 and (not isinstance(info.files, dict) or info.identity != combined_identity(info.files)):
        raise SeqvprError(f"{path}: its file digests and identity do not agree (edited by hand?); rebuild the map")
    named = [*(info.files or {}), *((info.index or {}).get(key) for key in ("file", "rows_file"))]
    for name in filter(None, named):
        if not is_plain_name(name):
            raise SeqvprError(f"{path}: names the file {name!r}, which is not inside the map folder")


def verify_map_files(folder: Path, info: MapInfo, fresh: bool = False) -> None:
    """Every file ``map.json`` records holds the bytes it recorded (a stat where a file was seen before, else one
    streamed read, remembered; ``fresh``: read them all); a version-1 map has no digests: a warning."""
    if info.files is None:
        import warnings

        warnings.warn(f"{folder} was written by an older seqvpr and records no content identity, so it cannot be "
                      "checked: rebuild it with seqvpr map build", SeqvprWarning, stacklevel=3)
        return
    owner = str(folder / INFO_FILE)
    for name, digest in info.files.items():
        check_digest(folder / name, digest, owner, fresh)


def with_crs(values: dict[str, Any]) -> dict[str, Any]:
    """``map.json``'s values with a ``crs``: a map written before maps recorded one is ``local`` if it has
    positions (UTM without a zone), else None."""
    if "crs" in values:
        return values
    return {**values, "crs": LOCAL if "positions" in values.get("columns", ()) else None}


def open_map(folder: str | Path) -> SavedMap:
    """Open a saved map: descriptors and the per-frame table memory-mapped read-only (names decoded on access),
    every file checked. A sharded map (``seqvpr map shard``) opens as the whole map, read through its shards."""
    folder = checks.a_path(folder, "folder")
    if (folder / SHARDS_FILE).is_file():
        return open_sharded_map(folder).as_map()
    info = read_map_info(folder)
    verify_map_files(folder, info)
    descriptors = _stored_rows(folder, info)
    column = lambda name, shape, dtype: _load_column(folder, f"{name}.npy", shape, dtype, mmap=True)  # noqa: E731
    optional = {c: column(c, (info.count, 2) if c == "positions" else (info.count,), "float64") for c in info.columns}
    names = open_names(folder, info.count)
    paths = None if names is None else FramePaths(names)
    frames = Traversal(folder.name, column("frame_index", (info.count,), "int64"),
                       column("segments", (info.count,), "int64"), descriptors, paths, source=str(folder),
                       names=names, crs=info.crs, **optional)
    return SavedMap(folder, info, frames, storage="parts" if info.parts else None)


def stored_rows(folder: Path, info: MapInfo):
    """The map's rows as stored (floats or codes): one memory-mapped array, or a grown map's parts chained."""
    if info.parts:
        return stored_parts(folder, info, lambda name, shape, dtype: _load_column(folder, name, shape, dtype, True))
    shape, dtype = stored_shape(info.dtype, info.count, info.dim)
    return _load_column(folder, DESCRIPTORS_FILE, shape, dtype, mmap=True)


def _stored_rows(folder: Path, info: MapInfo):
    """The map's descriptor rows: the memory-mapped array, or its codes decoded on access (``codes``)."""
    kind, m = parse_storage(info.dtype, info.dim)
    stored = stored_rows(folder, info)
    side = None
    if kind == "sq8":
        side = _load_column(folder, SIDE_FILES[kind], (2, info.dim), "float32")
    elif kind == "pq":
        side = _load_column(folder, SIDE_FILES[kind], (m, 256, info.dim // m), "float32")
    return decoded_rows(info.dtype, stored, side)


def _load_column(folder: Path, name: str, shape: tuple[int, ...], dtype: str, mmap: bool = False) -> np.ndarray:
    """One ``.npy`` of the map, checked against the shape and dtype ``map.json`` promises."""
    path = folder / name
    if not path.is_file():
        raise SeqvprError(f"{path}: missing map file")
    try:
        # copy-on-write: chunks are zero-copy tensor views, and nothing written ever reaches the file
        array = load_npy(path, mmap_mode="c" if mmap else None)
    except SeqvprError:
        raise
    except (ValueError, OSError, EOFError) as error:
        raise SeqvprError(f"{path}: unreadable or truncated ({str(error).splitlines()[0]})") from None
    if array.shape != shape or array.dtype != np.dtype(dtype):
        raise SeqvprError(f"{path}: holds {array.dtype} {array.shape}, the map needs {dtype} {shape}")
    return array


# ----------------------------------------------------------------------------------------------- sharded maps

SHARDS_FILE = "shards.json"
SHARDS_FORMAT = "seqvpr-sharded-map"
SHARDS_VERSION = 2  # 2: each shard's identity, and the whole map's, recorded and checked

@dataclass(frozen=True)
class ShardRecord:
    """One shard: its folder (relative to the sharded map), its first row, and the rows it owns, in whole-map rows."""

    folder: str
    first: int
    own_first: int
    own_last: int
    identity: str | None = None  # the shard map's identity (its map.json); None in a sharded map of version 1


@dataclass(frozen=True)
class ShardedMap:
    """An opened sharded map's description: where its shards are and which rows each owns."""

    folder: Path
    count: int
    overlap: int
    shards: tuple[ShardRecord, ...]
    info: dict[str, Any]  # the unsharded map's ``map.json``

    def open_shard(self, number: int) -> SavedMap:
        """Shard ``number`` as a map, memory-mapped (only its own files are touched), checked to be the shard
        ``shards.json`` records there: its identity, its number, its rows and the map it was cut from."""
        record = self.shards[number]
        saved = open_map(self.folder / record.folder)
        expected = {"number": number, "first": record.first, "own": [record.own_first, record.own_last],
                    "count": self.count, "map": self.info.get("identity")}
        found = {key: (saved.info.shard or {}).get(key) for key in expected}
        if record.identity is not None and (saved.info.identity != record.identity or found != expected):
            raise SeqvprError(f"{saved.folder}: not the shard {number} that {self.folder / SHARDS_FILE} records "
                              "(swapped, copied from another map, or its rows shifted); re-shard the map")
        return saved

    def __len__(self) -> int:
        return self.count

    @property
    def frames(self) -> Traversal:
        """The whole map's frame table, rows read through the shards (``map_table``)."""
        return map_table(self)

    def as_map(self) -> SavedMap:
        """The whole map in one process, its rows read through the shards: what ``open_map`` gives for a sharded
        map, so every command (match, localize, map info) takes one."""
        values = {**self.info, "sources": tuple(MapSource(**s) for s in self.info["sources"]),
                  "columns": tuple(self.info.get("columns", ())), "index": None, "shard": None}
        return SavedMap(self.folder, MapInfo(**with_crs(values)), map_table(self), storage="sharded")


def is_sharded_map(folder: str | Path) -> bool:
    return (Path(folder) / SHARDS_FILE).is_file()


def open_sharded_map(folder: str | Path) -> ShardedMap:
    """``shards.json`` of a sharded map, checked: the shards tile the map's rows and each overlaps as recorded."""
    folder = Path(folder)
    path = folder / SHARDS_FILE
    if not path.is_file():
        raise SeqvprError(f"{folder}: not a sharded map (no {SHARDS_FILE})")
    try:
        values = json.loads(path.read_text())
        if values.get("format") != SHARDS_FORMAT or values.get("version") not in (1, SHARDS_VERSION):
            raise ValueError(f"format {values.get('format')!r} version {values.get('version')!r}")
        records = tuple(ShardRecord(**r) for r in values["shards"])
        sharded = ShardedMap(folder, int(values["count"]), int(values["overlap"]), records, dict(values["map"]))
    except (ValueError, TypeError, KeyError, AttributeError) as error:
        raise SeqvprError(f"{path}: malformed sharded map description ({type(error).__name__}: {error})") from None
    outside = [r.folder for r in records if not is_plain_name(r.folder)]
    if outside:
        raise SeqvprError(f"{path}: names the shard folder {outside[0]!r}, which is not inside the sharded map")
    owned = [(r.own_first, r.own_last) for r in records]
    if [a for a, _ in owned] != [0, *[b for _, b in owned[:-1]]] or owned[-1][1] != sharded.count:
        raise SeqvprError(f"{path}: its shards do not tile the map's {sharded.count} frames")
    return sharded


class ShardedRows:
    """The whole map's descriptor rows read through its shards' memory maps (each row from the shard owning it),
    indexed like an array a slice or a row list at a time; nothing is loaded until asked for."""

    ndim = 2

    def __init__(self, sharded: ShardedMap, shards: Sequence[SavedMap]) -> None:
        self.shards, self.records = list(shards), sharded.shards
        first = self.shards[0].descriptors
        self.shape, self.dtype = (sharded.count, first.shape[1]), np.dtype(first.dtype)
        self.bounds = np.array([r.own_last for r in self.records])

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def nbytes(self) -> int:
        """Bytes the shards store (their overlaps included)."""
        return int(sum(shard.descriptors.nbytes for shard in self.shards))

    def __getitem__(self, key) -> np.ndarray:
        rows = np.arange(self.shape[0])[key]
        owner = np.searchsorted(self.bounds, rows, side="right")
        out = np.empty((len(rows), self.shape[1]), dtype=self.dtype)
        for number in np.unique(owner):
            picked = owner == number
            local = rows[picked] - self.records[number].first
            span = slice(int(local[0]), int(local[-1]) + 1)
            contiguous = len(local) == span.stop - span.start and bool(np.all(np.diff(local) == 1))
            out[picked] = self.shards[number].descriptors[span if contiguous else local]
        return out


def map_table(sharded: ShardedMap) -> Traversal:
    """The whole map's frames from each shard's own rows (frame index, segments as in the whole map, positions,
    ...), their descriptors read through the shards (``ShardedRows``): the reference a sharded match reports."""
    shards = [sharded.open_shard(number) for number in range(len(sharded.shards))]  # each checks its own files
    parts: dict[str, list] = {"frame_index": [], "segment_ids": [], "image_paths": [], "names": [],
                              **{c: [] for c in OPTIONAL_COLUMNS}}
    for shard, record in zip(shards, sharded.shards):
        own = slice(record.own_first - record.first, record.own_last - record.first)
        for name in parts:
            value = getattr(shard.frames, name)
            parts[name].append(None if value is None else value[own])
    joined: dict[str, Any] = {}
    for name, values in parts.items():
        if any(v is None for v in values):
            joined[name] = None
        elif name in ("image_paths", "names"):
            joined[name] = tuple(p for v in values for p in v)
        else:
            joined[name] = np.concatenate(values)
    return Traversal(sharded.folder.name, joined["frame_index"], joined["segment_ids"],
                     ShardedRows(sharded, shards), joined["image_paths"], joined["positions"],
                     joined["timestamps"], joined["headings"], source=str(sharded.folder), names=joined["names"],
                     crs=shards[0].frames.crs)
