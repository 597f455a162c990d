"""The unit of data: one traversal of a route, as ordered frames with descriptors, positions and segment ids."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr import checks
from seqvpr.data.geo import LOCAL, parse_crs
from seqvpr.arrays import file_mapped
from seqvpr.errors import SeqvprError, SettingError

MAX_POSITION_M = 1e8  # metres from any frame's origin: further is beyond the planet (UTM northings reach 1e7)
GAP_FACTOR = 10.0  # a time step this many times the median one starts a segment (time_gap_segments)



@dataclass(frozen=True)
class Traversal:
    """Ordered frames of one drive along a route.

    ``frame_index`` is each frame's index in its source (row of a descriptor file, position in an image list);
    it survives slicing, so frame-aligned ground truth and written predictions keep referring to the source.
    ``positions`` are metres (easting, northing), absent for frame-aligned sets; ``crs`` says in what
    (``seqvpr.data.geo``: ``utm:32N``, ``local`` when not given, None without positions). ``segment_ids`` mark
    trajectory breaks: a sequence window never spans two runs of different ids. ``names`` name the frames where
    their image files do not (a bag's frames, read from cached files, are ``BAG:/topic@STAMP``).
    """

    name: str
    frame_index: np.ndarray
    segment_ids: np.ndarray
    descriptors: np.ndarray | None = None
    image_paths: tuple[Path, ...] | None = None
    positions: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    headings: np.ndarray | None = None
    source: str = field(default="", compare=False)
    names: tuple[str, ...] | None = None
    crs: str | None = None
    #: a traversal's rows are in memory, normalised when matched (a saved map, ``SavedMap``, knows its storage)
    stored = None

    def __post_init__(self) -> None:
        n = len(self.frame_index)
        if n == 0:
            raise SeqvprError(f"{self._label()}: the traversal is empty (no frames)")
        _check_length(self, "segment_ids", self.segment_ids, n)
        _check_length(self, "positions", self.positions, n)
        _check_length(self, "timestamps", self.timestamps, n)
        _check_length(self, "headings", self.headings, n)
        _check_length(self, "image_paths", self.image_paths, n)
        _check_length(self, "names", self.names, n)
        if self.descriptors is not None:
            object.__setattr__(self, "descriptors", descriptor_rows(self.descriptors, self._label()))
            _check_descriptors(self, self.descriptors)
        if self.positions is not None:
            if self.positions.ndim != 2 or self.positions.shape[1] != 2:
                raise SeqvprError(f"{self._label()}: positions must be [N, 2] (easting, northing) in metres")
            if not _proven(self.positions) and not (np.abs(self.positions) <= MAX_POSITION_M).all():  # NaN: False
                bad = int(np.flatnonzero(~(np.abs(self.positions) <= MAX_POSITION_M).all(axis=1))[0])
                raise SeqvprError(f"{self._label()}: position of frame {int(self.frame_index[bad])} is not finite or "
                                  f"beyond {MAX_POSITION_M:g} m ({self.positions[bad].tolist()}): not a place")
        _settle_crs(self)
        if self.descriptors is None and self.image_paths is None:
            raise SeqvprError(f"{self._label()}: a traversal needs descriptors or image paths")
        _check_indices(self, "frame_index", self.frame_index)
        _check_indices(self, "segment_ids", self.segment_ids)
        if self.timestamps is not None and (np.asarray(self.timestamps).ndim != 1 or not _proven(self.timestamps)
                                            and not np.isfinite(np.asarray(self.timestamps, dtype=float)).all()):
            raise SeqvprError(f"{self._label()}: timestamps must be one finite number per frame")

    @classmethod
    def from_descriptors(
        cls,
        descriptors: np.ndarray,
        name: str = "traversal",
        *,
        positions: np.ndarray | None = None,
        segment_ids: np.ndarray | None = None,
        timestamps: np.ndarray | None = None,
        source: str = "",
    ) -> Traversal:
        """A traversal whose frame ``i`` is row ``i`` of ``descriptors`` (one segment unless ids are given): an array,
        a torch tensor or nested lists of numbers."""
        checks.text(name, "name")
        if not isinstance(source, str):
            raise SettingError(f"{{source}} must be text (where the frames came from), got {checks.shown(source)}")
        descriptors = descriptor_rows(descriptors, name)
        n = len(descriptors)
        label = source or name
        segment_ids = _per_frame(segment_ids, "segment_ids", None, label)
        return cls(
            name=name,
            frame_index=np.arange(n, dtype=np.int64),
            segment_ids=np.zeros(n, dtype=np.int64) if segment_ids is None else segment_ids,
            descriptors=descriptors,
            positions=_per_frame(positions, "positions", np.float64, label),
            timestamps=_per_frame(timestamps, "timestamps", np.float64, label),
            source=source,
        )

    def __len__(self) -> int:
        return len(self.frame_index)

    def __repr__(self) -> str:
        dim = "none" if self.descriptors is None else str(self.descriptors.shape[1])
        units = "metres" if self.positions is not None else "frames"
        return f"<Traversal {self.name!r}: {len(self)} frames, {self.n_segments} segments, dim {dim}, {units}>"

    @property
    def n_segments(self) -> int:
        return int(np.count_nonzero(np.diff(self.segment_ids))) + 1

    def frame_names(self) -> list[str]:
        """A printable name per frame: its recorded name, else the image file name, else the frame index."""
        if self.names is not None:
            return list(self.names)
        if self.image_paths is not None:
            return [p.name for p in self.image_paths]
        return [str(int(i)) for i in self.frame_index]

    def image_names(self) -> list[str] | None:
        """What a saved map records of each image frame (``names.txt``): its recorded name, else its image path;
        None for frames without images."""
        if self.image_paths is None:
            return None
        return list(self.names) if self.names is not None else [str(p) for p in self.image_paths]

    @property
    def dim(self) -> int:
        """Descriptor dimensions (0 for a traversal of images not yet described)."""
        return 0 if self.descriptors is None else int(self.descriptors.shape[1])

    @property
    def plain_rows(self) -> bool:
        """Whether the rows are a saved map's float32 array, read as they are (a traversal's never are)."""
        return False

    @property
    def frames(self) -> Traversal:
        """The frame table results index (a traversal is its own)."""
        return self

    @property
    def owned(self) -> slice:
        """The rows this reference answers for (all of a traversal's; a shard's own, ``SavedMap.owned``)."""
        return slice(0, len(self))

    @property
    def index(self) -> dict | None:
        """The saved nearest-neighbour index over the rows (a map's ``map.json`` record); a traversal has none."""
        return None

    def with_descriptors(self, descriptors: np.ndarray) -> Traversal:
        """The same frames with new descriptor rows in memory (for instance after a learned transform)."""
        return replace(self, descriptors=descriptors)

    def select(self, rows: np.ndarray) -> Traversal:
        """Keep the given rows (indices or boolean mask); removing frames from a run starts a new segment."""
        rows = np.asarray(rows)
        if rows.dtype == bool:
            rows = np.flatnonzero(rows)
        if len(rows) == 0:
            raise SeqvprError(f"{self._label()}: the selection leaves no frames")
        kept_ids = self.segment_ids[rows]
        new_run = np.ones(len(rows), dtype=bool)
        new_run[1:] = (np.diff(rows) != 1) | (np.diff(kept_ids) != 0)
        return replace(
            self,
            frame_index=self.frame_index[rows],
            segment_ids=np.cumsum(new_run) - 1,
            descriptors=None if self.descriptors is None else self.descriptors[rows],
            image_paths=None if self.image_paths is None else tuple(self.image_paths[i] for i in rows),
            names=None if self.names is None else tuple(self.names[i] for i in rows),
            positions=None if self.positions is None else self.positions[rows],
            timestamps=None if self.timestamps is None else self.timestamps[rows],
            headings=None if self.headings is None else self.headings[rows],
        )

    def slice_frames(self, start: int | None, stop: int | None) -> Traversal:
        """Keep frames whose source index lies in ``[start, stop)`` (e.g. to skip placeholder frames)."""
        lo = -np.inf if start is None else start
        hi = np.inf if stop is None else stop
        mask = (self.frame_index >= lo) & (self.frame_index < hi)
        if not mask.any():
            raise SeqvprError(f"{self._label()}: no frame has an index in [{start}, {stop})")
        return self.select(mask)

    def _label(self) -> str:
        return self.source or self.name


def _settle_crs(traversal: Traversal) -> None:
    """Positions without a coordinate system are ``local``; without positions there is none; a ``crs`` text must
    be one ``seqvpr.data.geo`` reads."""
    crs = None if traversal.positions is None else (traversal.crs or LOCAL)
    parse_crs(crs, traversal._label())
    object.__setattr__(traversal, "crs", crs)  # frozen: settled once, here


def _check_indices(traversal: Traversal, field_name: str, values: np.ndarray) -> None:
    """Frame numbers or segment ids: one integer per frame."""
    values = np.asarray(values)
    if values.ndim != 1 or values.dtype.kind not in "iu":
        raise SeqvprError(f"{traversal._label()}: {field_name} must be one integer per frame, got {values.dtype} "
                          f"{values.shape}")


def _proven(values: np.ndarray) -> bool:
    """A column memory-mapped from a map's files: its values were checked when the map was written and its bytes
    are proven by their digest when it is opened, so opening a 10M-frame map does not read every page again."""
    return file_mapped(values)


def _per_frame(values: Any, field_name: str, dtype: type | None, label: str) -> np.ndarray | None:
    """A per-frame field given to ``from_descriptors`` as an array (None as given); what is no array of numbers
    is one line naming the field."""
    if values is None:
        return None
    try:
        array = np.asarray(values, dtype=dtype)
    except (TypeError, ValueError):
        array = None
    if array is None or array.ndim == 0 or array.dtype.kind not in "iuf":
        raise SettingError(f"{label}: {{{field_name}}} must be an array of numbers, one entry per frame, got "
                           f"{checks.shown(values)}")
    return array


def _check_length(traversal: Traversal, field_name: str, values, n: int) -> None:
    if values is not None and (not hasattr(values, "__len__") or getattr(values, "ndim", 1) == 0):
        raise SeqvprError(f"{traversal._label()}: {field_name} must hold one entry per frame, got {values!r}")
    if values is not None and len(values) != n:
        raise SeqvprError(f"{traversal._label()}: {field_name} has {len(values)} entries for {n} frames")


def descriptor_rows(descriptors, label: str):
    """Descriptor rows as the matchers read them: a torch tensor (any floating type; a bfloat16 one as float32,
    gradients dropped) or nested lists become an array; an array, a memory map or coded rows pass as they are;
    anything that is no [frames, dim] table is one line naming it."""
    if hasattr(descriptors, "detach") and hasattr(descriptors, "is_floating_point"):  # a torch tensor
        tensor = descriptors.detach().cpu()
        if not tensor.is_floating_point():
            raise SettingError(f"{label}: {{descriptors}} must be floating point, got {tensor.dtype}")
        descriptors = (tensor.float() if str(tensor.dtype) == "torch.bfloat16" else tensor).numpy()
    elif isinstance(descriptors, (list, tuple)):
        try:
            descriptors = np.asarray(descriptors)
        except ValueError as error:  # ragged rows
            raise SettingError(f"{label}: {{descriptors}} must be a [frames, dim] table ({error})") from None
    shape = getattr(descriptors, "shape", None)
    if shape is None or len(shape) != 2:
        raise SettingError(f"{label}: {{descriptors}} must be a 2-D array [frames, dim], got "
                           f"{'shape ' + str(tuple(shape)) if shape is not None else type(descriptors).__name__}")
    return descriptors


def _check_descriptors(traversal: Traversal, descriptors: np.ndarray) -> None:
    if descriptors.ndim != 2:
        raise SeqvprError(f"{traversal._label()}: descriptors must be a 2-D array [frames, dim], got shape {descriptors.shape}")
    if descriptors.shape[0] != len(traversal.frame_index):
        raise SeqvprError(
            f"{traversal._label()}: {descriptors.shape[0]} descriptor rows for {len(traversal.frame_index)} frames"
        )
    if descriptors.shape[1] == 0:
        raise SeqvprError(f"{traversal._label()}: descriptors have dimension 0")
    if not np.issubdtype(descriptors.dtype, np.floating):
        raise SettingError(f"{traversal._label()}: {{descriptors}} must be floating point, got {descriptors.dtype}")
    if not isinstance(descriptors, np.ndarray) or file_mapped(descriptors):
        return  # a memory-mapped file's rows were checked a block at a time as they were read: not loaded here
    finite = np.isfinite(descriptors).all(axis=1)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise SeqvprError(
            f"{traversal._label()}: descriptor row {int(traversal.frame_index[row])} contains NaN or infinity"
        )


def segments_from_gaps(
    frame_numbers: np.ndarray | None = None,
    max_frame_step: int | None = None,
    timestamps: np.ndarray | None = None,
    max_time_gap: float | None = None,
    positions: np.ndarray | None = None,
    max_distance_gap: float | None = None,
) -> np.ndarray:
    """Segment ids that start a new segment wherever consecutive frames jump by more than a threshold.

    Jumps in frame numbers (frames removed), in time (seconds) or in distance (metres) mark trajectory breaks.
    Give any combination; an unset threshold is not checked.
    """
    lengths = [len(a) for a in (frame_numbers, timestamps, positions) if a is not None]
    if not lengths:
        raise SeqvprError("segments_from_gaps needs frame numbers, timestamps or positions")
    n = lengths[0]
    breaks = np.zeros(max(n - 1, 0), dtype=bool)
    if frame_numbers is not None and max_frame_step is not None:
        breaks |= np.diff(np.asarray(frame_numbers)) > max_frame_step
    if timestamps is not None and max_time_gap is not None:
        breaks |= np.diff(np.asarray(timestamps, dtype=np.float64)) > max_time_gap
    if positions is not None and max_distance_gap is not None:
        steps = np.linalg.norm(np.diff(np.asarray(positions, dtype=np.float64), axis=0), axis=1)
        breaks |= steps > max_distance_gap
    return np.concatenate([[0], np.cumsum(breaks)]).astype(np.int64)

def time_gap_segments(timestamps: np.ndarray) -> np.ndarray:
    """Segment ids breaking where the time step exceeds 10x the median step or goes backwards."""
    steps = np.diff(np.asarray(timestamps, dtype=np.float64))
    if len(steps) == 0:
        return np.zeros(len(timestamps), dtype=np.int64)
    median = float(np.median(steps))
    breaks = steps < 0
    if median > 0:
        breaks |= steps > GAP_FACTOR * median
    return np.concatenate([[0], np.cumsum(breaks)]).astype(np.int64)


def frame_positions(traversal: Traversal, spacing: float = 1.0) -> Traversal:
    """The traversal with along-route positions (``frame_index * spacing``, 0) and heading 0, for frame-aligned
    datasets (Nordland): radii and position cells then count frames (times ``spacing``); unchanged when it has
    positions."""
    if traversal.positions is not None:
        return traversal
    east = traversal.frame_index.astype(np.float64) * float(spacing)
    return replace(traversal, positions=np.stack([east, np.zeros_like(east)], axis=1),
                   headings=np.zeros(len(traversal)))


def parse_frame_range(text: str | None, what: str = "{frames}") -> tuple[int | None, int | None]:
    """``START:STOP`` (either side may be empty) -> a half-open range of source frame indices; ``what`` names the
    option or field in the one-line error."""
    if not text:
        return None, None
    start, sep, stop = text.partition(":")
    try:
        if not sep:
            raise ValueError
        return (int(start) if start else None), (int(stop) if stop else None)
    except ValueError:
        raise SettingError(f"{what} {text!r}: expected START:STOP, e.g. 17:2000") from None


def slice_frame_range(traversal: Traversal, text: str | None, what: str = "{frames}") -> Traversal:
    """The frames ``START:STOP`` (source frame indices) of a traversal; errors name ``what``."""
    start, stop = parse_frame_range(text, what)
    if start is None and stop is None:
        return traversal
    try:
        return traversal.slice_frames(start, stop)
    except SeqvprError as error:
        raise SettingError(f"{what} {text}: {error}") from None


def check_disjoint(a: str, b: str, names: tuple[str, str]) -> None:
    """Two frame ranges of the same traversals must not overlap (validation is neither train nor test)."""
    (a0, a1), (b0, b1) = parse_frame_range(a, names[0]), parse_frame_range(b, names[1])
    lo = max(a0 if a0 is not None else -10**18, b0 if b0 is not None else -10**18)
    hi = min(a1 if a1 is not None else 10**18, b1 if b1 is not None else 10**18)
    if lo < hi:
        raise SeqvprError(f"{names[0]} {a} and {names[1]} {b} overlap on the same traversals; use disjoint ranges")
