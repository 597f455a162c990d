"""A map's frame names, read where they are needed: ``names.txt`` (one UTF-8 name a line) memory-mapped, each line
found through ``names_offsets.npy`` (the byte offset of every line start, and the file's size), so opening a map
of ten million frames reads neither the names nor a Python object per frame. A map written before the offsets
file existed has its lines found by one scan of the file."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.errors import SeqvprError

NAMES_FILE, OFFSETS_FILE = "names.txt", "names_offsets.npy"


def name_offsets(names: Sequence[str]) -> np.ndarray:
    """The byte offsets [N + 1] of each name's line in ``names.txt`` as ``write_names`` writes it."""
    lengths = np.fromiter((len(n.encode()) + 1 for n in names), dtype=np.int64, count=len(names))
    return np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)


def write_names(names: Sequence[str], open_file: Callable[[str], Any]) -> None:
    """``names.txt`` and its ``names_offsets.npy``, each to ``open_file(name)`` (a binary handle), the names encoded
    65,536 at a time (names are checked to hold no line separator first)."""
    with open_file(NAMES_FILE) as handle:
        for start in range(0, len(names), 65_536):
            handle.write("".join(f"{n}\n" for n in names[start : start + 65_536]).encode())
    with open_file(OFFSETS_FILE) as handle:
        np.save(handle, name_offsets(names))


class FrameNames(Sequence[str]):
    """The names ``[first, last)`` of a map's ``names.txt``, decoded one at a time on access."""

    def __init__(self, data: np.ndarray, offsets: np.ndarray, first: int = 0, last: int | None = None) -> None:
        self.data, self.offsets = data, offsets
        self.first, self.last = first, len(offsets) - 1 if last is None else last

    def __len__(self) -> int:
        return self.last - self.first

    def __getitem__(self, key):
        if isinstance(key, slice):
            start, stop, step = key.indices(len(self))
            if step != 1:
                return tuple(self[i] for i in range(start, stop, step))
            return FrameNames(self.data, self.offsets, self.first + start, self.first + max(start, stop))
        row = int(key) + (len(self) if int(key) < 0 else 0)
        if not 0 <= row < len(self):
            raise IndexError(f"frame name {key} of {len(self)}")
        lo, hi = int(self.offsets[self.first + row]), int(self.offsets[self.first + row + 1])
        return bytes(self.data[lo : hi - 1]).decode()

    def __iter__(self) -> Iterator[str]:
        return (self[i] for i in range(len(self)))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and len(other) == len(self) and all(a == b for a, b in zip(self, other))

    __hash__ = None  # type: ignore[assignment]


class FramePaths(Sequence[Path]):
    """The frames' names as paths (an image map's ``image_paths``), made on access."""

    def __init__(self, names: FrameNames) -> None:
        self.names = names

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, key):
        picked = self.names[key]
        return FramePaths(picked) if isinstance(picked, FrameNames) else \
            tuple(Path(n) for n in picked) if isinstance(picked, tuple) else Path(picked)

    def __iter__(self) -> Iterator[Path]:
        return (Path(n) for n in self.names)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and len(other) == len(self) and all(a == b for a, b in zip(self, other))

    __hash__ = None  # type: ignore[assignment]


def open_names(folder: Path, count: int) -> FrameNames | None:
    """The map's frame names memory-mapped (None without ``names.txt``); one line if they do not number ``count``
    or the offsets do not fit the file."""
    from seqvpr.arrays import load_npy

    path = folder / NAMES_FILE
    if not path.is_file():
        return None
    size = path.stat().st_size
    data = np.memmap(path, dtype=np.uint8, mode="r") if size else np.zeros(0, np.uint8)
    if (folder / OFFSETS_FILE).is_file():
        offsets = load_npy(folder / OFFSETS_FILE, mmap_mode="r")
    else:  # a map written before the offsets file: one scan for the line ends
        offsets = np.concatenate([[0], np.flatnonzero(np.asarray(data) == 10) + 1]).astype(np.int64)
    if offsets.ndim != 1 or len(offsets) != count + 1:
        raise SeqvprError(f"{path}: {max(len(offsets) - 1, 0)} names for {count} frames")
    if int(offsets[0]) != 0 or int(offsets[-1]) != size or (count and not np.all(np.diff(offsets) >= 1)):
        raise SeqvprError(f"{folder / OFFSETS_FILE}: does not fit {path} (rebuild the map)")
    return FrameNames(data, offsets)
