"""Sequence windows: which frames form the window of each frame, under segment breaks and a boundary policy.

A window of length L for frame i covers frames ``[start, start + L)``. Its natural start is ``i - offset`` with
``offset = L // 2`` for centred windows (even L covers ``[i - L/2, i + L/2 - 1]``, as the reference code) and
``offset = L - 1`` for causal (trailing) windows, the only kind an online robot can use. A window never spans a
segment break or runs past the traversal. At a boundary, ``drop`` leaves the frame without a window and
``shift`` moves the window inward inside its segment (the reference code's behaviour).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from seqvpr import checks
from seqvpr.errors import SettingError

Align = Literal["centered", "causal"]
Boundary = Literal["drop", "shift"]

#: the most straight trajectories a search tries per window (each one is a pass over the distance matrix)
MAX_VELOCITIES = 1000
#: the fastest slope searched, in reference frames per query frame
MAX_VELOCITY = 100.0


@dataclass(frozen=True)
class SequenceSpec:
    """How frames are grouped into sequences: length, alignment, boundary policy and velocities searched.

    ``velocities`` are reference frames advanced per query frame (SeqSLAM-style slopes); ``(1.0,)`` is plain
    order-aligned sequence matching.
    """

    length: int = 1
    align: Align = "centered"
    boundary: Boundary = "drop"
    velocities: tuple[float, ...] = (1.0,)

    def __post_init__(self) -> None:
        object.__setattr__(self, "length", checks.whole(self.length, "seq_len", 1))
        object.__setattr__(self, "velocities", velocity_tuple(self.velocities))
        checks.text(self.align, "align", ("centered", "causal"))
        checks.text(self.boundary, "boundary", ("drop", "shift"))
        if not self.velocities or any(not np.isfinite(v) or v <= 0 for v in self.velocities):
            raise SettingError(f"{{velocities}} must be positive numbers, got {self.velocities}")
        check_velocities(self.velocities)

    @property
    def offset(self) -> int:
        """Frames of the window before the current frame."""
        return window_offset(self.length, self.align)


def window_offset(length: int, align: Align) -> int:
    """Index of the current frame inside its window: L // 2 (centred) or L - 1 (causal)."""
    return length // 2 if align == "centered" else length - 1


def velocity_steps(length: int, velocity: float) -> np.ndarray:
    """Reference frame offsets from the window start for each query frame of the window (0 first)."""
    return np.rint(np.arange(length) * velocity).astype(np.int64)


def segment_bounds(segment_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the ``[start, end)`` of the run of equal segment ids it belongs to."""
    n = len(segment_ids)
    new_run = np.ones(n, dtype=bool)
    new_run[1:] = np.diff(segment_ids) != 0
    run_starts = np.flatnonzero(new_run)
    run_ends = np.append(run_starts[1:], n)
    run_of_frame = np.cumsum(new_run) - 1
    return run_starts[run_of_frame], run_ends[run_of_frame]


def window_starts(segment_ids: np.ndarray, span: int, offset: int, boundary: Boundary) -> np.ndarray:
    """Start frame of each frame's window of ``span`` frames, or -1 where the frame has none.

    ``offset`` is the natural ``i - start``. With ``drop`` a window must fit as is; with ``shift`` it is clamped
    into the segment, and frames of segments shorter than ``span`` get none.
    """
    seg_start, seg_end = segment_bounds(np.asarray(segment_ids))
    natural = np.arange(len(segment_ids), dtype=np.int64) - offset
    fits_segment = (seg_end - seg_start) >= span
    if boundary == "drop":
        ok = (natural >= seg_start) & (natural + span <= seg_end)
        return np.where(ok, natural, -1)
    shifted = np.clip(natural, seg_start, np.maximum(seg_end - span, seg_start))
    return np.where(fits_segment, shifted, -1)


def window_frames(starts: np.ndarray, length: int) -> np.ndarray:
    """Frame rows [n, L] of the windows starting at ``starts`` (all >= 0)."""
    return np.asarray(starts, dtype=np.int64)[:, None] + np.arange(length, dtype=np.int64)[None, :]


def require_windows(starts: np.ndarray, span: int, what: str, segment_ids: np.ndarray) -> None:
    """Fail with a one-line message when no frame of a traversal has a window (L longer than every segment)."""
    if (starts >= 0).any():
        return
    seg_start, seg_end = segment_bounds(np.asarray(segment_ids))
    longest = int((seg_end - seg_start).max())
    raise SettingError(
        f"{what}: a window of {span} frames ({{seq_len}}) is longer than every segment (longest segment: {longest} "
        "frames)"
    )


def check_length(length: int, segment_ids: np.ndarray, what: str) -> None:
    """Fail before any work when no window of ``length`` frames fits ``what``'s segments (each window lies inside
    one segment, whatever the boundary policy)."""
    seg_start, seg_end = segment_bounds(np.asarray(segment_ids))
    longest = int((seg_end - seg_start).max(initial=0))
    if length > longest:
        raise SettingError(f"{{seq_len}} {length}: longer than every segment of {what} (longest segment: {longest} frames)")


def parse_velocities(text: str, what: str = "{velocities}") -> tuple[float, ...]:
    """``1`` or ``0.8,1,1.2`` or ``0.8:1.2:0.1`` (min:max:step) -> velocities; ``what`` names the option or key.
    A range is counted before it is made: more than ``MAX_VELOCITIES`` is one line, not millions of trajectories."""
    try:
        numbers = tuple(float(x) for x in text.split(":" if ":" in text else ","))
        if ":" in text and not (len(numbers) == 3 and numbers[2] > 0 and numbers[0] <= numbers[1]):
            raise ValueError
    except ValueError:
        raise SettingError(f"{what} {text!r}: expected V, V1,V2,... or MIN:MAX:STEP") from None
    if ":" not in text:
        check_velocities(numbers, what)
        return numbers
    lo, hi, step = numbers
    check_velocities((lo, hi), what)
    count = int((hi - lo) / step + 0.5) + 1
    if count > MAX_VELOCITIES:
        raise SettingError(f"{what} {text!r}: {count} velocities, at most {MAX_VELOCITIES} (widen the step)")
    velocities = tuple(float(v) for v in np.round(np.arange(lo, hi + step / 2, step), 6))
    check_velocities(velocities, what)
    return velocities


def velocity_tuple(velocities) -> tuple[float, ...]:
    """Velocities as a tuple of numbers: text (``0.8:1.2:0.1``, as ``--velocities`` takes it) parsed, a number alone
    one velocity, any other sequence of numbers as floats; anything else one line naming them."""
    if isinstance(velocities, str):
        return parse_velocities(velocities)
    if isinstance(velocities, (int, float, np.number)) and not isinstance(velocities, bool):
        return (float(velocities),)
    try:
        values = tuple(float(v) for v in velocities)
    except (TypeError, ValueError):
        raise SettingError(f"{{velocities}} must be numbers, got {velocities!r}") from None
    return values


def check_velocities(velocities: tuple[float, ...], what: str = "{velocities}") -> None:
    """One line unless there are at most ``MAX_VELOCITIES`` velocities, each positive and at most ``MAX_VELOCITY``
    (a trajectory count or a slope past these costs passes and windows no match needs)."""
    if len(velocities) > MAX_VELOCITIES:
        raise SettingError(f"{what}: {len(velocities)} velocities, at most {MAX_VELOCITIES} (widen the step)")
    if any(not (0 < v <= MAX_VELOCITY) for v in velocities):
        bad = next(v for v in velocities if not 0 < v <= MAX_VELOCITY)
        raise SettingError(f"{what}: velocities must be in (0, {MAX_VELOCITY:g}] reference frames per query frame, "
                          f"got {bad!r}")


MAX_STEPS = 16  # reference frames a query frame may move at most (adaptive, graph): a search's cost grows with it


def parse_steps(text: str, what: str = "{steps}") -> tuple[int, int]:
    """``MIN:MAX`` reference frames per query frame (adaptive matching): 0 <= MIN <= MAX <= 16."""
    try:
        low, high = (int(x) for x in text.split(":"))
    except ValueError:
        raise SettingError(f"{what} {text!r}: expected MIN:MAX with 0 <= MIN <= MAX <= {MAX_STEPS}, e.g. 0:2") from None
    return check_steps((low, high), f"{what} {text!r}")


def check_steps(steps, what: str = "{steps}") -> tuple[int, int]:
    """Steps (MIN, MAX) as two whole numbers with 0 <= MIN <= MAX <= 16, else one line naming them."""
    try:
        low, high = steps
        ok = all(checks.is_whole(v) for v in (low, high))
    except (TypeError, ValueError):
        ok = False
    if not ok or not 0 <= low <= high <= MAX_STEPS:
        raise SettingError(f"{what}: expected MIN, MAX with 0 <= MIN <= MAX <= {MAX_STEPS}, got {steps!r}")
    return int(low), int(high)
