"""What a traversal is, as a record to compare: its source, the frames it holds (the split) and a digest of its
content (descriptors, frame numbers, segments, positions, image names and sizes). A model trained on one traversal
records this, so a run that would reuse the model on other data (another file, another split) can tell."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.data.traversal import Traversal
from seqvpr.identity import ALGORITHM, file_digest


def frame_span(frame_index: np.ndarray) -> str:
    """The frames a traversal holds, as its source numbers them: ``START:STOP`` when contiguous, else
    ``START:STOP (N frames)``."""
    first, last = int(frame_index[0]), int(frame_index[-1])
    contiguous = len(frame_index) == last - first + 1 and bool(np.all(np.diff(frame_index) == 1))
    return f"{first}:{last + 1}" + ("" if contiguous else f" ({len(frame_index)} frames)")


def content_digest(traversal: Traversal) -> str:
    """A digest of the frames' content: arrays' bytes (with dtype and shape) and, for images, each file's name and
    size (the images themselves are not read: a name's bytes changing in place at the same size is not seen)."""
    digest = hashlib.new(ALGORITHM)
    arrays = {"frame_index": traversal.frame_index, "segment_ids": traversal.segment_ids,
              "descriptors": traversal.descriptors, "positions": traversal.positions}
    for name, array in arrays.items():
        if array is not None:
            array = np.ascontiguousarray(array)
            digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
            digest.update(memoryview(array).cast("B"))
    for path in traversal.image_paths or ():
        digest.update(f"{path}:{_size(path)}\n".encode())
    return f"{ALGORITHM}:{digest.hexdigest()}"


def _size(path: Path) -> int:
    try:
        return Path(path).stat().st_size
    except OSError:
        return -1


def traversal_record(traversal: Traversal) -> dict[str, Any]:
    """The record of a traversal: source, its file's digest (None for a folder or a source in memory), the frames
    held and the content digest; two records are equal only for the same data and split."""
    source = Path(traversal.source) if traversal.source else None
    return {
        "source": traversal.source,
        "file": file_digest(source) if source is not None and source.is_file() else None,
        "frames": frame_span(traversal.frame_index),
        "content": content_digest(traversal),
    }


def same_data(recorded: dict[str, Any], current: dict[str, Any]) -> bool:
    """Whether two traversal records describe the same frames with the same content (the file's path and digest
    may differ: a copied or re-written file of the same content is the same data)."""
    return all(recorded.get(key) == current.get(key) for key in ("frames", "content"))
