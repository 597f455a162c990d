"""Sequence matching one query frame at a time: running sums along the diagonals of the last L frames.

With causal windows the sequence distance of the window ending at reference frame r after query frame t is
``(1/L) sum_k d[t - k, r - k]``. Each new row of frame distances extends every diagonal by one term, so keeping the
partial sums of the last 1..L terms makes a step O(L x N), never a recomputation of whole windows. The results
equal ``sequence_topk`` with ``SequenceSpec(L, "causal")`` (``drop`` boundaries) frame for frame.
"""

from __future__ import annotations

import numpy as np

from seqvpr.errors import SeqvprError
from seqvpr.sequences.windows import window_starts


class DiagonalSums:
    """Causal window distances [N] after each query frame, from the frame distances [N] of that frame alone.

    ``reference_segments`` decide which reference windows exist (a window never spans a segment break); a query
    segment break or a restart is ``reset()``: the next L - 1 frames then have no window (warming up).
    """

    def __init__(self, reference_segments: np.ndarray, length: int) -> None:
        if length < 1:
            raise SeqvprError(f"seq_len must be a positive integer, got {length}")
        segments = np.asarray(reference_segments)
        self.length = length
        self.window_exists = window_starts(segments, length, length - 1, "drop") >= 0
        self.partial = np.full((length, len(segments)), np.inf)  # row j: sum of the last j + 1 terms
        self.missing = np.flatnonzero(~self.window_exists)  # the few frames that end no window
        self.means = np.empty(len(segments))  # each step's result, reused: no allocation of the map's size a frame
        self.count = 0

    def reset(self) -> None:
        """Forget the frames so far (a new query segment, a kidnapping, a new drive)."""
        self.count = 0

    def push(self, distances: np.ndarray) -> np.ndarray | None:
        """Add one query frame's distances to every reference frame; the window means [N] (+inf where a window
        does not exist; a buffer the next push overwrites), or None while fewer than L frames have come since the
        start or the last reset."""
        p = self.partial
        if distances.shape != (p.shape[1],):
            raise SeqvprError(f"expected distances to the {p.shape[1]} reference frames, got shape {distances.shape}")
        for j in range(min(self.count, self.length - 1), 0, -1):  # longest first: row j - 1 is still last frame's
            np.add(p[j - 1, :-1], distances[1:], out=p[j, 1:])
            p[j, 0] = np.inf
        p[0] = distances
        self.count += 1
        if self.count < self.length:
            return None
        np.divide(p[self.length - 1], self.length, out=self.means)
        self.means[self.missing] = np.inf
        return self.means

    def state(self) -> dict[str, np.ndarray]:
        return {"partial": self.partial.copy(), "count": np.array(self.count)}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        if state["partial"].shape != self.partial.shape:
            raise SeqvprError(f"saved sums have shape {state['partial'].shape}, this map and L need {self.partial.shape}")
        self.partial[:] = state["partial"]
        self.count = int(state["count"])
