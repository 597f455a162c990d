"""``seqvpr map check``: the full verification of a saved map, reading everything once. Opening a map checks only
what is cheap (its manifest, and each file's digest where the file was seen before); this reads every file again,
checks every row is finite (and of unit length in a normalised map), and that the index, or each shard, is the
one its manifest records."""

from __future__ import annotations

from pathlib import Path

from seqvpr.identity import check_digest
from seqvpr.maps.files import (
    DESCRIPTORS_FILE, INFO_FILE, check_rows, is_sharded_map, open_map, open_sharded_map, read_map_info,
    verify_map_files,
)
from seqvpr.maps.index import check_index_record, open_frame_index


def check_map(folder: str | Path) -> list[str]:
    """Verify a map (or a sharded map, shard by shard) in full; what was checked, a line each. The first fault is
    one SeqvprError naming the file."""
    folder = Path(folder)
    if is_sharded_map(folder):
        return check_sharded_map(folder)
    info = read_map_info(folder)
    verify_map_files(folder, info, fresh=True)
    saved = open_map(folder)
    unit = info.normalized and info.dtype in ("float32", "float16")  # coded rows are unit only to within a code
    check_rows(saved.descriptors, unit, str(folder / DESCRIPTORS_FILE))
    lines = [f"{folder}: {info.count} frames of {info.dim}-D {info.dtype}, identity {info.identity or '-'}",
             f"  files: {len(info.files or {})} match the digests map.json records"
             if info.files is not None else "  files: not recorded (a map written before identities)",
             f"  rows: all finite{', of unit length' if unit else ''}"]
    if info.index:
        lines.append(_check_index(saved))
    return lines


def _check_index(saved) -> str:
    """The index's files read again against their digests, and the index opened against the map's rows."""
    record = saved.info.index
    owner = str(Path(saved.folder) / INFO_FILE)
    if "digest" in record:
        check_digest(Path(saved.folder) / record["file"], record["digest"], owner, fresh=True)
    if record.get("rows_file"):
        check_digest(Path(saved.folder) / record["rows_file"], record["rows_digest"], owner, fresh=True)
    check_index_record(saved, record, Path(saved.folder) / record["file"])
    index = open_frame_index(saved)
    return f"  index: {record['spec']} over {record['over']}, {index.ntotal} vectors, built over these rows"


def check_sharded_map(folder: Path) -> list[str]:
    """Every shard verified in full, and each the shard ``shards.json`` records in its place."""
    sharded = open_sharded_map(folder)
    lines = []
    for number, record in enumerate(sharded.shards):
        lines += check_map(folder / record.folder)
        sharded.open_shard(number)
    lines.append(f"{folder}: {sharded.count} frames in {len(sharded.shards)} shards, each the one shards.json "
                 "records")
    return lines

