"""A grown map's sessions (what each ``map add`` appended; a map as built is one) and its descriptor rows in
parts: ``descriptors.npy`` as built, then one ``descriptors-NNN.npy`` per ``seqvpr map add``
(``seqvpr.maps.grow``), so adding frames writes and digests only the new rows. ``map.json``'s
``parts`` lists each file and its row count in order; ``PartRows`` reads them as one array, a slice or a row list
at a time, memory-mapped (never loaded whole).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.errors import SeqvprError

PART_FILE = "descriptors-{:03d}.npy"


class PartRows:
    """Arrays of one width laid end to end ([N, W] stored rows: floats or codes), indexed like one array."""

    ndim = 2

    def __init__(self, parts: Sequence[np.ndarray]) -> None:
        self.parts = list(parts)
        self.starts = np.cumsum([0] + [len(p) for p in self.parts])
        self.shape = (int(self.starts[-1]), int(self.parts[0].shape[1]))
        self.dtype = np.dtype(self.parts[0].dtype)

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def nbytes(self) -> int:
        return int(sum(p.nbytes for p in self.parts))

    def __getitem__(self, key: Any) -> np.ndarray:
        if isinstance(key, slice) and key.step in (None, 1):
            start, stop, _ = key.indices(len(self))
            pieces = [np.asarray(p[max(start - lo, 0) : min(stop, hi) - lo])
                      for p, lo, hi in zip(self.parts, self.starts[:-1], self.starts[1:]) if start < hi and stop > lo]
            return np.concatenate(pieces) if len(pieces) != 1 else np.array(pieces[0])
        rows = np.arange(len(self))[key]
        if np.ndim(rows) == 0:
            return self[int(rows) : int(rows) + 1][0]
        owner = np.searchsorted(self.starts, rows, side="right") - 1
        out = np.empty((len(rows), self.shape[1]), dtype=self.dtype)
        for number in np.unique(owner):
            picked = owner == number
            out[picked] = self.parts[number][rows[picked] - self.starts[number]]
        return out


def part_records(values: Any, count: int, where: Path) -> tuple[tuple[str, int], ...]:
    """``map.json``'s ``parts``, checked: plain file names with whole row counts that add up to the map's."""
    try:
        records = tuple((str(name), int(rows)) for name, rows in values)
    except (TypeError, ValueError) as error:
        raise SeqvprError(f"{where}: malformed parts ({error})") from None
    if not records or any(not is_plain_name(name) or rows < 1 for name, rows in records) or \
            sum(rows for _, rows in records) != count:
        raise SeqvprError(f"{where}: its parts {list(records)} do not hold the map's {count} rows")
    return records


def stored_parts(folder: Path, info: Any, load) -> PartRows:
    """The parts' stored rows (``load(name, shape, dtype)``: a checked memory map of one file), chained."""
    from seqvpr.maps.codes import stored_shape

    arrays = []
    for name, rows in info.parts:
        shape, dtype = stored_shape(info.dtype, rows, info.dim)
        arrays.append(load(name, shape, dtype))
    return PartRows(arrays)


def is_plain_name(name: object) -> bool:
    """A file name with no folder part (so it stays inside the folder that names it)."""
    return isinstance(name, str) and name not in ("", ".", "..") and "/" not in name and "\\" not in name \
        and "\0" not in name


def sessions_of(info: Any) -> list[dict[str, Any]]:
    """The map's sessions: those ``map add`` recorded, or, for a map as built, one holding all of its sources."""
    if info.sessions:
        return [dict(s) for s in info.sessions]
    return [{"name": "build", "first": 0, "frames": info.count, "sources": list(range(len(info.sources))),
             "added": info.created}]


def session_of_rows(info: Any, rows: np.ndarray) -> list[str]:
    """The name of the session each map row belongs to ("" for -1)."""
    sessions = sessions_of(info)
    firsts = np.array([s["first"] for s in sessions])
    owner = np.searchsorted(firsts, np.asarray(rows), side="right") - 1
    return [sessions[o]["name"] if r >= 0 else "" for o, r in zip(owner.tolist(), np.asarray(rows).tolist())]
