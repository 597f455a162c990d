"""Sequence matching one query frame at a time: window means along the diagonals of the last L frames.

With causal windows the sequence distance of the window ending at reference frame r after query frame t is
``(1/L) sum_k d[t - k, r - k]``. The last L rows of frame distances are kept in a ring (float32, as measured; the
newest written in place by the distance pass), and each step sums every window's L terms along its diagonal in
float64, oldest first, fused with the running top-K: one pass over L x N values and nothing of the map's size
written. The results equal ``sequence_topk`` with ``SequenceSpec(L, "causal")`` (``drop`` boundaries) frame for
frame, bit for bit the running partial sums the localiser kept before.
"""

from __future__ import annotations

import numpy as np

from seqvpr import sequences
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.sequences.windows import window_starts


class DiagonalSums:
    """Causal window distances after each query frame, from the frame distances [N] of that frame alone.

    ``reference_segments`` decide which reference windows exist (a window never spans a segment break); a query
    segment break or a restart is ``reset()``: the next L - 1 frames then have no window (warming up). A step is
    ``next_row()`` (the ring's row to measure the new frame's distances into), then ``push`` or ``push_topk``; or the
    frame's dot products measured into ``next_row()``, then ``push_dots_topk``.
    """

    def __init__(self, reference_segments: np.ndarray, length: int) -> None:
        if length < 1:
            raise SettingError(f"{{seq_len}} must be a positive integer, got {length}")
        segments = np.asarray(reference_segments)
        self.length = length
        self.window_exists = window_starts(segments, length, length - 1, "drop") >= 0
        self.ring = np.zeros((length, len(segments)), dtype=np.float32)  # slot count % L: the frame count's row
        self.means: np.ndarray | None = None  # push's result, made on its first call and reused
        self.count = 0

    def reset(self) -> None:
        """Forget the frames so far (a new query segment, a kidnapping, a new drive)."""
        self.count = 0

    def next_slot(self) -> int:
        """The ring's row that the next frame's distances go into (the oldest frame's, no longer needed)."""
        return self.count % self.length

    def next_row(self) -> np.ndarray:
        """``ring[next_slot()]`` [N]."""
        return self.ring[self.next_slot()]

    def _enter(self, distances: np.ndarray) -> int | None:
        """Take one frame's distances (copied into the ring unless measured into ``next_row``); the slot of the
        newest row once L frames have come, else None."""
        row = self.next_row()
        if distances.shape != row.shape:
            raise SeqvprError(f"expected distances to the {row.shape[0]} reference frames, got shape {distances.shape}")
        if not np.shares_memory(distances, row):
            row[:] = distances
        self.count += 1
        return None if self.count < self.length else (self.count - 1) % self.length

    def push(self, distances: np.ndarray) -> np.ndarray | None:
        """Add one query frame's distances to every reference frame; the window means [N] (+inf where a window
        does not exist; a buffer the next push overwrites), or None while fewer than L frames have come since the
        start or the last reset."""
        from seqvpr.sequences._fused import diagonal_means_

        newest = self._enter(distances)
        if newest is None:
            return None
        if self.means is None:
            self.means = np.empty(self.ring.shape[1])
        diagonal_means_(self.ring, newest, self.window_exists, self.means)
        return self.means

    def push_topk(self, distances: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray] | None:
        """``push``, answering only the ``k`` best windows (rows, means ascending; ``best_k``'s rows and ties) in one
        pass that writes nothing of the map's size; None while warming up."""
        from seqvpr.sequences._fused import diagonal_topk

        newest = self._enter(distances)
        return None if newest is None else diagonal_topk(self.ring, newest, self.window_exists, min(k, self.ring.shape[1]))

    def push_dots_topk(self, query: np.ndarray, norms: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray] | None:
        """``push_topk`` of a frame whose dot products with every reference row were measured into ``next_row()``
        (``query`` the frame's row [D], ``norms`` the reference rows' squared norms [N], float32): they become its
        distances (``frame_distances_``'s values) in the pass that ranks the windows, one call a frame."""
        kernels = sequences._fused
        newest = self.next_slot()
        self.count += 1
        if self.count < self.length:
            kernels.frame_distances_(self.ring[newest], query, norms)
            return None
        return kernels.diagonal_topk(self.ring, newest, self.window_exists, min(k, self.ring.shape[1]), query, norms)

    def state(self) -> dict[str, np.ndarray]:
        """The ring and the frame count since the last reset (what ``load_state`` goes on from)."""
        return {"ring": self.ring.copy(), "count": np.array(self.count)}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        if "ring" not in state:
            raise SeqvprError("saved sums hold no ring of distance rows (a state of an older seqvpr): start afresh")
        if state["ring"].shape != self.ring.shape:
            raise SeqvprError(f"saved sums have shape {state['ring'].shape}, this map and L need {self.ring.shape}")
        self.ring[:] = state["ring"]
        self.count = int(state["count"])
