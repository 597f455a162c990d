"""Adaptive sequence matching: the query window aligned to a reference stretch without a constant velocity.

Where the kernel compares query frame k of a window with reference frame ``j - a + k`` (slope 1), the adaptive
matcher lets every query frame advance the reference by any step in ``[min_step, max_step]`` (0: the robot stood
still; 2: it drove twice as fast as on the reference run), a DTW-like alignment with slope constraints as in
AdaptSeq / CaseVPR's adaptive back-ends:

    S[i, j] = (1/L) min over paths r_0 <= ... <= r_{L-1}, r_a = j, r_k - r_{k-1} in steps, one reference segment,
              of sum_k d[q_k, r_k]

with ``a`` the window's anchor (its current frame, as the kernel reports). The default steps are 1..2: allowing 0
(a stop) lets a path dwell on one confusable reference frame, and measured worse on Nordland and on the demo world
(BENCHMARKS.md); give 0 where the query stops while the reference did not. It is computed for all columns at once
by a forward pass to the anchor and a backward pass from the window's end (``S = F_a + B_a - d_a``), so a block
costs about (L - 1) x steps passes over the block's frame distances. It plugs into the kernel's blocked top-K as a
``WindowScorer`` (same blocks, halos, segments and memory budget); steps ``(1, 1)`` give the kernel's distances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from seqvpr.errors import SeqvprError
from seqvpr.sequences.windows import SequenceSpec


@dataclass(frozen=True)
class AdaptiveScorer:
    """Window distances under non-constant velocity: each query frame moves the reference by a step in
    ``[min_step, max_step]``. Reference windows follow the ``drop`` rule (a path never leaves its segment)."""

    min_step: int = 1
    max_step: int = 2

    def __post_init__(self) -> None:
        if not (0 <= self.min_step <= self.max_step):
            raise SeqvprError(f"adaptive steps must satisfy 0 <= min <= max, got {self.min_step}..{self.max_step}")

    def span(self, spec: SequenceSpec) -> int:
        """Reference frames a path may cover: the halo a reference chunk needs on each side."""
        return self.max_step * (spec.length - 1) + 1

    def __call__(self, d: torch.Tensor, rows: np.ndarray, query_starts: np.ndarray, reference_segments: np.ndarray,
                 spec: SequenceSpec, inplace: bool = False) -> torch.Tensor:
        """Adaptive distances [len(query_starts), n_reference] of the windows starting at ``query_starts`` (rows of
        ``d``; ``rows`` is unused: the anchor is the window's ``spec.offset``-th frame, as the kernel's)."""
        starts = torch.as_tensor(np.asarray(query_starts, dtype=np.int64), device=d.device)
        frames = [d.index_select(0, starts + k) for k in range(spec.length)]
        same = same_segment_masks(reference_segments, self.max_step, d.device)
        a = spec.offset
        forward = frames[0]
        for k in range(1, a + 1):
            forward = frames[k] + steps_min(forward, self.min_step, self.max_step, same, +1)
        backward = frames[-1]
        for k in range(spec.length - 2, a - 1, -1):
            backward = frames[k] + steps_min(backward, self.min_step, self.max_step, same, -1)
        total = forward + backward - frames[a]
        return total.div_(spec.length)


def same_segment_masks(segments: np.ndarray, max_step: int, device: torch.device) -> list[torch.Tensor]:
    """For each step t, whether reference frame r and r - t lie in one segment (False where r - t < 0)."""
    seg = torch.as_tensor(np.asarray(segments, dtype=np.int64), device=device)
    out = []
    for t in range(max_step + 1):
        ok = torch.zeros(len(seg), dtype=torch.bool, device=device)
        ok[t:] = seg[t:] == seg[: len(seg) - t]
        out.append(ok)
    return out


def steps_min(values: torch.Tensor, low: int, high: int, same: list[torch.Tensor], direction: int) -> torch.Tensor:
    """``min_t values[:, r - t]`` (direction +1, paths arriving at r) or ``min_t values[:, r + t]`` (-1, paths
    leaving r) over steps t in [low, high] that stay inside a segment; +inf where none does."""
    n = values.shape[1]
    best = torch.full_like(values, float("inf"))
    for t in range(low, high + 1):
        if t >= n:
            break
        shifted = torch.full_like(values, float("inf"))
        if direction > 0:
            shifted[:, t:] = values[:, : n - t]
            shifted[:, ~same[t]] = float("inf")
        else:
            shifted[:, : n - t] = values[:, t:]
            shifted[:, : n - t][:, ~same[t][t:]] = float("inf")
        torch.minimum(best, shifted, out=best)
    return best


def adaptive_path(frame_distances: np.ndarray, reference: int, anchor: int, scorer: AdaptiveScorer,
                  reference_segments: np.ndarray) -> np.ndarray:
    """The reference frame of each of the window's L query frames on the best path through ``reference`` at the
    anchor (``frame_distances`` [L, n_reference]): the per-frame correspondences of one adaptive match."""
    length, n = frame_distances.shape
    seg = np.asarray(reference_segments)
    path = np.full(length, -1, dtype=np.int64)
    path[anchor] = reference
    for direction, ks in ((-1, range(anchor - 1, -1, -1)), (+1, range(anchor + 1, length))):
        costs = _side_costs(frame_distances, reference, anchor, scorer, seg, direction)
        r = reference
        for k in ks:
            options = [r + direction * t for t in range(scorer.min_step, scorer.max_step + 1)
                       if 0 <= r + direction * t < n and seg[r + direction * t] == seg[reference]]
            r = min(options, key=lambda c: (costs[k][c], abs(c - r)))
            path[k] = r
    return path


def _side_costs(d: np.ndarray, reference: int, anchor: int, scorer: AdaptiveScorer, seg: np.ndarray,
                direction: int) -> dict[int, np.ndarray]:
    """Per query frame k on one side of the anchor, the best cost of the rest of the path (towards that side's
    window end) from each reference frame: what a greedy walk outward from the anchor needs to be optimal."""
    length, n = d.shape
    ks = list(range(0, anchor)) if direction < 0 else list(range(anchor + 1, length))
    costs: dict[int, np.ndarray] = {}
    if not ks:  # no query frame on this side of the anchor (L = 1, or a causal window's end)
        return costs
    end = ks[0] if direction < 0 else ks[-1]
    current = d[end].astype(np.float64).copy()
    costs[end] = current
    order = ks[1:] if direction < 0 else ks[-2::-1]
    for k in order:
        nxt = np.full(n, np.inf)
        for t in range(scorer.min_step, scorer.max_step + 1):
            source = np.arange(n) + (-t if direction < 0 else t)  # where the path goes next, away from the anchor
            ok = (source >= 0) & (source < n)
            ok[ok] &= seg[source[ok]] == seg[np.arange(n)[ok]]
            nxt[ok] = np.minimum(nxt[ok], current[source[ok]])
        current = d[k] + nxt
        costs[k] = current
    return costs


def adaptive_rerank(query: torch.Tensor, reference, shortlist, spec: SequenceSpec, scorer: AdaptiveScorer,
                    query_segments: np.ndarray, reference_segments: np.ndarray, k: int):
    """A shortlist's candidates re-ordered by adaptive distance (CaseVPR's hierarchy: sequence-descriptor start
    points, then adaptive frame matching inside each candidate stretch), through the one re-ranking
    (``rerank.rerank_candidates``). Each candidate's reachable stretch is cut from the reference and the stretches
    are scored together as separate segments, so no path crosses two."""
    from seqvpr.sequences.matching import frame_distances, reference_rows
    from seqvpr.sequences.rerank import rerank_candidates
    from seqvpr.sequences.windows import window_frames, window_starts

    q_starts = window_starts(np.asarray(query_segments), spec.length, spec.offset, "drop")
    r_seg = np.asarray(reference_segments, dtype=np.int64)
    before, after = spec.offset * scorer.max_step, (spec.length - 1 - spec.offset) * scorer.max_step

    def adaptive_distances(rows: np.ndarray, anchors: np.ndarray) -> np.ndarray:
        values = np.full(anchors.shape, np.inf)
        for i, (row, picked) in enumerate(zip(rows, anchors)):
            candidates = picked[picked >= 0]
            if len(candidates) == 0:
                continue
            spans = [(max(0, c - before), min(len(r_seg), c + after + 1)) for c in candidates]
            frames_of = np.concatenate([np.arange(lo, hi) for lo, hi in spans])
            labels = np.concatenate([np.full(hi - lo, n) for n, (lo, hi) in enumerate(spans)]) * (r_seg.max() + 1) \
                + r_seg[frames_of]
            stretch = reference_rows(reference, frames_of, query)
            frames = torch.as_tensor(window_frames(q_starts[row : row + 1], spec.length)[0])
            scored = scorer(frame_distances(query[frames], stretch), np.zeros(1, np.int64), np.zeros(1, np.int64),
                            labels, spec)[0].double().cpu().numpy()
            anchored = np.cumsum([0] + [hi - lo for lo, hi in spans[:-1]]) + (candidates - [lo for lo, _ in spans])
            values[i, picked >= 0] = scored[anchored]
        return values

    return rerank_candidates(shortlist, q_starts >= 0, k, adaptive_distances)

