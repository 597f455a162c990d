"""Loop closures a frame at a time: ``LoopDetector`` takes each new frame's descriptor, matches the window that ends
at it against every earlier window outside the exclusion (``seqvpr.localization.loops``' settings, limits and
score), and then adds the frame to the past it searches. A replayed drive gives what ``find_loops`` gives.

    detector = LoopDetector(LoopSettings(seq_len=5, exclude="30s"))
    for descriptor, stamp in camera:
        loop = detector.update(descriptor, timestamp=stamp)
        if loop.accepted:
            back_end.add_loop(loop.frame, loop.match)

The past grows by one row a frame, appended in amortised O(1) (``GrowingRows``: capacity doubled, memory-mapped
once it passes ``memory_budget``); per frame the cost is one distance pass over the past and one pass over the
last L distance rows, as for the localiser.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from seqvpr.data.exclusion import Exclusion, parse_exclusion
from seqvpr.errors import SeqvprError
from seqvpr.localization.loops import DEFAULT_FRAMES, DEFAULT_SECONDS, LoopSettings, loop_score
from seqvpr.matchers.rows import frame_row, frame_transform
from seqvpr.sequences.topk import best_k

#: bytes of past rows kept in memory before they go to a memory-mapped file
DEFAULT_BUDGET = 1024**3
LOOP_STATE_FORMAT = "seqvpr-loop-state"
LOOP_STATE_VERSION = 1
STATE_ARRAYS = ("rows", "sessions", "segments", "clock", "limits", "ring", "ring_lengths", "position", "starts",
                "neighbours", "index", "index_rows", "stamps")


@dataclass(frozen=True)
class Loop:
    """One frame's loop: its row in the drive, the best eligible earlier frame (``match``, -1 when none), its
    sequence distance, the score and whether it is accepted; the sessions and timestamps of both (NaN: none given,
    or no match)."""

    frame: int
    match: int
    distance: float
    score: float
    accepted: bool
    session: int
    match_session: int
    stamp: float = float("nan")
    match_stamp: float = float("nan")


class GrowingRows:
    """Rows [n, width] appended one at a time with amortised O(1) cost: the capacity doubles, in memory up to
    ``budget`` bytes, then in a memory-mapped file in ``folder`` (a temporary one unless given)."""

    def __init__(self, width: int, dtype: Any = np.float32, budget: int = DEFAULT_BUDGET,
                 folder: str | Path | None = None) -> None:
        self.width, self.dtype, self.budget, self.folder = width, np.dtype(dtype), budget, folder
        self.data = np.zeros((16, width), self.dtype) if width else np.zeros(16, self.dtype)
        self.count = 0
        self._file: Any = None

    def __len__(self) -> int:
        return self.count

    @property
    def rows(self) -> np.ndarray:
        """The rows so far (a view; a later append may move them)."""
        return self.data[: self.count]

    def append(self, row: Any) -> None:
        if self.count == len(self.data):
            self._grow(2 * len(self.data))
        self.data[self.count] = row
        self.count += 1

    def extend(self, rows: np.ndarray) -> None:
        """Append several rows at once."""
        capacity = len(self.data)
        while capacity < self.count + len(rows):
            capacity *= 2
        if capacity != len(self.data):
            self._grow(capacity)
        self.data[self.count : self.count + len(rows)] = rows
        self.count += len(rows)

    def _grow(self, capacity: int) -> None:
        shape = (capacity, self.width) if self.width else (capacity,)
        if capacity * max(self.width, 1) * self.dtype.itemsize <= self.budget:
            grown = np.zeros(shape, self.dtype)
        else:
            folder = self.folder or tempfile.gettempdir()
            self._file = tempfile.NamedTemporaryFile(dir=folder, prefix="seqvpr-loops-", suffix=".bin")
            grown = np.memmap(self._file, self.dtype, "w+", shape=shape)
        grown[: self.count] = self.data[: self.count]
        self.data = grown


class LoopDetector:
    """Loop closures over a drive that grows a frame at a time (``update``); ``new_session`` and ``new_segment``
    mark where windows may not continue; ``state``/``load_state`` save and resume it (a restarted robot)."""

    def __init__(self, settings: LoopSettings = LoopSettings(), models: dict[str, Any] | None = None, *,
                 memory_budget: int = DEFAULT_BUDGET, folder: str | Path | None = None) -> None:
        self.settings, self.transform = settings, frame_transform(models or {})
        self.length = settings.window
        self.memory_budget, self.folder = memory_budget, folder
        self.rows: GrowingRows | None = None  # made at the first frame, when the width is known
        self.sessions = GrowingRows(0, np.int64)
        self.segments = GrowingRows(0, np.int64)
        self.clock = GrowingRows(0, np.float64)  # running maximum of seconds or metres along the session
        self.limits = GrowingRows(0, np.int64)
        self.starts = GrowingRows(0, np.int64)  # each frame's window start (-1: none)
        self.stamps = GrowingRows(0, np.float64)  # each frame's timestamp (NaN: none given)
        self.neighbours = GrowingRows(settings.shortlist, np.int64)  # with a shortlist: each frame's nearest rows
        self.index: Any = None  # with a shortlist: the GrowingIndex over the eligible past
        self.ring: list[np.ndarray] = []  # the last L frames' distances to every earlier frame
        self.session, self.segment, self.since_break, self.position = 0, 0, 0, None
        self.exclusion: Exclusion | None = None if settings.exclude is None else parse_exclusion(settings.exclude)

    def key(self) -> dict[str, Any]:
        """What a saved state depends on: the settings' meaning and the exclusion in force."""
        settings = self.settings
        return {"method": settings.method, "length": self.length, "exclusion": settings.exclusion,
                "threshold": settings.accept, "exclude": None if self.exclusion is None else str(self.exclusion),
                "shortlist": settings.shortlist, "shortlist_index": settings.shortlist_index}

    def save_state(self, path: str | Path) -> None:
        """The grown past and where the drive stands (rows, sessions, segments, clock, limits, the last L distance
        rows, counters), written atomically as ``.npz``: ``restore`` goes on from it after a restart."""
        import json

        from seqvpr.io import atomic_write

        count = len(self.sessions)
        ring = np.zeros((len(self.ring), max(count - 1, 0)), np.float32)
        for row, distances in zip(ring, self.ring):
            row[: len(distances)] = distances
        header = {"format": LOOP_STATE_FORMAT, "version": LOOP_STATE_VERSION, "settings": self.key(),
                  "session": self.session, "segment": self.segment, "since_break": self.since_break}
        arrays = {"rows": self.rows.rows if self.rows is not None else np.zeros((0, 0), np.float32),
                  "sessions": self.sessions.rows, "segments": self.segments.rows, "clock": self.clock.rows,
                  "limits": self.limits.rows, "ring": ring, "ring_lengths": np.array([len(r) for r in self.ring]),
                  "position": np.asarray(self.position if self.position is not None else [], np.float64),
                  "starts": self.starts.rows, "neighbours": self.neighbours.rows, "stamps": self.stamps.rows,
                  "index": self.index.to_bytes() if self.index is not None else np.zeros(0, np.uint8),
                  "index_rows": np.array(self.index.added if self.index is not None else 0)}
        with atomic_write(path, "wb") as handle:
            np.savez(handle, header=np.array(json.dumps(header)), **arrays)

    def restore(self, path: str | Path) -> None:
        """Go on from a state ``save_state`` wrote with these settings; a damaged file, another format or other
        settings is one line naming it, and the detector stays as it was."""
        import json

        from seqvpr.arrays import open_npz
        from seqvpr.errors import reading

        with reading(path, "a loop detector state"):
            with open_npz(path) as data:
                header = json.loads(str(data["header"]))
                arrays = {k: data[k] for k in data.files if k != "header"}
        if not isinstance(header, dict) or header.get("format") != LOOP_STATE_FORMAT or \
                header.get("version") != LOOP_STATE_VERSION:
            raise SeqvprError(f"{path}: not a loop detector state of this seqvpr (format {LOOP_STATE_FORMAT} "
                              f"version {LOOP_STATE_VERSION})")
        saved = header.get("settings") or {}
        if saved.get("exclude") is not None and self.exclusion is None:
            self.exclusion = parse_exclusion(saved["exclude"])
        if saved != self.key():
            raise SeqvprError(f"{path}: saved with other settings ({saved}; these: {self.key()})")
        self._load_arrays(path, arrays)
        self.session, self.segment, self.since_break = (int(header[k]) for k in ("session", "segment", "since_break"))

    def _load_arrays(self, path: str | Path, arrays: dict[str, np.ndarray]) -> None:
        """The saved past, checked: one count across the per-frame arrays, finite rows, a ring that fits."""
        if not set(STATE_ARRAYS) <= set(arrays):
            missing = ", ".join(sorted(set(STATE_ARRAYS) - set(arrays)))
            raise SeqvprError(f"{path}: a loop detector state without {missing}")
        count = len(arrays["sessions"])
        rows, ring, lengths = arrays["rows"], arrays["ring"], arrays["ring_lengths"]
        shortlist = self.settings.shortlist
        sound = all(len(arrays[k]) == count for k in ("segments", "clock", "limits", "starts", "stamps")) and \
            (not shortlist or len(arrays["neighbours"]) == count) and \
            (count == 0 or (rows.ndim == 2 and len(rows) == count and np.isfinite(rows).all())) and \
            len(ring) == len(lengths) <= self.length and (lengths <= max(count - 1, 0)).all()
        if not sound:
            raise SeqvprError(f"{path}: a loop detector state whose arrays do not agree (damaged?)")
        self.rows = None
        for name in ("sessions", "segments", "clock", "limits", "starts", "neighbours", "stamps"):
            grown = GrowingRows(getattr(self, name).width, getattr(self, name).dtype)
            grown.extend(arrays[name])
            setattr(self, name, grown)
        if count:
            self.rows = GrowingRows(rows.shape[1], np.float32, self.memory_budget, self.folder)
            self.rows.extend(rows)
            self.index = self._restored_index(path, arrays, rows)
        self.ring = [np.array(row[:n]) for row, n in zip(ring, lengths.tolist())]
        self.position = arrays["position"] if len(arrays["position"]) else None

    def _restored_index(self, path: str | Path, arrays: dict[str, np.ndarray], rows: np.ndarray):
        """The shortlist's index as saved (None without a shortlist)."""
        if not self.settings.shortlist:
            return None
        from seqvpr.localization.loop_shortlist import GrowingIndex, check_shortlist_index

        index = GrowingIndex(check_shortlist_index(self.settings.shortlist_index), rows)
        try:
            index.load_bytes(arrays["index"], int(arrays["index_rows"]))
        except (ValueError, RuntimeError):
            raise SeqvprError(f"{path}: a loop detector state whose shortlist index is damaged") from None
        return index

    def new_session(self) -> None:
        """The next frame starts a new session (another drive): the earlier sessions are eligible whole."""
        if len(self.sessions):
            self.session += 1
            self.new_segment()

    def new_segment(self) -> None:
        """The next frame starts a new segment: no window spans the break."""
        if len(self.segments):
            self.segment += 1
            self.since_break = 0

    def update(self, descriptor: Any, timestamp: float | None = None, position: Any = None) -> Loop:
        """Match the window ending at this frame against the eligible past, then add the frame to the past. A frame
        that is not a finite descriptor is one line, and leaves the detector as it was."""
        row = frame_row(descriptor, self.transform, True).numbers.copy()
        if not np.isfinite(row).all():
            raise SeqvprError(f"a frame's descriptor holds NaN or infinity (frame {len(self.sessions)}); nothing added")
        self._enter(row, timestamp, position)
        frame = len(self.sessions) - 1
        if self.settings.shortlist:
            return self._shortlisted(frame)
        distances = self._distances_to_past(row)
        self.ring = [*self.ring[-(self.length - 1):], distances] if self.length > 1 else [distances]
        if self.since_break < self.length:
            return self._loop(frame, -1, np.inf, 0.0)
        indices, values = self._ranked(int(self.limits.rows[frame]))
        score = loop_score(indices, values, self.settings.exclusion) if indices[0] >= 0 else 0.0
        return self._loop(frame, int(indices[0]), float(values[0]), score)

    def _enter(self, row: np.ndarray, timestamp: float | None, position: Any) -> None:
        """The frame's row, session, segment, clock and eligible limit appended."""
        if self.rows is None:
            self.rows = GrowingRows(len(row), np.float32, self.memory_budget, self.folder)
        elif len(row) != self.rows.width:
            raise SeqvprError(f"a frame of {len(row)} values for a drive of {self.rows.width}-D frames")
        self.exclusion = self.exclusion or parse_exclusion(DEFAULT_SECONDS if timestamp is not None
                                                           else DEFAULT_FRAMES)
        start = self._session_start()
        self.clock.append(self._clock_value(timestamp, position, start))
        self.rows.append(row)
        self.stamps.append(np.nan if timestamp is None else float(timestamp))
        self.sessions.append(self.session)
        self.segments.append(self.segment)
        self.since_break += 1
        self.limits.append(self._limit(start))
        self.starts.append(len(self.sessions) - self.length if self.since_break >= self.length else -1)

    def _session_start(self) -> int:
        """The row the current session began at (the next row when it begins now)."""
        sessions = self.sessions.rows
        if not len(sessions) or sessions[-1] != self.session:
            return len(sessions)
        return int(np.searchsorted(sessions, self.session, "left"))

    def _clock_value(self, timestamp: float | None, position: Any, start: int) -> float:
        """Seconds, or metres travelled since the session began (as ``exclusion.travelled``), or 0 for frames."""
        unit = self.exclusion.unit
        if unit == "s":
            if timestamp is None:
                raise SeqvprError(f"exclusion {self.exclusion} needs each frame's timestamp")
            value = float(timestamp)
        elif unit == "m":
            if position is None:
                raise SeqvprError(f"exclusion {self.exclusion} needs each frame's position")
            here = np.asarray(position, dtype=np.float64)
            moved = 0.0 if start == len(self.sessions) or self.position is None else \
                float(np.linalg.norm(here - self.position))
            value = (self.clock.rows[-1] if start < len(self.sessions) else 0.0) + moved
            self.position = here
        else:
            return 0.0
        previous = self.clock.rows[-1] if start < len(self.sessions) else -np.inf
        return max(value, previous)

    def _limit(self, start: int) -> int:
        """The new frame's eligible rows ``[0, limit)`` (``exclusion.eligible_limits`` for the frame just added)."""
        frame = len(self.sessions) - 1
        if self.exclusion.unit == "f":
            own = frame - int(np.floor(self.exclusion.value))
        else:
            part = self.clock.rows[start:]
            own = start + int(np.searchsorted(part, part[-1] - self.exclusion.value, "left"))
        limit = max(min(own, frame), start)
        return max(limit, int(self.limits.rows[-1])) if len(self.limits) else limit

    def _distances_to_past(self, row: np.ndarray) -> np.ndarray:
        """The new frame's distances to every earlier frame (float32, clamped as ``frame_distances``)."""
        from seqvpr.sequences.matching import frame_distances

        past = self.rows.rows[:-1]
        if not len(past):
            return np.zeros(0, np.float32)
        return frame_distances(torch.from_numpy(row)[None], torch.from_numpy(np.asarray(past)))[0].numpy().copy()

    def _shortlisted(self, frame: int) -> Loop:
        """The frame's nearest eligible rows found and kept; the candidates its window's frames place re-ranked
        exactly (``loop_shortlist``: as ``find_loops`` with a shortlist does a block at a time)."""
        from seqvpr.localization.loop_shortlist import GrowingIndex, check_shortlist_index, rerank_block
        from seqvpr.localization.loops import causal_spec
        from seqvpr.sequences.rerank import frame_shortlist

        rows, limits = self.rows.rows, self.limits.rows
        if self.index is None:
            self.index = GrowingIndex(check_shortlist_index(self.settings.shortlist_index), rows)
        self.index.grow_to(int(limits[frame]), rows)
        self.neighbours.append(self.index.nearest_eligible(frame, frame + 1, limits, self.settings.shortlist)[0])
        if self.since_break < self.length:
            return self._loop(frame, -1, np.inf, 0.0)
        starts = self.starts.rows
        candidates = frame_shortlist(self.neighbours.rows, starts[frame : frame + 1], causal_spec(self.settings),
                                     frame + 1)
        candidates.indices[candidates.indices >= limits[frame]] = -1
        top = rerank_block(torch.from_numpy(np.asarray(rows)), np.asarray(rows), starts, frame, self.length,
                           candidates, self.settings.ranked())
        indices, values = top.indices[0], top.distances[0]
        score = loop_score(indices, values, self.settings.exclusion) if indices[0] >= 0 else 0.0
        return self._loop(frame, int(indices[0]), float(values[0]), score)

    def _ranked(self, limit: int) -> tuple[np.ndarray, np.ndarray]:
        """The best eligible windows (rows, mean distances), best first: the window ending at row j averages the
        ring's rows along the diagonal; +inf where j's window would cross a segment."""
        length, k = self.length, self.settings.ranked()
        if limit < length:
            return np.full(1, -1), np.full(1, np.inf)
        ends = np.arange(length - 1, limit)
        sums = np.zeros(len(ends), np.float64)
        for back in range(length):  # oldest first
            sums += self.ring[back][ends - (length - 1) + back]
        segments = self.segments.rows
        means = np.where(segments[ends - length + 1] == segments[ends], sums / length, np.inf)
        indices, values = best_k(means, k)
        return np.where(indices >= 0, indices + length - 1, -1), values

    def _loop(self, frame: int, match: int, distance: float, score: float) -> Loop:
        sessions, stamps = self.sessions.rows, self.stamps.rows
        found = match >= 0 and np.isfinite(distance)
        return Loop(frame, match if found else -1, distance if found else np.inf, score if found else 0.0,
                    bool(found and score >= self.settings.accept), int(sessions[frame]),
                    int(sessions[match]) if found else -1, float(stamps[frame]),
                    float(stamps[match]) if found else float("nan"))


def replay_loops(drive, settings: LoopSettings = LoopSettings(), models: dict[str, Any] | None = None,
                 **options: Any):
    """A drive (``loops.Drive``) fed to a ``LoopDetector`` frame by frame, a new session or segment where the
    drive's change: the ``Loops`` that ``find_loops`` gives for it."""
    from seqvpr.localization.loops import Loops

    frames = drive.frames
    detector = LoopDetector(settings, models, **options)
    detector.exclusion = settings.exclusion_for(frames)
    rows, segments = frames.descriptors, np.asarray(frames.segment_ids)
    found = []
    for i in range(len(frames)):
        if i and drive.sessions[i] != drive.sessions[i - 1]:
            detector.new_session()
        elif i and segments[i] != segments[i - 1]:
            detector.new_segment()
        stamp = None if frames.timestamps is None else float(frames.timestamps[i])
        position = None if frames.positions is None else frames.positions[i]
        found.append(detector.update(np.asarray(rows[i : i + 1])[0], stamp, position))
    column = lambda name, dtype: np.array([getattr(loop, name) for loop in found], dtype)  # noqa: E731
    return Loops(drive, settings, detector.exclusion, detector.limits.rows.copy(), column("match", np.int64),
                 column("distance", np.float64), column("score", np.float64), column("accepted", bool))
