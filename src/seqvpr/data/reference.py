"""What a matcher matches against: a ``Reference``. A traversal in memory, a saved map (its frame table, rows
memory-mapped or coded) and a sharded map (rows read through its shards) all are one, so no code asks which it
holds: the matcher reads ``stored`` to know whether the rows are a saved map's (as the map normalised them, read a
chunk at a time) or in memory (normalised when matched). A traversal's rows are always in memory; a saved map knows
how it stores its own."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from seqvpr.data.traversal import Traversal


class Reference(Protocol):
    """Rows of frames in route order, with their segments and a frame table to report."""

    name: str
    source: str
    segment_ids: np.ndarray
    #: the rows: an array, a memory map, or any object whose slices and row lists are float arrays (coded rows)
    descriptors: object
    #: how a saved map stores the rows (None: in memory)
    stored: str | None

    def __len__(self) -> int: ...

    @property
    def dim(self) -> int: ...

    @property
    def plain_rows(self) -> bool: ...

    @property
    def frames(self) -> Traversal: ...

    #: the rows it answers for (a shard holds its neighbours' edges too, and answers for its own)
    @property
    def owned(self) -> slice: ...

    #: its saved nearest-neighbour index's record, if it has one
    @property
    def index(self) -> dict | None: ...
