"""Sharded maps: one map split into N shards, each a map of its own that one process memory-maps and matches.

    SHARDED/shards.json    format, version, the whole map's frame count, overlap, and per shard its folder, its
                           first row and the rows it owns ``[own_first, own_last)``
    SHARDED/shard-000/     a map (``files``) of rows ``[own_first - overlap, own_last + overlap)``, clipped to the
                           whole; its ``map.json`` says which shard it is

Shards own contiguous, equal runs of frames and overlap their neighbours by ``overlap`` frames on each side, so
every sequence window anchored at a frame a shard owns lies inside that shard while its span is at most
``overlap + 1`` frames: no window is cut at a shard edge. A shard's top-K over the frames it owns, merged with the
others' (distance, then the lower map row, as the kernel breaks ties), is the unsharded map's top-K. Under
``torchrun`` each rank matches its shards (``seqvpr.distributed``); without it one process matches them all.
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
from seqvpr.maps.files import OPTIONAL_COLUMNS, SavedMap, open_map, write_map_rows
from seqvpr.sequences.matching import TopK

if TYPE_CHECKING:
    from seqvpr.pipeline import MatchResult

SHARDS_FILE = "shards.json"
SHARDS_FORMAT = "seqvpr-sharded-map"
SHARDS_VERSION = 1
DEFAULT_OVERLAP = 63  # windows of up to 64 frames (any velocity) are never cut
SHARDABLE_FAMILIES = ("matching", "retrieval")  # per-window scores: a shard's top-K over its own frames is exact
WHOLE_MAP_SCORERS = ("seqslam-cone", "seqslam-hybrid")  # they use each frame's best match over the whole map


@dataclass(frozen=True)
class ShardRecord:
    """One shard: its folder (relative to the sharded map), its first row, and the rows it owns, in whole-map rows."""

    folder: str
    first: int
    own_first: int
    own_last: int


@dataclass(frozen=True)
class ShardMatch:
    """One shard's part of a match: its top-K in whole-map rows, and its top-1 pairs (query rows, whole-map rows)
    when the method makes its own (adaptive paths, winning trajectories)."""

    number: int
    topk: TopK
    pairs: tuple[np.ndarray, np.ndarray] | None


@dataclass(frozen=True)
class ShardedMap:
    """An opened sharded map's description: where its shards are and which rows each owns."""

    folder: Path
    count: int
    overlap: int
    shards: tuple[ShardRecord, ...]

    def open_shard(self, number: int) -> SavedMap:
        """Shard ``number`` as a map, memory-mapped (only its own files are touched)."""
        return open_map(self.folder / self.shards[number].folder)


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
                       "overlap": overlap, "source": str(source), "shards": [r.__dict__ for r in records]}
        (tmp / SHARDS_FILE).write_text(json.dumps(description, indent=2))
    return open_sharded_map(out)


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
        if values.get("format") != SHARDS_FORMAT or values.get("version") != SHARDS_VERSION:
            raise ValueError(f"format {values.get('format')!r} version {values.get('version')!r}")
        records = tuple(ShardRecord(**r) for r in values["shards"])
        sharded = ShardedMap(folder, int(values["count"]), int(values["overlap"]), records)
    except (ValueError, TypeError, KeyError, AttributeError) as error:
        raise SeqvprError(f"{path}: malformed sharded map description ({type(error).__name__}: {error})") from None
    owned = [(r.own_first, r.own_last) for r in records]
    if [a for a, _ in owned] != [0, *[b for _, b in owned[:-1]]] or owned[-1][1] != sharded.count:
        raise SeqvprError(f"{path}: its shards do not tile the map's {sharded.count} frames")
    return sharded


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
    shards = [sharded.open_shard(number) for number in range(len(sharded.shards))]
    parts: dict[str, list] = {"frame_index": [], "segment_ids": [], "image_paths": [],
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
        elif name == "image_paths":
            joined[name] = tuple(p for v in values for p in v)
        else:
            joined[name] = np.concatenate(values)
    return Traversal(sharded.folder.name, joined["frame_index"], joined["segment_ids"],
                     ShardedRows(sharded, shards), joined["image_paths"], joined["positions"],
                     joined["timestamps"], joined["headings"], source=str(sharded.folder))


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
    if all(p.pairs is not None for p in parts):
        owner = np.searchsorted([r.own_last for r in sharded.shards], np.maximum(top.indices[:, 0], 0), side="right")
        q_rows = np.stack([p.pairs[0] for p in parts])[owner, np.arange(len(owner))]
        r_rows = np.stack([p.pairs[1] for p in parts])[owner, np.arange(len(owner))]
        matched = (top.indices[:, 0] >= 0)[:, None]
        pairs = (np.where(matched, q_rows, -1), np.where(matched, r_rows, -1))
    return MatchResult(map_table(sharded), query, top, settings, correspondences=pairs)
