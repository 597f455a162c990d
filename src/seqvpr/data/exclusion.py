"""The recent past a loop closure may not come from: ``30s`` (seconds), ``200f`` (frames) or ``50m`` (metres
travelled), and the earlier frames each frame of a drive may match, which are always a prefix of the drive.

Frames of earlier sessions are all eligible; a frame's own session is eligible before the exclusion. Since time,
frame count and travelled distance only grow along a session, the eligible frames of frame i are rows
``[0, limit[i])`` of the drive laid end to end by session, with ``limit`` non-decreasing: what the matching kernel
takes as its per-query ``limits``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

import numpy as np

from seqvpr.errors import SettingError

ExclusionUnit = Literal["s", "f", "m"]
UNITS = {"s": "seconds", "f": "frames", "m": "metres travelled"}
_EXCLUSION = re.compile(r"^\s*([-+]?\d+(?:\.\d*)?|[-+]?\.\d+)\s*([a-z]*)\s*$", re.IGNORECASE)
_SPELLINGS = {"s": "s", "sec": "s", "secs": "s", "seconds": "s", "second": "s", "f": "f", "frame": "f",
              "frames": "f", "m": "m", "metres": "m", "meters": "m", "metre": "m", "meter": "m"}


@dataclass(frozen=True)
class Exclusion:
    """The recent past excluded from a frame's candidates: ``value`` in ``unit`` (s, f or m) before the frame."""

    value: float
    unit: ExclusionUnit

    def __str__(self) -> str:
        return f"{self.value:g}{self.unit}"


def parse_exclusion(text: str | Exclusion) -> Exclusion:
    """``30s``, ``200f`` or ``50m`` (a number and its unit; no unit is refused: each means something else)."""
    if isinstance(text, Exclusion):
        return text
    match = _EXCLUSION.match(str(text))
    unit = _SPELLINGS.get(match.group(2).lower()) if match else None
    if match is None or unit is None:
        raise SettingError(f"{{exclude}} {text!r}: expected a number and a unit, s (seconds), f (frames) or m "
                           "(metres travelled), e.g. 30s, 200f or 50m")
    value = float(match.group(1))
    if value < 0 or not np.isfinite(value):
        raise SettingError(f"{{exclude}} {text!r} must not be negative")
    return Exclusion(value, unit)  # type: ignore[arg-type]


def session_starts(sessions: np.ndarray) -> np.ndarray:
    """Per frame, the row where its session begins (sessions laid end to end, each a run of one id)."""
    sessions = np.asarray(sessions)
    first = np.concatenate([[True], sessions[1:] != sessions[:-1]]) if len(sessions) else np.zeros(0, bool)
    return np.maximum.accumulate(np.where(first, np.arange(len(sessions)), 0))


def travelled(positions: np.ndarray, sessions: np.ndarray) -> np.ndarray:
    """Metres travelled since the start of each frame's session, along the positions."""
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1) if len(positions) > 1 else np.zeros(0)
    steps = np.where(np.asarray(sessions)[1:] != np.asarray(sessions)[:-1], 0.0, steps)
    return np.concatenate([[0.0], np.cumsum(steps)])


def eligible_limits(exclusion: Exclusion, sessions: np.ndarray, timestamps: np.ndarray | None = None,
                    positions: np.ndarray | None = None, where: str = "the drive") -> np.ndarray:
    """Per frame i, the row ``limit[i]``: frames ``[0, limit[i])`` are eligible (earlier sessions whole, its own
    session up to the exclusion), non-decreasing. Seconds need timestamps, metres positions (one line naming
    ``where`` otherwise)."""
    sessions = np.asarray(sessions)
    starts = session_starts(sessions)
    rows = np.arange(len(sessions))
    if exclusion.unit == "f":
        # j is excluded when i - j <= value: the frame itself and the ``value`` before it
        own = rows - np.floor(exclusion.value).astype(np.int64)
    else:
        clock = _clock(exclusion, sessions, timestamps, positions, where)
        own = np.empty(len(sessions), np.int64)
        for first, last in _session_runs(starts):
            part = np.maximum.accumulate(clock[first:last])  # a clock that steps back holds its latest value
            # eligible: part[j] < part[i] - value (strictly more than ``value`` before)
            own[first:last] = first + np.searchsorted(part, part - exclusion.value, "left")
    return np.maximum.accumulate(np.maximum(np.minimum(own, rows), starts))


def _clock(exclusion: Exclusion, sessions: np.ndarray, timestamps: np.ndarray | None,
           positions: np.ndarray | None, where: str) -> np.ndarray:
    """What the exclusion is measured along: seconds or metres travelled."""
    if exclusion.unit == "s":
        if timestamps is None:
            raise SettingError(f"{where}: {{exclude}} {exclusion} needs timestamps; this drive has none (use "
                               "frames, e.g. 200f, or metres with positions)")
        return np.asarray(timestamps, dtype=np.float64)
    if positions is None:
        raise SettingError(f"{where}: {{exclude}} {exclusion} needs positions; this drive has none (use frames, "
                       "e.g. 200f, or seconds with timestamps)")
    return travelled(np.asarray(positions, dtype=np.float64), sessions)


def _session_runs(starts: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) row of each session."""
    firsts = np.flatnonzero(np.concatenate([[True], starts[1:] != starts[:-1]])) if len(starts) else np.zeros(0, int)
    return list(zip(firsts.tolist(), [*firsts[1:].tolist(), len(starts)]))
