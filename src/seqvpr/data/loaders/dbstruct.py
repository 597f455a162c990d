"""NetVLAD / SeqNet ``dbStruct`` files (``.mat`` or ``.db``): a reference and a query traversal with radii.

Both extensions are MATLAB v5 files holding one struct variable ``dbStruct`` with named fields:

* ``whichSet`` (train/val/test), optional ``dataset``;
* ``dbImageFns`` or ``dbImage`` and ``qImageFns`` or ``qImage``: cells [N, 1] of image paths relative to an
  image root;
* ``utmDb`` and ``utmQ``: [2, N] positions in metres (rows are taken as easting, northing in file order; distances
  do not depend on it). For Nordland they are [1, N] and hold the frame index instead: the traversals then have
  no positions, their ``frame_index`` is that index (so radii in frames apply) and ``frame_aligned`` is true;
* optional ``numDb``/``numImages`` and ``numQ``/``numQueries``, checked against the lists when present;
* ``posDistThr`` (evaluation radius) and ``nonTrivPosDistSqThr`` (squared training positive radius);
  ``posDistSqThr`` is redundant and not read;
* optional ``gpsDb``/``gpsQ`` ([2, N] latitude, longitude) and ``dbTimeStamp``/``qTimeStamp`` (kept in the
  file's unit).

Fields are read BY NAME. The reference readers (pytorch-NetVlad, seqNet, SeqMatchNet) index the struct by
position and, in seqNet/SeqMatchNet, return ``gpsQ`` where ``gpsDb`` belongs and vice versa; here ``gpsDb``
always describes the reference (database) and ``gpsQ`` the query.

The format has no sequence bounds, so each side is one segment, except that when timestamps are present a new
segment starts wherever the time step exceeds 10x the median step or time runs backwards (a jump between drives
or a removed stretch such as a tunnel).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io
from scipy.io.matlab import matfile_version

from seqvpr.data.traversal import Traversal, time_gap_segments
from seqvpr.errors import SeqvprError

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


@dataclass(frozen=True)
class DbStruct:
    """A dbStruct file: reference (database) and query traversals, its radii and whether it is frame-aligned.

    ``pos_dist_thr`` is the evaluation radius (metres, or frames when ``frame_aligned``); ``non_triv_pos_dist``
    is the training positive radius, the square root of the stored ``nonTrivPosDistSqThr``. ``gps_reference`` and
    ``gps_query`` are [N, 2] (latitude, longitude) when the file has ``gpsDb``/``gpsQ``.
    """

    which_set: str
    dataset: str
    reference: Traversal
    query: Traversal
    pos_dist_thr: float
    non_triv_pos_dist: float
    frame_aligned: bool
    gps_reference: np.ndarray | None = None
    gps_query: np.ndarray | None = None


@dataclass(frozen=True)
class _Side:
    """The per-side field names of the struct."""

    role: str
    images: tuple[str, ...]
    utm: str
    count: tuple[str, ...]
    gps: str
    time: str


_REFERENCE = _Side("reference", ("dbImageFns", "dbImage"), "utmDb", ("numDb", "numImages"), "gpsDb", "dbTimeStamp")
_QUERY = _Side("query", ("qImageFns", "qImage"), "utmQ", ("numQ", "numQueries"), "gpsQ", "qTimeStamp")


def load_dbstruct(path: str | Path, *, image_root: str | Path | None = None) -> DbStruct:
    """Read a dbStruct ``.mat``/``.db`` file into reference and query traversals (image paths under image_root)."""
    path = Path(path)
    record = _read_record(path)
    fields = _Fields(path, record)
    which_set = fields.text("whichSet")
    dataset = fields.text("dataset") if fields.has("dataset") else path.stem
    root = (Path(image_root) if image_root is not None else path.parent).absolute()
    ref_utm = fields.matrix(_REFERENCE.utm)
    q_utm = fields.matrix(_QUERY.utm)
    frame_aligned = ref_utm.shape[0] == 1
    if (q_utm.shape[0] == 1) != frame_aligned:
        raise SeqvprError(
            f"{path}: field 'utmDb' has {ref_utm.shape[0]} row(s) but 'utmQ' has {q_utm.shape[0]}; "
            "both must be [2, N] positions or both [1, N] frame indices"
        )
    label = f"{dataset}-{which_set}" if which_set else dataset
    ref, gps_ref = _side(fields, _REFERENCE, ref_utm, root, label)
    query, gps_q = _side(fields, _QUERY, q_utm, root, label)
    return DbStruct(
        which_set=which_set,
        dataset=dataset,
        reference=ref,
        query=query,
        pos_dist_thr=fields.scalar("posDistThr"),
        non_triv_pos_dist=float(np.sqrt(fields.scalar("nonTrivPosDistSqThr"))),
        frame_aligned=frame_aligned,
        gps_reference=gps_ref,
        gps_query=gps_q,
    )


def _read_record(path: Path) -> np.void:
    """The ``dbStruct`` record of a MATLAB v5 file, with errors for missing, non-MAT and v7.3 files."""
    from seqvpr.arrays import check_regular_file, load_mat

    if path.exists():
        check_regular_file(path, "a dbStruct .mat file")
    if not path.is_file():
        raise SeqvprError(f"{path}: dbStruct file not found")
    with open(path, "rb") as handle:
        head = handle.read(520)
    if head[:8] == _HDF5_MAGIC or head[512:520] == _HDF5_MAGIC:
        raise SeqvprError(f"{path}: MATLAB v7.3 (HDF5) file; save it from MATLAB with save(..., '-v7')")
    try:
        with open(path, "rb") as handle:
            major, _ = matfile_version(handle)
    except Exception as exc:  # scipy raises several types (MatReadError, ValueError) for non-MAT input
        raise SeqvprError(f"{path}: not a MATLAB .mat file ({_one_line(exc)})") from None
    if major == 2:
        raise SeqvprError(f"{path}: MATLAB v7.3 (HDF5) file; save it from MATLAB with save(..., '-v7')")
    try:
        contents = load_mat(path, struct_as_record=True, chars_as_strings=True)
    except SeqvprError:
        raise
    except Exception as exc:  # a corrupt or truncated file can fail anywhere inside scipy's reader
        raise SeqvprError(f"{path}: not a readable MATLAB .mat file ({_one_line(exc)})") from None
    if "dbStruct" not in contents:
        found = ", ".join(k for k in contents if not k.startswith("__")) or "none"
        raise SeqvprError(f"{path}: no variable 'dbStruct' (variables: {found})")
    struct = contents["dbStruct"]
    if not isinstance(struct, np.ndarray) or struct.dtype.names is None or struct.size != 1:
        raise SeqvprError(f"{path}: variable 'dbStruct' is not a single struct with named fields")
    return struct.flat[0]


class _Fields:
    """Typed access to the named fields of the struct, with errors naming the file and field."""

    def __init__(self, path: Path, record: np.void) -> None:
        self.path = path
        self.record = record
        self.names = set(record.dtype.names or ())

    def has(self, name: str) -> bool:
        """Whether the struct has this field."""
        return name in self.names

    def first_present(self, names: tuple[str, ...], required: bool = True) -> str | None:
        """The first of the alternative field names present (error when required and none is)."""
        for name in names:
            if name in self.names:
                return name
        if required:
            raise SeqvprError(f"{self.path}: dbStruct has no field {' or '.join(repr(n) for n in names)}")
        return None

    def raw(self, name: str) -> np.ndarray:
        """The field's array as loaded (error when absent)."""
        self.first_present((name,))
        return np.asarray(self.record[name])

    def text(self, name: str) -> str:
        """A char field as a string."""
        value = _as_text(self.raw(name))
        if value is None:
            raise SeqvprError(f"{self.path}: field {name!r} is not text")
        return value

    def scalar(self, name: str) -> float:
        """A numeric field holding one finite number."""
        value = self.raw(name)
        if value.dtype.kind not in "biuf" or value.size != 1 or not np.isfinite(value).all():
            raise SeqvprError(f"{self.path}: field {name!r} must be one finite number, got shape {value.shape}")
        return float(value.ravel()[0])

    def count(self, names: tuple[str, ...]) -> tuple[str, int] | None:
        """An optional non-negative integer count field and its name."""
        name = self.first_present(names, required=False)
        if name is None:
            return None
        value = self.scalar(name)
        if value < 0 or not float(value).is_integer():
            raise SeqvprError(f"{self.path}: field {name!r} must be a non-negative integer, got {value:g}")
        return name, int(value)

    def matrix(self, name: str) -> np.ndarray:
        """A finite 2-D numeric field with one or two rows ([1|2, N])."""
        value = self.raw(name)
        if value.dtype.kind not in "biuf" or value.ndim != 2 or value.shape[0] not in (1, 2) or value.shape[1] == 0:
            raise SeqvprError(
                f"{self.path}: field {name!r} must be a numeric [2, N] (or [1, N]) array, got {value.shape}"
            )
        value = value.astype(np.float64)
        if not np.isfinite(value).all():
            column = int(np.flatnonzero(~np.isfinite(value).all(axis=0))[0])
            raise SeqvprError(f"{self.path}: field {name!r} has a non-finite value in column {column}")
        return value

    def vector(self, name: str, n: int) -> np.ndarray:
        """A finite numeric field of n values in any [1, n] / [n, 1] / [n] shape."""
        value = self.raw(name)
        if value.dtype.kind not in "biuf" or value.size != n or max(value.shape, default=0) != n:
            raise SeqvprError(f"{self.path}: field {name!r} must hold {n} numbers, got shape {value.shape}")
        value = value.astype(np.float64).ravel()
        if not np.isfinite(value).all():
            index = int(np.flatnonzero(~np.isfinite(value))[0])
            raise SeqvprError(f"{self.path}: field {name!r} has a non-finite value at index {index}")
        return value

    def names_list(self, names: tuple[str, ...]) -> tuple[str, list[str]]:
        """A cell (or char matrix) of image names, and the field name used."""
        name = self.first_present(names)
        value = self.raw(name)
        items = list(value.ravel()) if value.dtype.kind in "OUS" else None
        if items is None:
            raise SeqvprError(f"{self.path}: field {name!r} must be a cell of image names, got {value.dtype}")
        out = []
        for i, item in enumerate(items):
            text = _as_text(np.asarray(item))
            if not text:
                raise SeqvprError(f"{self.path}: field {name!r} entry {i} is not a non-empty image name")
            out.append(text)
        return name, out


def _side(
    fields: _Fields, side: _Side, utm: np.ndarray, root: Path, label: str
) -> tuple[Traversal, np.ndarray | None]:
    """One traversal (and its GPS, if stored) from its image list, UTM/frame-index array and timestamps."""
    path = fields.path
    list_name, names = fields.names_list(side.images)
    n = len(names)
    if n == 0:
        raise SeqvprError(f"{path}: field {list_name!r} lists no images")
    counted = fields.count(side.count)
    if counted is not None and counted[1] != n:
        raise SeqvprError(f"{path}: field {counted[0]!r} is {counted[1]} but {list_name!r} has {n} images")
    if utm.shape[1] != n:
        raise SeqvprError(f"{path}: field {side.utm!r} has {utm.shape[1]} columns but {list_name!r} has {n} images")
    if utm.shape[0] == 1:
        frame_index = _frame_index(path, side.utm, utm[0])
        positions = None
    else:
        frame_index = np.arange(n, dtype=np.int64)
        positions = np.ascontiguousarray(utm.T)
    timestamps = fields.vector(side.time, n) if fields.has(side.time) else None
    gps = _gps(fields, side.gps, n) if fields.has(side.gps) else None
    traversal = Traversal(
        name=f"{label}-{side.role}",
        frame_index=frame_index,
        segment_ids=time_gap_segments(timestamps) if timestamps is not None else np.zeros(n, dtype=np.int64),
        image_paths=tuple(root / nm for nm in names),
        positions=positions,
        timestamps=timestamps,
        source=str(path),
    )
    return traversal, gps


def _frame_index(path: Path, name: str, row: np.ndarray) -> np.ndarray:
    """A one-row utm array read as integer frame indices (Nordland)."""
    rounded = np.rint(row)
    if np.abs(row - rounded).max() > 1e-6:
        raise SeqvprError(f"{path}: field {name!r} has one row, read as frame indices, but holds non-integers")
    return rounded.astype(np.int64)


def _gps(fields: _Fields, name: str, n: int) -> np.ndarray:
    """A [2, N] latitude/longitude field as [N, 2]."""
    value = fields.matrix(name)
    if value.shape != (2, n):
        raise SeqvprError(f"{fields.path}: field {name!r} must be [2, {n}] (latitude, longitude), got {value.shape}")
    return np.ascontiguousarray(value.T)



def _as_text(value: np.ndarray) -> str | None:
    """The string in a loaded MATLAB char array or 1-element cell ('' when empty), None when not text."""
    while value.dtype.kind == "O" and value.size == 1:
        value = np.asarray(value.ravel()[0])
    if value.dtype.kind == "O":
        return None
    if value.size == 0:
        return "" if value.dtype.kind in "USf" else None
    if value.dtype.kind not in "US" or value.size != 1:
        return None
    text = value.ravel()[0]
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    return str(text).rstrip(" \x00")


def _one_line(exc: BaseException) -> str:
    """An exception's message folded onto one line."""
    return " ".join(str(exc).split()) or type(exc).__name__


def write_dbstruct(path: str | Path, reference: Traversal, query: Traversal, radius: float, dataset: str = "seqvpr",
                   which_set: str = "test") -> Path:
    """A seqNet/SeqMatchNet ``.db`` struct of two traversals (written atomically): image names (or frame names),
    ``utmDb``/``utmQ`` as [2, N] positions or, for frame-aligned traversals, [1, N] frame indices, timestamps when
    both have them, and ``posDistThr`` = ``radius`` (metres, or frames when frame-aligned)."""
    from seqvpr.io import atomic_write

    aligned = reference.positions is None or query.positions is None
    fields: dict = {"whichSet": which_set, "dataset": dataset, "posDistThr": float(radius),
                    "posDistSqThr": float(radius) ** 2, "nonTrivPosDistSqThr": float(radius) ** 2}
    for side, traversal in ((_REFERENCE, reference), (_QUERY, query)):
        fields[side.images[0]] = _name_cell(traversal)
        fields[side.utm] = (traversal.frame_index[None, :].astype(np.float64) if aligned
                            else np.ascontiguousarray(traversal.positions.T, dtype=np.float64))
        fields[side.count[1]] = len(traversal)
        if traversal.timestamps is not None:
            fields[side.time] = np.asarray(traversal.timestamps, dtype=np.float64)[None, :]
    with atomic_write(path, "wb") as handle:
        scipy.io.savemat(handle, {"dbStruct": fields})
    return Path(path)


def _name_cell(traversal: Traversal) -> np.ndarray:
    """A MATLAB cell [N, 1] of the frames' image names (their source names when there are no images)."""
    names = ([str(p) for p in traversal.image_paths] if traversal.image_paths is not None
             else traversal.frame_names())
    cell = np.empty((len(names), 1), dtype=object)
    cell[:, 0] = names
    return cell
