"""Maps that grow: ``seqvpr map add MAP SOURCE...`` appends traversals to a saved map as one new session, described
as the map's own frames were (its descriptor settings and models; another is refused), without touching what the
map holds. The new rows go into a file of their own (``seqvpr.maps.parts``): the map's row files are hard-linked
into the new version, so adding N frames writes and digests N rows, never the map again. The frame table (segments,
source frames, columns, names) is written anew (a few bytes a frame). A frame index over frames is extended by
the new rows; an index over windows is rebuilt over the grown map (its vectors pool windows), with its spec, seed
and model.

The new version is built in a temporary folder beside the map and swapped in by one atomic exchange, under the
map's lock: a failed or killed ``map add`` leaves the map as it was, byte for byte.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr import checks
from seqvpr.arrays import load_npy
from seqvpr.errors import SeqvprError
from seqvpr.io import commit_folder, output_lock, temporary_folder
from seqvpr.maps.codes import SIDE_FILES, coder_of, parse_storage, row_chunks
from seqvpr.maps.files import (
    DESCRIPTORS_FILE, GROWN_VERSION, INFO_FILE, MapInfo, SavedMap, check_names, check_rows,
    is_sharded_map, open_map, write_frame_table,
)
from seqvpr.maps.parts import PART_FILE, sessions_of
from seqvpr.models.registry import TrainedModel
from seqvpr.progress import ProgressFactory


def add_to_map(map_folder: str | Path, sources: Sequence[str], session: str | None = None,
               models: Mapping[str, TrainedModel] | None = None, *, device: str = "cpu",
               progress: ProgressFactory | None = None, frames: str | None = None, **extraction: Any) -> SavedMap:
    """``sources`` appended to the map at ``map_folder`` as the session ``session`` (default: ``session-N``), each
    its own segments; the grown map, committed as one."""
    from seqvpr.maps.build import checked_sources

    folder = checks.a_path(map_folder, "map")
    if is_sharded_map(folder):
        raise SeqvprError(f"{folder}: a sharded map takes no map add; grow the whole map, then shard it again "
                          "(seqvpr map shard)")
    from seqvpr.maps.thumbnails import has_thumbnails

    if has_thumbnails(folder):
        raise SeqvprError(f"{folder}: a map that keeps thumbnails takes no map add yet (its new frames would have "
                          "none); build it again with every source and --thumbnails")
    sources = checked_sources(sources, folder, models)
    with output_lock(folder):
        saved = open_map(folder)
        check_new_sources(saved, sources)
        check_models(saved, models or {})
        whole, added = described_sources(saved, sources, models or {}, device, progress, frames, extraction)
        name = session or f"session-{len(sessions_of(saved.info))}"
        if any(s["name"] == name for s in sessions_of(saved.info)):
            raise SeqvprError(f"{folder}: already has a session named {name!r}")
        write_grown(saved, whole, added, name)
    return open_map(folder)


def check_new_sources(saved: SavedMap, sources: Sequence[str]) -> None:
    """No source the map already holds (the same path, resolved), nor one given twice."""
    held = {str(Path(s.source).resolve()): s.source for s in saved.info.sources}
    seen: set[str] = set()
    for source in sources:
        key = str(Path(source).resolve())
        if key in held or key in seen:
            raise SeqvprError(f"{source}: already in the map {saved.folder} (as {held.get(key, source)}); a map "
                              "holds each source once")
        seen.add(key)


def check_models(saved: SavedMap, models: Mapping[str, TrainedModel]) -> None:
    """The models given are the ones the map's frames went through (kind, weights' sha256), or none for none."""
    from seqvpr.maps.build import model_records

    given, recorded = model_records(models), saved.info.model
    if (given or None) != (recorded or None):
        def named(record):
            return ", ".join(f"{kind} {r.get('sha256', '')[:12]}" for kind, r in (record or {}).items()) or "none"
        raise SeqvprError(f"{saved.folder}: built through models {named(recorded)}; map add got {named(given)} "
                          "(give the map's own with --model)")


def described_sources(saved: SavedMap, sources: Sequence[str], models: Mapping[str, TrainedModel], device: str,
                      progress, frames: str | None, extraction: dict[str, Any]):
    """The new sources described as the map's frames were, and the map's frames with them laid end to end (each
    source its own segments; the columns every part has); one line if they do not fit the map."""
    from seqvpr.data.traversal import Traversal
    from seqvpr.maps.build import FrameDescription, concatenate_traversals, described_map

    description = FrameDescription.from_json({**saved.info.description, "descriptor": _descriptor_of(saved)})
    check_described_alike(saved, sources, frames)
    added, info = described_map(sources, saved.folder.name, description, dict(models), dtype=saved.info.dtype,
                                normalize=saved.info.normalized, device=device, progress=progress, frames=frames,
                                **extraction)
    if info.dim != saved.info.dim:
        raise SeqvprError(f"{sources[0]}: {info.dim}-D frames; the map {saved.folder} holds {saved.info.dim}-D ones "
                          "(described otherwise)")
    old = Traversal(saved.frames.name, saved.frames.frame_index, saved.frames.segment_ids, saved.descriptors,
                    saved.frames.image_paths, saved.frames.positions, saved.frames.timestamps, saved.frames.headings,
                    names=saved.frames.names, crs=saved.frames.crs)
    whole = concatenate_traversals([old, added], saved.folder.name)
    return whole, (added, info)


def _descriptor_of(saved: SavedMap) -> str:
    """The descriptor ``FrameDescription`` names for the map's images (a model kind or ``file`` describe nothing)."""
    recorded = saved.info.description.get("descriptor", "patchnorm")
    return "patchnorm" if recorded in ("file", "jist", "cosplace") else recorded


def check_described_alike(saved: SavedMap, sources: Sequence[str], frames: str | None) -> None:
    """Descriptor files for a map of descriptor files, images for a map of images: a map never mixes them."""
    from seqvpr.data.sources import load_traversal

    of_files = saved.info.description.get("descriptor") == "file"
    for source in sources:
        has_rows = load_traversal(source, "reference").descriptors is not None
        if has_rows != of_files:
            raise SeqvprError(f"{source}: {'descriptors' if has_rows else 'images'}, but the map {saved.folder} "
                              f"holds {'descriptor files' if of_files else 'described images'}")


def write_grown(saved: SavedMap, whole, added, session: str) -> None:
    """The grown map written beside the old one (its row files linked, the new rows a new part) and swapped in."""
    from seqvpr.maps.index import link_map_files
    from seqvpr.maps.keep import keep_users_files

    new_frames, new_info = added
    check_rows(new_frames.descriptors, saved.info.normalized, f"{new_frames.source}: the new rows")
    check_names(whole.image_names(), saved.folder)
    tmp = temporary_folder(saved.folder)
    try:
        kept = {name: digest for name, digest in link_map_files(saved, tmp).items() if _row_file(name)}
        for name in [p.name for p in tmp.iterdir() if not _row_file(p.name)]:
            (tmp / name).unlink()  # the frame table is written anew below
        part = PART_FILE.format(len(parts_of(saved.info)))
        _write_part(tmp / part, new_frames.descriptors, saved)
        info = grown_info(saved.info, whole, new_info, part, session)
        write_frame_table(whole, info, whole.image_names(), lambda name: open(tmp / name, "wb"))
        _seal(tmp, replace(info, index=_grown_index(saved, tmp, new_frames.descriptors, whole)), kept)
        open_map(tmp)  # what a reader will do, before the map replaces anything
        keep_users_files(saved.folder, tmp)
        commit_folder(tmp, saved.folder, INFO_FILE)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _row_file(name: str) -> bool:
    """The files a grown map keeps as they are: its row parts and the coder's side file."""
    return name == DESCRIPTORS_FILE or (name.startswith("descriptors-") and name.endswith(".npy")) or \
        name in SIDE_FILES.values()


def parts_of(info: MapInfo) -> list[tuple[str, int]]:
    return [tuple(p) for p in info.parts] if info.parts else [(DESCRIPTORS_FILE, info.count)]


def _write_part(path: Path, rows, saved: SavedMap) -> None:
    """The new rows stored as the map stores its own (by its coder; sq8 refuses rows outside its range)."""
    from numpy.lib import format as npy

    from seqvpr.maps.codes import stored_shape

    kind, _ = parse_storage(saved.info.dtype, saved.info.dim)
    side = None if kind in ("float32", "float16") else load_npy(saved.folder / SIDE_FILES[kind])
    coder = coder_of(saved.info.dtype, side)
    shape, dtype = stored_shape(saved.info.dtype, len(rows), saved.info.dim)
    with open(path, "wb") as handle:
        npy.write_array_header_1_0(handle, {"descr": npy.dtype_to_descr(np.dtype(dtype)), "fortran_order": False,
                                            "shape": shape})
        for start, block in row_chunks(rows):
            if kind == "sq8":
                _check_in_range(block, side, start, saved)
            handle.write(np.ascontiguousarray(coder(block), dtype=dtype).tobytes())


def _check_in_range(block: np.ndarray, side: np.ndarray, start: int, saved: SavedMap) -> None:
    """sq8 codes cover the range the map was fitted to; a row outside it would be clipped: refused."""
    low, high = side[0], side[0] + 255.0 * side[1]
    outside = (block < low - 1e-6 * np.abs(low)) | (block > high + 1e-6 * np.abs(high))
    if outside.any():
        row = start + int(np.argmax(outside.any(axis=1)))
        raise SeqvprError(f"{saved.folder}: new frame {row} lies outside the sq8 map's value range in "
                          f"{int(outside.any(axis=0).sum())} dimension(s); rebuild the map with every source "
                          "(seqvpr map build) or store it as float16")


def grown_info(info: MapInfo, whole, new_info: MapInfo, part: str, session: str) -> MapInfo:
    """``map.json`` of the grown map: the count, the sources (the new ones after the old), the parts, the sessions
    and the columns and positions' system the whole has."""
    sessions = sessions_of(info)
    offset = info.count
    sources = (*info.sources, *(replace(s, first=s.first + offset) for s in new_info.sources))
    sessions.append({"name": session, "first": offset, "frames": new_info.count,
                     "sources": list(range(len(info.sources), len(sources))),
                     "added": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
    columns = tuple(c for c in info.columns if getattr(whole, c) is not None)
    return replace(info, count=len(whole), sources=sources, parts=tuple([*parts_of(info), (part, new_info.count)]),
                   sessions=tuple(sessions), columns=columns, crs=whole.crs if "positions" in columns else None,
                   version=GROWN_VERSION)


def _grown_index(saved: SavedMap, tmp: Path, rows, whole) -> dict[str, Any] | None:
    """The map's index for the grown map, written in ``tmp``; its record (None without an index). A frame index is
    extended by the new rows; an index over windows is rebuilt (a window at the old map's end now reaches into the
    new rows only where a segment continues, but its vectors and their row list are made again as one)."""
    record = saved.info.index
    if not record:
        return None
    if record.get("over") != "frames":
        return _rebuilt_window_index(saved, tmp, whole, record)
    return _extended_index(saved, tmp, rows, record)


def _rebuilt_window_index(saved: SavedMap, tmp: Path, whole, record: dict[str, Any]) -> dict[str, Any]:
    """The index over windows built again over the grown map's frames, with its spec, seed and model."""
    import faiss

    from seqvpr.identity import seal_files
    from seqvpr.maps.index import INDEX_FILE, ROWS_FILE, build_frame_index, index_model, parse_index_spec
    from seqvpr.maps.index import window_vectors

    started = time.perf_counter()
    method, length = record["over"].split(":")
    described = window_vectors(whole.descriptors, whole.segment_ids, int(length), method, index_model(saved))
    index = build_frame_index(described.vectors, parse_index_spec(record["spec"]), int(record.get("seed", 0)))
    faiss.write_index(index, str(tmp / INDEX_FILE))
    np.save(tmp / ROWS_FILE, described.rows)
    digests = seal_files(tmp, [INDEX_FILE, ROWS_FILE])
    return {**record, "ntotal": int(index.ntotal), "map": None, "digest": digests[INDEX_FILE],
            "rows_digest": digests[ROWS_FILE], "build_seconds": round(time.perf_counter() - started, 2)}


def _extended_index(saved: SavedMap, tmp: Path, rows, record: dict[str, Any]) -> dict[str, Any]:
    """The map's frame index with the new rows added (faiss ``add``: the ids go on from the map's count)."""
    import faiss

    from seqvpr.identity import seal_files
    from seqvpr.maps.index import ADD_BLOCK, INDEX_FILE

    index = faiss.read_index(str(saved.folder / INDEX_FILE))
    for start, block in row_chunks(rows, ADD_BLOCK):
        index.add(np.ascontiguousarray(block, dtype=np.float32))
    faiss.write_index(index, str(tmp / INDEX_FILE))
    return {**record, "ntotal": int(index.ntotal), "map": None, "digest": seal_files(tmp, [INDEX_FILE])[INDEX_FILE]}


def _seal(tmp: Path, info: MapInfo, kept: dict[str, str]) -> MapInfo:
    """``map.json`` last: the kept files' digests as recorded, the new files' read once, the identity over all."""
    from seqvpr.identity import combined_identity, seal_files
    from seqvpr.maps.index import INDEX_FILE, ROWS_FILE

    new = [p.name for p in tmp.iterdir() if p.name not in kept and p.name not in (INFO_FILE, INDEX_FILE, ROWS_FILE)]
    files = {**kept, **seal_files(tmp, sorted(new))}
    sealed = replace(info, files=files, identity=combined_identity(files))
    if sealed.index:
        sealed = replace(sealed, index={**sealed.index, "map": sealed.identity})
    (tmp / INFO_FILE).write_text(json.dumps(sealed.to_json(), indent=2))
    return sealed
