"""Thumbnails kept in a map (``seqvpr map build --thumbnails``): every frame's small JPEG (``seqvpr.data.thumbnails``)
in one file, ``thumbnails.bin``, with ``thumbnails_offsets.npy`` [N + 1] saying where each starts (an empty entry
for a frame without an image). They are map files like the rows (sealed with their digests, in the identity), so a
robot's node can show what it matched where the source images are not (a map built from a bag, a map copied to
the robot). ``map add`` to such a map is refused (its new frames would have none): build it again."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from seqvpr.arrays import load_npy

THUMBNAILS_FILE, OFFSETS_FILE = "thumbnails.bin", "thumbnails_offsets.npy"


def write_map_thumbnails(folder: Path, images: Sequence[str] | None, tick: Callable[[int], None] | None = None
                         ) -> int:
    """Each frame's thumbnail into ``folder``'s two files; how many frames got one."""
    from seqvpr.data.thumbnails import cached_thumbnail, thumbnail_cache

    cache, offsets, made = thumbnail_cache(), [0], 0
    with open(folder / THUMBNAILS_FILE, "wb") as out:
        for image in images or []:
            cached = cached_thumbnail(image, cache)
            data = cached.read_bytes() if cached is not None else b""
            out.write(data)
            offsets.append(offsets[-1] + len(data))
            made += bool(data)
            if tick:
                tick(1)
    np.save(folder / OFFSETS_FILE, np.asarray(offsets, dtype=np.int64))
    return made


def has_thumbnails(folder: str | Path) -> bool:
    return (Path(folder) / OFFSETS_FILE).is_file()


def map_thumbnail(folder: str | Path, row: int) -> bytes | None:
    """The JPEG bytes the map keeps for frame ``row`` (None: the map keeps none, or none for this frame)."""
    folder = Path(folder)
    if not has_thumbnails(folder):
        return None
    offsets = load_npy(folder / OFFSETS_FILE, mmap_mode="r")
    start, stop = int(offsets[row]), int(offsets[row + 1])
    if stop <= start:
        return None
    with open(folder / THUMBNAILS_FILE, "rb") as handle:
        handle.seek(start)
        return handle.read(stop - start)
