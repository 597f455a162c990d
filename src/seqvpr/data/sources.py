"""Resolve what a user names on the command line (a file, a folder, a description file) to a Traversal.

- ``.npy`` / ``.npz`` / ``.mat`` (optionally ``FILE:VAR``): descriptor rows, frame-aligned. An ``.npz`` with a
  ``descriptors`` array is a whole traversal file (optional ``positions`` [N,2] and their ``crs``, ``timestamps``,
  ``segments``).
- ``.db`` or a ``.mat`` holding ``dbStruct``: the reference (database) or query side, by role.
- a folder of ``@east@north@...@.jpg`` images (or with ``database/`` and ``queries/``): UTM from the names.
- a folder of images, with ``positions.csv`` inside when present.
- ``.toml``: a dataset description with ``[reference]``, ``[query]`` and ``[ground_truth]`` tables.
"""

from __future__ import annotations

import zipfile
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal


import numpy as np
import scipy.io

from seqvpr.arrays import check_regular_file, open_npz
from seqvpr.data.ground_truth import Radius, parse_radius
from seqvpr.data.loaders.descriptor_files import DESCRIPTOR_SUFFIXES, load_descriptor_array, split_variable
from seqvpr.data.traversal import Traversal
from seqvpr import checks
from seqvpr.errors import SeqvprError, reading

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

Role = Literal["reference", "query"]


@dataclass(frozen=True)
class GroundTruthSpec:
    """Ground truth named by a description file: a radius, or a file of positives."""

    radius: Radius | None = None
    file: Path | None = None


def load_traversal(source: str | Path, role: Role) -> Traversal:
    """The traversal a command-line source names, for the given role; whatever a malformed file raises while it is
    read becomes one error naming the source."""
    from typing import get_args

    checks.a_path(source, "source")
    checks.text(role, "role", get_args(Role))
    with reading(source, f"a {role} traversal"):
        traversal = _load_traversal(str(source), role)
    return traversal


def _load_traversal(text: str, role: Role) -> Traversal:
    from seqvpr.data.loaders.rosbag import load_rosbag, parse_bag_source

    bag = parse_bag_source(text)
    if bag is not None:
        return load_rosbag(*bag)
    path, _ = split_variable(text)
    if path.suffix.lower() == ".toml":
        return _traversal_from_description(path, role)
    if path.is_dir():
        return _traversal_from_folder(path, role)
    if not path.exists():
        raise SeqvprError(f"{path}: no such file or folder")
    check_regular_file(path, f"a {role} traversal")
    suffix = path.suffix.lower()
    if suffix == ".db" or (suffix == ".mat" and _holds_dbstruct(path)):
        return _dbstruct_side(path, role)
    if suffix == ".npz" and _is_traversal_npz(path):
        return load_traversal_npz(path)
    if suffix in DESCRIPTOR_SUFFIXES:
        name = f"{path.parent.name}/{path.stem}" if path.parent.name else path.stem
        return Traversal.from_descriptors(load_descriptor_array(text), name=name, source=text)
    raise SeqvprError(f"{path}: not a descriptor file (.npy/.npz/.mat), dbStruct (.db), folder or description (.toml)")


def load_pair(reference: str | Path, query: str | Path, frames: str | None = None) -> tuple[Traversal, Traversal]:
    """The reference and query traversals two sources name, both cut to the frames ``START:STOP`` when given."""
    from seqvpr.data.traversal import slice_frame_range

    ref, qry = load_traversal(reference, "reference"), load_traversal(query, "query")
    return slice_frame_range(ref, frames), slice_frame_range(qry, frames)


def ground_truth_spec(source: str | Path) -> GroundTruthSpec | None:
    """The ``[ground_truth]`` table of a description file, if the source is one and has it."""
    path, _ = split_variable(str(source))
    if path.suffix.lower() != ".toml" or not path.exists():
        return None
    values = _read_toml(path)
    table = values.get("ground_truth")
    if table is None:
        return _dbstruct_radius(path, values)
    for key in ("radius", "file"):
        if key in table and not isinstance(table[key], str):
            raise SeqvprError(f"{path}: [ground_truth] {key} must be in quotes (e.g. \"25m\", \"gt.mat\"), "
                              f"got {table[key]!r}")
    radius = parse_radius(table["radius"]) if "radius" in table else None
    file = (path.parent / table["file"]) if "file" in table else None
    return GroundTruthSpec(radius, file)


def _dbstruct_radius(path: Path, values: dict) -> GroundTruthSpec | None:
    """A description without [ground_truth] whose reference names a dbStruct: its ``posDistThr`` (metres, or frames
    for a frame-aligned struct) is the radius, as the seqNet and SeqMatchNet code evaluates."""
    db_file = values.get("reference", {}).get("dbstruct")
    if db_file is None:
        return None
    from seqvpr.data.loaders.dbstruct import load_dbstruct

    db = load_dbstruct(path.parent / db_file)
    return GroundTruthSpec(parse_radius(f"{db.pos_dist_thr:g}{'f' if db.frame_aligned else 'm'}"), None)


def _traversal_from_folder(folder: Path, role: Role) -> Traversal:
    from seqvpr.data.loaders.msls import is_msls_side, load_msls_side
    from seqvpr.data.loaders.utm_names import is_utm_named_folder, load_utm_named_folder

    if is_msls_side(folder):
        return load_msls_side(folder)
    if is_utm_named_folder(folder):
        return load_utm_named_folder(folder, role=role)
    from seqvpr.data.loaders.image_folder import load_image_folder

    csv = folder / "positions.csv"
    return load_image_folder(folder, csv if csv.exists() else None)


def _holds_dbstruct(path: Path) -> bool:
    """A MAT file whose variables include ``dbStruct``. A file scipy cannot list (its reader fails in these ways on
    bytes that are no MAT file) is left to the descriptor loader, whose error names the file and the reason."""
    from scipy.io.matlab import MatReadError

    try:
        return any(name == "dbStruct" for name, _, _ in scipy.io.whosmat(path))
    except (MatReadError, ValueError, OSError, IndexError, EOFError):
        return False


def _dbstruct_side(path: Path, role: Role) -> Traversal:
    from seqvpr.data.loaders.dbstruct import load_dbstruct

    db = load_dbstruct(path)
    return db.reference if role == "reference" else db.query


def _is_traversal_npz(path: Path) -> bool:
    """An archive holding ``descriptors`` (a traversal file). One that is no zip is left to the descriptor loader,
    whose error names it; an unsafe member (a pickle, a lying size) is ``open_npz``'s one-line error, raised here."""
    try:
        with open_npz(path) as archive:
            return "descriptors" in archive.files
    except (zipfile.BadZipFile, OSError, ValueError):
        return False


def load_traversal_npz(path: Path) -> Traversal:
    """A traversal file: ``descriptors`` plus optional ``positions`` (in ``crs``, else ``local``), ``timestamps``,
    ``segments``."""
    with open_npz(path) as archive:
        arrays = {name: archive[name] for name in archive.files}
    descriptors = load_descriptor_array(f"{path}:descriptors")
    traversal = Traversal.from_descriptors(
        descriptors,
        name=path.stem,
        positions=arrays.get("positions"),
        segment_ids=_whole(arrays.get("segments")),
        timestamps=arrays.get("timestamps"),
        source=str(path),
    )
    if "crs" in arrays:  # the coordinate system of the positions (seqvpr.data.geo), when the writer knew it
        traversal = replace(traversal, crs=str(arrays["crs"]))
    if "frame_index" in arrays:  # source frame numbers survive extraction with skipped images
        frame_index = np.asarray(arrays["frame_index"], dtype=np.int64)
        if frame_index.shape != (len(descriptors),) or len(np.unique(frame_index)) != len(frame_index) \
                or (np.asarray(arrays["frame_index"]) != frame_index).any():
            raise SeqvprError(f"{path}: frame_index must be one different whole number per descriptor row")
        traversal = replace(traversal, frame_index=frame_index)
    return traversal


def _whole(values: np.ndarray | None) -> np.ndarray | None:
    """Segment ids stored as whole floats (some tools write every array as float) as integers; else as they are."""
    if values is None or values.dtype.kind != "f" or not np.isfinite(values).all() or (values != np.round(values)).any():
        return values
    return values.astype(np.int64)


def save_traversal_npz(path: Path, traversal: Traversal) -> None:
    """Write a traversal file readable by ``load_traversal_npz`` (atomically)."""
    from seqvpr.io import atomic_write

    arrays = {"descriptors": traversal.descriptors, "segments": traversal.segment_ids,
              "frame_index": traversal.frame_index}
    if traversal.positions is not None:
        arrays["positions"] = traversal.positions
        arrays["crs"] = np.array(traversal.crs or "local")
    if traversal.timestamps is not None:
        arrays["timestamps"] = traversal.timestamps
    with atomic_write(path, "wb") as handle:
        np.savez(handle, **arrays)


#: what a dataset description may hold: its tables, and the keys of each
DESCRIPTION_KEYS = {
    "reference": ("descriptors", "images", "positions", "dbstruct", "seq_bounds", "name"),
    "query": ("descriptors", "images", "positions", "dbstruct", "seq_bounds", "name"),
    "ground_truth": ("radius", "file"),
}


def _read_toml(path: Path) -> dict:
    if not path.exists():
        raise SeqvprError(f"{path}: description file not found")
    check_regular_file(path, "a dataset description")
    try:
        values = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise SeqvprError(f"{path}: not valid TOML ({error})") from None
    _check_description_keys(path, values)
    return values


def _check_description_keys(path: Path, values: dict) -> None:
    """Every table and key known: a misspelt one (``raduis``) is an error naming it, never silently ignored."""
    import difflib

    for table, content in values.items():
        allowed = DESCRIPTION_KEYS.get(table)
        if allowed is None or not isinstance(content, dict):
            raise SeqvprError(f"{path}: unknown table [{table}] (known: {', '.join(DESCRIPTION_KEYS)})")
        for key in content:
            if key not in allowed:
                close = difflib.get_close_matches(key, allowed, n=1)
                hint = f"; did you mean {close[0]}?" if close else f" (known: {', '.join(allowed)})"
                raise SeqvprError(f"{path}: unknown key {key!r} in [{table}]{hint}")


def _traversal_from_description(path: Path, role: Role) -> Traversal:
    """The ``[reference]`` or ``[query]`` table: ``descriptors`` (with ``dbstruct``: its positions), ``images``
    (+ ``positions``) or ``dbstruct``; ``seq_bounds`` a seqBounds file whose sequences become the segments."""
    table = _read_toml(path).get(role)
    if table is None:
        raise SeqvprError(f"{path}: no [{role}] table")
    _check_file_values(path, role, table)
    base = path.parent
    if "descriptors" in table:
        traversal = load_traversal(str(base / table["descriptors"]), role)
        if "dbstruct" in table:
            traversal = _with_dbstruct_positions(traversal, base / table["dbstruct"], role)
    elif "dbstruct" in table:
        traversal = _dbstruct_side(base / table["dbstruct"], role)
    elif "images" in table:
        from seqvpr.data.loaders.image_folder import load_image_folder

        positions = base / table["positions"] if "positions" in table else None
        traversal = load_image_folder(base / table["images"], positions)
    else:
        raise SeqvprError(f"{path}: [{role}] needs one of descriptors, images or dbstruct")
    if "seq_bounds" in table:
        from seqvpr.data.loaders.seq_bounds import load_seq_bounds

        traversal = replace(traversal, segment_ids=load_seq_bounds(base / table["seq_bounds"], len(traversal)))
    if "name" in table:
        traversal = replace(traversal, name=str(table["name"]))
    return traversal


def _check_file_values(path: Path, role: Role, table: dict) -> None:
    """Every file a side names is a path text, and not another description (which could name this one)."""
    for key in ("descriptors", "dbstruct", "images", "positions", "seq_bounds"):
        value = table.get(key)
        if value is None:
            continue
        if not isinstance(value, str) or not value:
            raise SeqvprError(f"{path}: [{role}] {key} must be a file name in quotes, got {value!r}")
        if value.lower().endswith(".toml"):
            raise SeqvprError(f"{path}: [{role}] {key} names a description ({value}); name the data files")


def _with_dbstruct_positions(traversal: Traversal, db_path: Path, role: Role) -> Traversal:
    """Descriptor rows with the positions (and timestamps) of the same side of a dbStruct, which must match them."""
    side = _dbstruct_side(db_path, role)
    if len(side) != len(traversal):
        raise SeqvprError(f"{db_path}: its {role} side has {len(side)} frames, the descriptors "
                          f"{traversal.source or traversal.name} have {len(traversal)}")
    return replace(traversal, positions=side.positions, timestamps=side.timestamps, crs=side.crs)
