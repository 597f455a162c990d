"""Mapillary Street-level Sequences (MSLS) as Mapillary ships it, no reformatting:
``train_val/<city>/{database,query}/`` with ``images/<key>.jpg``, ``seq_info.csv`` (key, sequence, frame number),
``postprocessed.csv`` (key, UTM easting/northing, night, view direction...), ``raw.csv`` (key, lon, lat, ca,
captured_at, pano) and, where present, ``subtask_index.csv`` (a boolean column per subtask).

Each sequence is a segment, its frames in frame-number order (a gap in the numbers starts a new segment);
panoramas (``raw.csv``'s ``pano``) are left out, as the official evaluation does. Positions are UTM metres; the
MSLS evaluation radius is 25 m, seqvpr's default for positioned traversals.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError, SettingError

SEQUENCE_COLUMNS = ("sequence_key", "sequence_id")  # the code names it sequence_key, the README sequence_id
SUBTASKS = ("all", "s2w", "w2s", "o2n", "n2o", "d2n", "n2d")


def is_msls_side(folder: Path) -> bool:
    """A folder laid out as an MSLS database or query side."""
    return (folder / "seq_info.csv").is_file() and (folder / "images").is_dir()


def read_csv_rows(path: Path) -> list[dict[str, str]]:
    """The rows of a CSV with a header (pandas' unnamed index column kept as ``""``); one line on any fault."""
    from seqvpr.arrays import check_regular_file

    if path.exists():
        check_regular_file(path, "an MSLS CSV")
    if not path.is_file():
        raise SeqvprError(f"{path}: missing MSLS file")
    try:
        with open(path, newline="") as handle:
            reader = csv.DictReader(handle)
            rows = list(reader)
            header = reader.fieldnames or []
    except (csv.Error, UnicodeDecodeError) as error:
        raise SeqvprError(f"{path}: not a readable CSV ({error})") from None
    if not rows:
        raise SeqvprError(f"{path}: no rows")
    for number, row in enumerate(rows, start=2):  # line 1 is the header
        if None in row or any(value is None for value in row.values()):  # more or fewer fields than the header
            fields = len(header) + len(row.get(None) or []) - sum(value is None for value in row.values())
            raise SeqvprError(f"{path}: line {number} has {fields} fields, the header {len(header)} (a file cut "
                              "short, or a stray comma?)")
    return rows


def _column(rows: list[dict[str, str]], names: tuple[str, ...], path: Path) -> str:
    found = next((name for name in names if name in rows[0]), None)
    if found is None:
        raise SeqvprError(f"{path}: no column {' or '.join(names)} (columns: {', '.join(k for k in rows[0] if k)})")
    return found


def load_msls_side(folder: str | Path, subtask: str | None = None, keep_panoramas: bool = False) -> Traversal:
    """One MSLS side (``.../<city>/database`` or ``.../query``) as a traversal of its images, sequences as
    segments; ``subtask`` (``d2n``...) keeps the frames ``subtask_index.csv`` marks for it."""
    folder = Path(folder)
    info = read_csv_rows(folder / "seq_info.csv")
    sequence, key = _column(info, SEQUENCE_COLUMNS, folder / "seq_info.csv"), _column(info, ("key",), folder / "seq_info.csv")
    _column(info, ("frame_number",), folder / "seq_info.csv")
    keep = _kept_keys(folder, [row[key] for row in info], subtask, keep_panoramas)
    rows = sorted((r for r in info if r[key] in keep), key=lambda r: (r[sequence], int(float(r["frame_number"]))))
    if not rows:
        raise SeqvprError(f"{folder}: no frames left (subtask {subtask or 'all'}, panoramas left out)")
    positions = _positions(folder, [r[key] for r in rows])
    numbers = np.array([int(float(r["frame_number"])) for r in rows])
    names = [r[sequence] for r in rows]
    new = np.ones(len(rows), bool)
    new[1:] = (np.array(names[1:]) != np.array(names[:-1])) | (np.diff(numbers) != 1)
    paths = tuple((folder / "images" / f"{r[key]}.jpg").absolute() for r in rows)
    city = folder.absolute().parent.name
    return Traversal(f"msls-{city}-{folder.name}", np.arange(len(rows), dtype=np.int64),
                     (np.cumsum(new) - 1).astype(np.int64), None, paths, positions, source=str(folder))


def _kept_keys(folder: Path, keys: list[str], subtask: str | None, keep_panoramas: bool) -> set[str]:
    """The keys left after the subtask's selection and without panoramas."""
    kept = set(keys)
    if subtask is not None:
        if subtask not in SUBTASKS:
            raise SettingError(f"{{subtask}} {subtask!r} is not known (choose from: {', '.join(SUBTASKS)})")
        index = read_csv_rows(folder / "subtask_index.csv")
        _column(index, (subtask,), folder / "subtask_index.csv")
        marked = [row.get("key", keys[i] if i < len(keys) else "") for i, row in enumerate(index)
                  if row[subtask].strip().lower() in ("true", "1")]
        kept &= set(marked)
    raw = folder / "raw.csv"
    if not keep_panoramas and raw.is_file():
        rows = read_csv_rows(raw)
        if "pano" in rows[0]:
            kept -= {row["key"] for row in rows if row["pano"].strip().lower() in ("true", "1")}
    return kept


def _positions(folder: Path, keys: list[str]) -> np.ndarray:
    """UTM easting/northing [n, 2] of the keys from ``postprocessed.csv`` (``easting``/``northing`` columns)."""
    path = folder / "postprocessed.csv"
    rows = read_csv_rows(path)
    east, north = _column(rows, ("easting",), path), _column(rows, ("northing",), path)
    table = {row["key"]: (row[east], row[north]) for row in rows}
    missing = [k for k in keys if k not in table]
    if missing:
        raise SeqvprError(f"{path}: no position for image {missing[0]} ({len(missing)} missing)")
    try:
        return np.array([[float(table[k][0]), float(table[k][1])] for k in keys])
    except ValueError:
        raise SeqvprError(f"{path}: easting and northing must be numbers") from None
