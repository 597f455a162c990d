"""SeqSLAM beside the kernel (OpenSeqSLAM / OpenSeqSLAM2): local contrast enhancement of the distance matrix as a
``WindowScorer`` wrapper, and OpenSeqSLAM2's cone and hybrid searches as scorers.

Each frame distance is standardised against the reference frames around it, for the same query frame:
``e[i, r] = (d[i, r] - mean_w d[i, .]) / max(std_w d[i, .], eps)`` over the ``window`` reference frames centred on
r (OpenSeqSLAM2's ``r_window``, default 10), clipped to r's segment. A place that looks like every place nearby (a
long wall, a tunnel) no longer wins by being uniformly close; what stands out locally does. The enhanced matrix
then goes to the inner scorer (the kernel's constant-velocity windows, with SeqSLAM's velocity sweep from the
spec's velocities, or the adaptive matcher), on the same blocks: a reference chunk only needs ``window // 2``
more frames of halo.

The cone and hybrid searches vote with each query frame's single-image best match over the whole reference, so
they are bound to the traversals once (``prepare``, one single-image pass) and to each block's frames (``locate``)
before scoring; their straight trajectories are OpenSeqSLAM2's velocity grid (``velocity_grid``), drawn as the
kernel draws a velocity's window.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from seqvpr.errors import SeqvprError, SettingError
from seqvpr.sequences.matching import WindowScorer, max_span, sequence_rows
from seqvpr.sequences.windows import MAX_VELOCITIES, SequenceSpec, segment_bounds, velocity_steps, window_starts

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

    def trajectory_velocities(self, spec: SequenceSpec) -> tuple[float, ...] | None:
        """The straight trajectories the inner scorer chooses among (the kernel: ``spec.velocities``)."""
        from seqvpr.sequences.correspondences import trajectory_velocities

        return trajectory_velocities(self.inner, spec)

    def prepare(self, *traversals) -> ContrastScorer:
        """The inner scorer bound to the whole traversals, where it needs them (hybrid search)."""
        return replace(self, inner=self.inner.prepare(*traversals)) if hasattr(self.inner, "prepare") else self

    def locate(self, query_frames: np.ndarray, reference_first: int) -> ContrastScorer:
        """The inner scorer bound to one block's frames, where it needs them (hybrid search)."""
        if not hasattr(self.inner, "locate"):
            return self
        return replace(self, inner=self.inner.locate(query_frames, reference_first))

    def __call__(self, d: torch.Tensor, rows: np.ndarray, query_starts: np.ndarray, reference_segments: np.ndarray,
                 spec: SequenceSpec, inplace: bool = False) -> torch.Tensor:
        enhanced = enhance_contrast(d, reference_segments, self.window)
        score = self.inner if self.inner is not None else sequence_rows
        return score(enhanced, rows, query_starts, reference_segments, spec, inplace=True)


def velocity_grid(spec: SequenceSpec) -> tuple[float, ...]:
    """OpenSeqSLAM2's cone and hybrid velocities: every distinct straight trajectory between the slowest and the
    fastest of ``spec.velocities``, ``k / h`` for whole k from round(h * v_min) to round(h * v_max), with h the
    window's frames on its longer side of the anchor (``d_s // 2`` for a centred window); its ``v_step`` is unused."""
    h = max(spec.offset, spec.length - 1 - spec.offset)
    if h == 0:
        return (1.0,)
    low, high = (int(np.floor(h * v + 0.5)) for v in (min(spec.velocities), max(spec.velocities)))
    if high - max(low, 1) + 1 > MAX_VELOCITIES:
        raise SettingError(f"{{velocities}} {min(spec.velocities):g}:{max(spec.velocities):g} with {{seq_len}} {spec.length}: "
                          f"{high - max(low, 1) + 1} trajectories, at most {MAX_VELOCITIES} (narrow the range or "
                          "shorten -L)")
    return tuple(k / h for k in range(max(low, 1), high + 1)) or (1.0,)


def grid_trajectories(spec: SequenceSpec, reference_segments: np.ndarray, device) -> list[torch.Tensor]:
    """The grid's straight trajectories in a block: per velocity, the reference frame each query frame of the window
    meets from anchor column r, [n_reference, L] (-1 where the trajectory leaves r's segment)."""
    frames = []
    for velocity in velocity_grid(spec):
        steps = velocity_steps(spec.length, velocity)
        starts = window_starts(reference_segments, int(steps[-1]) + 1, int(steps[spec.offset]), spec.boundary)
        frames.append(torch.as_tensor(np.where(starts[:, None] >= 0, starts[:, None] + steps[None, :], -1),
                                      device=device))
    return frames


@dataclass(frozen=True, eq=False)
class BestFrames:
    """Each query frame's single-image best reference row over the whole reference (SeqSLAM's ``bestRs``, from the
    raw frame distances), the votes of the cone and hybrid searches; bound by ``prepare``, placed by ``locate``."""

    best: np.ndarray | None = None  # [n_query] global reference rows
    local: np.ndarray | None = None  # [rows of a block's d] the same rows, relative to the block's first column

    def prepare(self, query: torch.Tensor, reference, query_segments: np.ndarray, reference_segments: np.ndarray,
                memory_budget: int | None):
        from seqvpr.sequences.matching import sequence_topk

        top = sequence_topk(query, reference, SequenceSpec(1), 1, query_segments, reference_segments,
                            memory_budget=memory_budget)
        return replace(self, best=top.indices[:, 0])

    def locate(self, query_frames: np.ndarray, reference_first: int):
        if self.best is None:
            raise SeqvprError("the cone and hybrid searches need each query frame's best match: run them through "
                              "sequence_topk (which prepares them), not on a bare block")
        return replace(self, local=self.best[np.asarray(query_frames)] - reference_first)

    def window_best(self, query_starts: np.ndarray, spec: SequenceSpec, device) -> torch.Tensor:
        """[n_windows, L]: the best reference (block column) of each query frame of each window."""
        if self.local is None:
            raise SeqvprError("the cone and hybrid searches are scored block by block after locate()")
        frames = np.asarray(query_starts, dtype=np.int64)[:, None] + np.arange(spec.length)[None, :]
        return torch.as_tensor(self.local[frames], device=device)

    def span(self, spec: SequenceSpec) -> int:
        return max_span(replace(spec, velocities=velocity_grid(spec)))


@dataclass(frozen=True, eq=False)
class ConeScorer(BestFrames):
    """OpenSeqSLAM2's cone search: from anchor reference r, query frame k of the window may take any reference
    frame the grid's trajectories meet at k (a cone between the slowest and the fastest); the window's distance is
    ``1 - (frames whose single-image best match lies in the cone) / L``. It counts votes and reads no distance, as
    OpenSeqSLAM2's does; +inf where no trajectory stays in r's segment."""

    def __call__(self, d: torch.Tensor, rows: np.ndarray, query_starts: np.ndarray, reference_segments: np.ndarray,
                 spec: SequenceSpec, inplace: bool = False) -> torch.Tensor:
        best = self.window_best(query_starts, spec, d.device)
        paths = grid_trajectories(spec, reference_segments, d.device)
        votes = torch.zeros((len(best), d.shape[1]), dtype=d.dtype, device=d.device)
        for k in range(spec.length):
            hit = torch.zeros(votes.shape, dtype=torch.bool, device=d.device)
            for frames in paths:
                hit |= (frames[:, k][None, :] == best[:, k][:, None]) & (frames[:, k] >= 0)[None, :]
            votes += hit.to(d.dtype)
        score = 1 - votes / spec.length
        usable = torch.stack([frames[:, 0] >= 0 for frames in paths]).any(0)
        return score.masked_fill_(~usable[None, :], float("inf"))


@dataclass(frozen=True, eq=False)
class HybridScorer(BestFrames):
    """OpenSeqSLAM2's hybrid search: the grid's straight trajectories (as the cone's), each kept only if it passes
    through the single-image best match of some frame of the window (any frame, at any position); the window's
    distance is the best kept trajectory's mean distance, +inf where none is kept. Wrapped in ``ContrastScorer``
    it reads the contrast-enhanced distances, as OpenSeqSLAM2's does."""

    def trajectory_velocities(self, spec: SequenceSpec) -> tuple[float, ...]:
        """The grid's velocities: a match is scored by one of their trajectories."""
        return velocity_grid(spec)

    def __call__(self, d: torch.Tensor, rows: np.ndarray, query_starts: np.ndarray, reference_segments: np.ndarray,
                 spec: SequenceSpec, inplace: bool = False) -> torch.Tensor:
        best = self.window_best(query_starts, spec, d.device)
        n_w, n_r = len(best), d.shape[1]
        member = torch.zeros((n_w, n_r + 1), dtype=torch.bool, device=d.device)  # column n_r: "outside"
        member.scatter_(1, torch.where((best >= 0) & (best < n_r), best, n_r), True)
        member[:, n_r] = False
        result = torch.full((n_w, n_r), float("inf"), dtype=d.dtype, device=d.device)
        for velocity, frames in zip(velocity_grid(spec), grid_trajectories(spec, reference_segments, d.device)):
            kept = torch.zeros((n_w, n_r), dtype=torch.bool, device=d.device)
            for k in range(spec.length):
                kept |= member[:, torch.where(frames[:, k] >= 0, frames[:, k], n_r)]
            line = sequence_rows(d, rows, query_starts, reference_segments, replace(spec, velocities=(velocity,)),
                                 inplace=False)
            result = torch.minimum(result, line.masked_fill(~kept, float("inf")))
        return result
