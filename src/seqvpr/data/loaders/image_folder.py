"""A folder of images, optionally with a CSV of per-image positions, as one traversal.

Without a CSV the images of the folder (not its subfolders) are taken in natural file-name order
(``img2`` before ``img10``) and carry no positions: such a traversal is matched frame-aligned.

With a CSV the CSV decides which images are frames and in what order (row order). Its header names the columns
(case-insensitive, surrounding spaces ignored):

* the image: ``name``, ``image``, ``filename`` or ``file`` (the first of these present), relative to the folder;
* the position: ``easting`` and ``northing`` in metres (``crs`` ``local``), or else ``lat``/``lon``
  (``latitude``/``longitude``) in degrees, converted to UTM metres in the zone of the first row (so a route
  crossing a zone line stays in one planar frame; ``crs`` that zone, e.g. ``utm:56S``);
* optional ``timestamp`` (seconds), ``heading`` (degrees) and ``segment`` (integer id; a change of id between
  consecutive rows is a trajectory break).

Without a ``segment`` column, segments come from time and distance gaps when thresholds are given.
Hidden files (names starting with ``.``, such as macOS ``._img.jpg``) are never images.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from seqvpr.data.geo import LOCAL, latlon_to_utm
from seqvpr.data.traversal import Traversal, segments_from_gaps
from seqvpr.errors import SeqvprError

IMAGE_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".ppm", ".pgm"})
NAME_COLUMNS = ("name", "image", "filename", "file")
_DIGITS = re.compile(r"([0-9]+)")


def natural_key(text: str) -> tuple:
    """Sort key that orders digit runs by value (``img2`` < ``img10``), ties broken by the exact text."""
    parts = _DIGITS.split(text)
    # re.split with one group alternates text, digits, text, ...: odd positions are always digit runs.
    key = tuple(int(p) if i % 2 else p.lower() for i, p in enumerate(parts))
    return key, text


def is_image_name(name: str) -> bool:
    """True for a visible file name with one of the image extensions (any case)."""
    return not name.startswith(".") and Path(name).suffix.lower() in IMAGE_EXTENSIONS


def load_image_folder(
    folder: str | Path,
    positions_csv: str | Path | None = None,
    *,
    name: str | None = None,
    max_time_gap: float | None = None,
    max_distance_gap: float | None = None,
) -> Traversal:
    """Read a folder of images (natural order) or the frames a positions CSV lists, as one traversal."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SeqvprError(f"{folder}: image folder not found")
    label = name if name is not None else folder.absolute().name
    if positions_csv is None:
        return _folder_only(folder, label)
    rows = _read_positions_csv(Path(positions_csv), folder)
    return _traversal_from_rows(rows, folder, label, max_time_gap, max_distance_gap)


def _folder_only(folder: Path, label: str) -> Traversal:
    """All images directly in the folder, naturally sorted, one segment, no positions."""
    names = sorted((p.name for p in folder.iterdir() if p.is_file() and is_image_name(p.name)), key=natural_key)
    if not names:
        extensions = " ".join(sorted(IMAGE_EXTENSIONS))
        raise SeqvprError(f"{folder}: no images in the folder (looked for {extensions})")
    root = folder.absolute()
    n = len(names)
    return Traversal(
        name=label,
        frame_index=np.arange(n, dtype=np.int64),
        segment_ids=np.zeros(n, dtype=np.int64),
        image_paths=tuple(root / nm for nm in names),
        source=str(folder),
    )


@dataclass
class _CsvRows:
    """Columns parsed from a positions CSV, one entry per data row."""

    path: Path
    names: list[str]
    positions: np.ndarray
    crs: str
    timestamps: np.ndarray | None
    headings: np.ndarray | None
    segments: np.ndarray | None


@dataclass(frozen=True)
class _Columns:
    """Index of each recognised column in the header (None where absent)."""

    name: int
    first: int
    second: int
    latlon: bool
    timestamp: int | None
    heading: int | None
    segment: int | None


def _read_positions_csv(path: Path, folder: Path) -> _CsvRows:
    """Parse and validate every row of a positions CSV against the image folder."""
    from seqvpr.arrays import check_regular_file

    if path.exists():
        check_regular_file(path, "a positions CSV")
    if not path.is_file():
        raise SeqvprError(f"{path}: positions CSV not found")
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            return _parse_rows(path, csv.reader(handle), folder)
    except UnicodeDecodeError as exc:
        raise SeqvprError(f"{path}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    except csv.Error as exc:
        raise SeqvprError(f"{path}: malformed CSV ({_one_line(exc)})") from None


def _parse_rows(path: Path, reader, folder: Path) -> _CsvRows:
    """Walk the CSV rows, collecting names and numbers with row/column-specific errors."""
    header = _read_header(path, reader)
    cols = _find_columns(path, header)
    values = _RowValues()
    seen: dict[str, int] = {}
    for row in reader:
        if not any(cell.strip() for cell in row):
            continue  # blank lines carry no frame
        row_no = len(values.names) + 1
        where = f"{path}: row {row_no} (line {reader.line_num})"
        image = _checked_image(row, header, cols, where, seen, folder)
        seen[image] = row_no
        values.add(image, row, header, cols, where)
    if not values.names:
        raise SeqvprError(f"{path}: the CSV has a header but no rows")
    return _csv_rows(path, cols, values)


def _read_header(path: Path, reader) -> list[str]:
    """The header row; a one-line error when the CSV is empty or its first row is blank."""
    header = next(reader, None)
    if header is None or not any(cell.strip() for cell in header):
        raise SeqvprError(f"{path}: no header row (expected columns such as name,easting,northing)")
    return header


@dataclass
class _RowValues:
    """The image names and numbers read so far, one entry per data row (optional columns only when present)."""

    names: list[str] = field(default_factory=list)
    first: list[float] = field(default_factory=list)
    second: list[float] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)
    heads: list[float] = field(default_factory=list)
    segs: list[int] = field(default_factory=list)

    def add(self, image: str, row: list[str], header: list[str], cols: _Columns, where: str) -> None:
        """Append one row's image and numbers, in column order, failing on the first one that does not parse."""
        self.names.append(image)
        self.first.append(_number(row, cols.first, header, where))
        self.second.append(_number(row, cols.second, header, where))
        if cols.timestamp is not None:
            self.stamps.append(_number(row, cols.timestamp, header, where))
        if cols.heading is not None:
            self.heads.append(_number(row, cols.heading, header, where))
        if cols.segment is not None:
            self.segs.append(_integer(row, cols.segment, header, where))


def _checked_image(
    row: list[str], header: list[str], cols: _Columns, where: str, seen: dict[str, int], folder: Path
) -> str:
    """The row's image name, once the row is complete and the name is non-empty, new and a file in the folder."""
    if len(row) < len(header):
        raise SeqvprError(f"{where} has {len(row)} fields, the header has {len(header)}")
    image = row[cols.name].strip()
    if not image:
        raise SeqvprError(f"{where}, column {header[cols.name].strip()!r}: the image name is empty")
    if image in seen:
        raise SeqvprError(f"{where}: image {image!r} is listed twice (first at row {seen[image]})")
    if not (folder / image).is_file():
        raise SeqvprError(f"{where}: image {image!r} does not exist in {folder}")
    return image


def _csv_rows(path: Path, cols: _Columns, values: _RowValues) -> _CsvRows:
    """The parsed columns as arrays, latitude/longitude converted to UTM metres."""
    if cols.latlon:
        positions, crs = latlon_to_utm(np.asarray(values.first), np.asarray(values.second), path)
    else:
        positions, crs = np.column_stack([values.first, values.second]).astype(np.float64), LOCAL
    return _CsvRows(
        path=path,
        names=values.names,
        positions=positions,
        crs=crs,
        timestamps=np.asarray(values.stamps, dtype=np.float64) if cols.timestamp is not None else None,
        headings=np.asarray(values.heads, dtype=np.float64) if cols.heading is not None else None,
        segments=np.asarray(values.segs, dtype=np.int64) if cols.segment is not None else None,
    )


def _find_columns(path: Path, header: list[str]) -> _Columns:
    """Locate the name, position and optional columns in the header."""
    keys = [cell.strip().lower() for cell in header]
    for i, key in enumerate(keys):
        if key and key in keys[:i]:
            raise SeqvprError(f"{path}: column {header[i].strip()!r} appears twice in the header")
    index = {key: i for i, key in enumerate(keys)}
    name_col = next((index[c] for c in NAME_COLUMNS if c in index), None)
    if name_col is None:
        raise SeqvprError(
            f"{path}: no image name column (expected one of {', '.join(NAME_COLUMNS)}); header is {','.join(keys)}"
        )
    pair = _position_pair(path, index)
    return _Columns(
        name=name_col,
        first=pair[0],
        second=pair[1],
        latlon=pair[2],
        timestamp=index.get("timestamp"),
        heading=index.get("heading"),
        segment=index.get("segment"),
    )


def _position_pair(path: Path, index: dict[str, int]) -> tuple[int, int, bool]:
    """Columns of easting/northing (preferred) or latitude/longitude, and whether they are degrees."""
    candidates = (("easting", "northing", False), ("lat", "lon", True), ("latitude", "longitude", True))
    for a, b, latlon in candidates:
        if a in index and b in index:
            return index[a], index[b], latlon
    for a, b, _ in candidates:
        if (a in index) != (b in index):
            have, lack = (a, b) if a in index else (b, a)
            raise SeqvprError(f"{path}: column {have!r} has no partner column {lack!r}")
    raise SeqvprError(f"{path}: no position columns (expected easting,northing in metres or lat,lon in degrees)")


def _cell(row: list[str], col: int, header: list[str], where: str) -> str:
    """The stripped cell text, refusing an empty cell with the row and column named."""
    text = row[col].strip()
    if not text:
        raise SeqvprError(f"{where}, column {header[col].strip()!r}: the value is empty")
    return text


def _number(row: list[str], col: int, header: list[str], where: str) -> float:
    """A finite float from one cell, or an error naming the row and column."""
    text = _cell(row, col, header, where)
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise SeqvprError(f"{where}, column {header[col].strip()!r}: {text!r} is not a finite number")
    return value


def _integer(row: list[str], col: int, header: list[str], where: str) -> int:
    """An integer id from one cell (``3`` or ``3.0``), or an error naming the row and column."""
    text = _cell(row, col, header, where)
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or not value.is_integer():
        raise SeqvprError(f"{where}, column {header[col].strip()!r}: {text!r} is not an integer")
    return int(value)


def _traversal_from_rows(
    rows: _CsvRows, folder: Path, label: str, max_time_gap: float | None, max_distance_gap: float | None
) -> Traversal:
    """Assemble the traversal from parsed CSV rows, deriving segments when no segment column is given."""
    n = len(rows.names)
    if rows.segments is not None:
        segment_ids = rows.segments
    elif max_time_gap is not None or max_distance_gap is not None:
        if max_time_gap is not None and rows.timestamps is None:
            raise SeqvprError(f"{rows.path}: max_time_gap needs a timestamp column")
        segment_ids = segments_from_gaps(
            timestamps=rows.timestamps,
            max_time_gap=max_time_gap,
            positions=rows.positions,
            max_distance_gap=max_distance_gap,
        )
    else:
        segment_ids = np.zeros(n, dtype=np.int64)
    root = folder.absolute()
    return Traversal(
        name=label,
        frame_index=np.arange(n, dtype=np.int64),
        segment_ids=np.asarray(segment_ids, dtype=np.int64),
        image_paths=tuple(root / nm for nm in rows.names),
        positions=rows.positions,
        timestamps=rows.timestamps,
        headings=rows.headings,
        source=str(folder),
        crs=rows.crs,
    )


def _one_line(exc: BaseException) -> str:
    """An exception's message folded onto one line."""
    return " ".join(str(exc).split())
