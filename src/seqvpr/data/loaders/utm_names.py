"""Folders whose image names carry UTM positions (VPR-datasets-downloader, VPR-methods-evaluation, gsv-cities).

A name reads ``@UTM_east@UTM_north@zone_number@zone_letter@lat@lon@pano_id@tile@heading@pitch@roll@height@
timestamp@note@.jpg``; after splitting on ``@`` field 1 is the easting, 2 the northing, 3 and 4 the zone, 9 the
heading and 13 the timestamp. Only fields 1 and 2 are required; when every name carries the same zone the
traversal's ``crs`` is that zone (``utm:32N``), else ``local``. The sequence layout of JIST/SeqVLAD (MSLS reformatted),
``@east@north@seq_id@frame_num@pano_id@city@timestamp@.jpg``, is recognised by having fewer than 13 fields and an
integer field 4: frames are then ordered by that frame number, and a jump in it starts a new segment (JIST only
builds windows over consecutive frame numbers).

A dataset root holds ``database/`` and ``queries/``; pick one with ``role`` ('reference' or 'query'); a role given
for a folder without that subfolder reads the folder itself. Images are gathered recursively and every relative
directory is a segment of its own (JIST and MSLS put one sequence per folder). Inside a directory, frames are ordered by timestamp when every image there has a numeric one, else by
natural name order. Headings and timestamps are filled only when every frame has a numeric value.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seqvpr.data.geo import LOCAL, utm_crs
from seqvpr.data.loaders.image_folder import is_image_name, natural_key
from seqvpr.data.traversal import Traversal, segments_from_gaps
from seqvpr.errors import SeqvprError

ROLE_FOLDERS = {"reference": "database", "query": "queries"}
_EAST, _NORTH, _ZONE, _FRAME_NUMBER, _HEADING, _TIMESTAMP = 1, 2, 3, 4, 9, 13


@dataclass(frozen=True)
class _Frame:
    """One image with the numbers parsed from its name."""

    relative_dir: str
    path: Path
    easting: float
    northing: float
    heading: float | None
    timestamp: float | None
    frame_number: int | None = None
    crs: str | None = None


def load_utm_named_folder(
    folder: str | Path,
    *,
    role: str | None = None,
    name: str | None = None,
    max_distance_gap: float | None = None,
) -> Traversal:
    """Read a folder of ``@east@north@...`` images (or a dataset root's database/ or queries/) as a traversal."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SeqvprError(f"{folder}: image folder not found")
    images_dir, default_name = _select_folder(folder, role)
    frames = _gather_frames(images_dir)
    if not frames:
        raise SeqvprError(f"{images_dir}: no images in the folder or its subfolders")
    frames = _ordered(frames)
    return _traversal(frames, images_dir, name if name is not None else default_name, max_distance_gap)


def is_utm_named_folder(folder: str | Path) -> bool:
    """True when the folder (or its database/ or queries/) holds an image named ``@<east>@<north>@...``."""
    folder = Path(folder)
    for candidate in (folder, folder / "database", folder / "queries"):
        if candidate.is_dir() and any(_utm_fields(Path(p).name) is not None for p in _image_files(candidate)):
            return True
    return False


def _select_folder(folder: Path, role: str | None) -> tuple[Path, str]:
    """The folder holding the images for ``role``, and a default traversal name."""
    if role is not None and role not in ROLE_FOLDERS:
        raise SeqvprError(f"{folder}: role must be 'reference' or 'query', got {role!r}")
    base = folder.absolute().name
    is_root = all((folder / sub).is_dir() for sub in ROLE_FOLDERS.values())
    if role is None:
        if is_root:
            raise SeqvprError(
                f"{folder}: a dataset root with database/ and queries/; choose one with role='reference' or 'query'"
            )
        return folder, base
    sub = ROLE_FOLDERS[role]
    if (folder / sub).is_dir():
        return folder / sub, f"{base}-{sub}"
    halves = [name for name in ROLE_FOLDERS.values() if (folder / name).is_dir()]
    if halves:  # a root with only the other half: reading it whole would give that half's images again
        raise SeqvprError(f"{folder}: a dataset root with {halves[0]}/ but no {sub}/ for the {role} side")
    return folder, base


def _image_files(root: Path):
    """Yield image paths under ``root`` recursively, following folder links once each (no cycles)."""
    seen: set[str] = set()
    for dirpath, dirnames, filenames in os.walk(root, followlinks=True):
        real = os.path.realpath(dirpath)
        if real in seen:
            dirnames[:] = []
            continue
        seen.add(real)
        for filename in filenames:
            if is_image_name(filename):
                yield os.path.join(dirpath, filename)


def _utm_fields(filename: str) -> list[str] | None:
    """The ``@``-separated fields of a UTM-style name, or None when it is not one."""
    if not filename.startswith("@"):
        return None
    fields = Path(filename).stem.split("@")  # the standard name ends "@.jpg"; "@e@n.jpg" is accepted too
    if len(fields) < 3 or _as_float(fields[_EAST]) is None or _as_float(fields[_NORTH]) is None:
        return None
    return fields


def _as_float(text: str) -> float | None:
    """A finite float, or None when the text is not one."""
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def _optional_field(fields: list[str], index: int) -> float | None:
    """A numeric optional field, or None when absent or not a number."""
    return _as_float(fields[index]) if index < len(fields) else None


def _gather_frames(images_dir: Path) -> list[_Frame]:
    """Parse every image under the folder, failing on the first whose name has no numeric UTM fields."""
    frames: list[_Frame] = []
    root = images_dir.absolute()
    for raw in _image_files(root):
        path = Path(raw)
        fields = _utm_fields(path.name)
        if fields is None:
            raise SeqvprError(
                f"{path}: file name is not @<UTM east>@<UTM north>@...: the first two '@' fields must be numbers"
            )
        frames.append(
            _Frame(
                relative_dir=path.parent.relative_to(root).as_posix(),
                path=path,
                easting=float(fields[_EAST]),
                northing=float(fields[_NORTH]),
                heading=_optional_field(fields, _HEADING),
                timestamp=_optional_field(fields, _TIMESTAMP),
                frame_number=_sequence_frame_number(fields),
                crs=_zone(fields),
            )
        )
    return frames


def _zone(fields: list[str]) -> str | None:
    """The ``crs`` of the name's zone number and letter (fields 3 and 4, e.g. ``32@T``: ``utm:32N``), or None when
    the name carries no valid zone (the short sequence layout has other fields there)."""
    if len(fields) < _TIMESTAMP or not fields[_ZONE].isdigit() or not 1 <= int(fields[_ZONE]) <= 60:
        return None
    letter = fields[_ZONE + 1].strip().upper()
    if len(letter) != 1 or letter not in "CDEFGHJKLMNPQRSTUVWX":
        return None
    return utm_crs(int(fields[_ZONE]), letter >= "N")


def _sequence_frame_number(fields: list[str]) -> int | None:
    """Field 4 of the short JIST/SeqVLAD layout when it is an integer, else None."""
    if len(fields) >= _TIMESTAMP or len(fields) <= _FRAME_NUMBER or not fields[_FRAME_NUMBER].isdigit():
        return None
    return int(fields[_FRAME_NUMBER])


def _ordered(frames: list[_Frame]) -> list[_Frame]:
    """Frames grouped by relative directory; inside each, by timestamp when all have one, else by name."""
    groups: dict[str, list[_Frame]] = {}
    for frame in frames:
        groups.setdefault(frame.relative_dir, []).append(frame)
    ordered: list[_Frame] = []
    for directory in sorted(groups, key=natural_key):
        group = groups[directory]
        if all(f.frame_number is not None for f in group):
            group.sort(key=lambda f: (f.frame_number, natural_key(f.path.name)))
        elif all(f.timestamp is not None for f in group):
            group.sort(key=lambda f: (f.timestamp, natural_key(f.path.name)))
        else:
            group.sort(key=lambda f: natural_key(f.path.name))
        ordered.extend(group)
    return ordered


def _traversal(frames: list[_Frame], images_dir: Path, label: str, max_distance_gap: float | None) -> Traversal:
    """Build the traversal: one segment per directory, further split at distance gaps when asked."""
    n = len(frames)
    positions = np.array([[f.easting, f.northing] for f in frames], dtype=np.float64)
    new_dir = np.zeros(n, dtype=bool)
    new_dir[1:] = [a.relative_dir != b.relative_dir for a, b in zip(frames[:-1], frames[1:])]
    breaks = new_dir.copy()
    numbers = [f.frame_number for f in frames]
    if n > 1 and None not in numbers:
        breaks[1:] |= np.diff(np.asarray(numbers)) != 1
    if max_distance_gap is not None:
        gap_ids = segments_from_gaps(positions=positions, max_distance_gap=max_distance_gap)
        breaks[1:] |= np.diff(gap_ids) != 0
    headings = [f.heading for f in frames]
    stamps = [f.timestamp for f in frames]
    return Traversal(
        name=label,
        frame_index=np.arange(n, dtype=np.int64),
        segment_ids=np.cumsum(breaks).astype(np.int64),
        image_paths=tuple(f.path for f in frames),
        positions=positions,
        headings=None if None in headings else np.asarray(headings, dtype=np.float64),
        timestamps=None if None in stamps else np.asarray(stamps, dtype=np.float64),
        source=str(images_dir),
        crs=_one_zone(frames),
    )


def _one_zone(frames: list[_Frame]) -> str:
    """The frames' UTM zone when every name carries the same one, else ``local`` (easting/northing of no one zone)."""
    zones = {f.crs for f in frames}
    return zones.pop() if len(zones) == 1 and None not in zones else LOCAL
