"""SeqSLAM's local contrast enhancement of the distance matrix (OpenSeqSLAM / OpenSeqSLAM2), as a ``WindowScorer``
wrapper beside the kernel.

Each frame distance is standardised against the reference frames around it, for the same query frame:
``e[i, r] = (d[i, r] - mean_w d[i, .]) / max(std_w d[i, .], eps)`` over the ``window`` reference frames centred on
r (OpenSeqSLAM2's ``r_window``, default 10), clipped to r's segment. A place that looks like every place nearby (a
long wall, a tunnel) no longer wins by being uniformly close; what stands out locally does. The enhanced matrix
then goes to the inner scorer (the kernel's constant-velocity windows, with SeqSLAM's velocity sweep from the
spec's velocities, or the adaptive matcher), on the same blocks: a reference chunk only needs ``window // 2``
more frames of halo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from seqvpr.errors import SeqvprError
from seqvpr.sequences.matching import WindowScorer, max_span, sequence_rows
from seqvpr.sequences.windows import SequenceSpec, segment_bounds

CONTRAST_WINDOW = 10  # OpenSeqSLAM2's default r_window
MIN_STD = 1e-6  # a flat neighbourhood (identical frames) is not divided by zero


def enhance_contrast(d: torch.Tensor, reference_segments: np.ndarray, window: int = CONTRAST_WINDOW) -> torch.Tensor:
    """Frame distances [n_query, n_reference] standardised along the reference axis over ``window`` frames centred
    on each reference frame, inside its segment (float64 sums, so long rows lose no precision)."""
    if window < 2:
        raise SeqvprError(f"the contrast window must be at least 2 frames, got {window}")
    seg_start, seg_end = segment_bounds(np.asarray(reference_segments))
    n = d.shape[1]
    r = np.arange(n)
    lo = torch.as_tensor(np.maximum(seg_start, r - window // 2), device=d.device)
    hi = torch.as_tensor(np.minimum(seg_end, r - window // 2 + window), device=d.device)
    wide = d.double()
    zero = torch.zeros((d.shape[0], 1), dtype=torch.float64, device=d.device)
    sums = torch.cat([zero, wide.cumsum(1)], 1)
    squares = torch.cat([zero, (wide * wide).cumsum(1)], 1)
    count = (hi - lo).double()
    mean = (sums[:, hi] - sums[:, lo]) / count
    variance = ((squares[:, hi] - squares[:, lo]) / count - mean * mean).clamp_(min=0)
    return ((wide - mean) / variance.sqrt().clamp_(min=MIN_STD)).to(d.dtype)


@dataclass(frozen=True)
class ContrastScorer:
    """Window distances over the contrast-enhanced matrix: ``inner`` (None: the kernel) scores the enhanced rows."""

    window: int = CONTRAST_WINDOW
    inner: WindowScorer | None = None

    def span(self, spec: SequenceSpec) -> int:
        inner = self.inner.span(spec) if self.inner is not None else max_span(spec)
        return inner + self.window // 2 + 1

    def __call__(self, d: torch.Tensor, rows: np.ndarray, query_starts: np.ndarray, reference_segments: np.ndarray,
                 spec: SequenceSpec, inplace: bool = False) -> torch.Tensor:
        enhanced = enhance_contrast(d, reference_segments, self.window)
        score = self.inner if self.inner is not None else sequence_rows
        return score(enhanced, rows, query_starts, reference_segments, spec, inplace=True)


@dataclass(frozen=True)
class ConeScorer:
    """OpenSeqSLAM2's cone search: from the anchor frame's reference j, query frame k of the window may match any
    reference frame between the slowest and the fastest velocity's line (``spec.velocities``' min and max), inside
    j's segment; the window's distance is the mean over k of the best frame in that range. With one velocity it is
    the kernel's straight line."""

    def span(self, spec: SequenceSpec) -> int:
        return int(np.ceil(max(spec.velocities) * (spec.length - 1))) + 1

    def __call__(self, d: torch.Tensor, rows: np.ndarray, query_starts: np.ndarray, reference_segments: np.ndarray,
                 spec: SequenceSpec, inplace: bool = False) -> torch.Tensor:
        from seqvpr.sequences.adaptive import shifted_min

        low, high = min(spec.velocities), max(spec.velocities)
        starts = torch.as_tensor(np.asarray(query_starts, dtype=np.int64), device=d.device)
        reach = int(np.ceil(high * max(spec.offset, spec.length - 1 - spec.offset))) + 1
        total = torch.zeros((len(starts), d.shape[1]), dtype=d.dtype, device=d.device)
        for k in range(spec.length):
            offset = k - spec.offset
            ends = sorted((int(np.floor(low * offset + 0.5)), int(np.floor(high * offset + 0.5))))
            row = d.index_select(0, starts + k)
            total += shifted_min(row, ends[0], ends[1], reference_segments, reach)
        return total.div_(spec.length)
