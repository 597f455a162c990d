"""The matching kernel: sequence distances between query and reference windows (SeqMatchNet Eq. 3/4).

The sequence distance between the windows of query i and reference j is the mean of the L order-aligned
Euclidean frame distances, ``S[i, j] = (1/L) sum_k d[qs_i + k, rs_j + k]``, where ``qs``/``rs`` are window
starts (see ``windows``). Matrices are laid out [n_query, n_reference]. Whole matrices are computed as sums along
shifted diagonals: on CPU by a fused in-place pass, elsewhere by one strided reduction; never by an
identity-kernel conv2d. Positions without a window hold +inf. ``sequence_topk`` builds the matrix block by block
within a memory budget and keeps only the K best references per query.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import torch

from seqvpr.errors import SeqvprError
from seqvpr.sequences.topk import TopKMerge
from seqvpr.results import TopK
from seqvpr.sequences.windows import SequenceSpec, require_windows, velocity_steps, window_frames, window_starts

ProgressFn = Callable[[int], None]


def unit_rows(rows: torch.Tensor, dim: int = 1, out: torch.Tensor | None = None) -> torch.Tensor:
    """Rows scaled to unit L2 norm along ``dim``, first divided by their largest magnitude so that float32 squares
    neither overflow (values near 1e19) nor underflow (near 1e-25): valid descriptors at any scale stay usable."""
    peak = rows.abs().amax(dim=dim, keepdim=True).clamp_min(torch.finfo(rows.dtype).tiny)
    scaled = torch.div(rows, peak, out=out)
    return torch.nn.functional.normalize(scaled, dim=dim, out=scaled if out is not None else None)


TINY32 = float(np.finfo(np.float32).tiny)  # unit_rows' clamp of the largest magnitude
EPS32 = float(np.float32(1e-12))  # torch's normalize clamps the norm at its eps, as a float32


def frame_distances(query: torch.Tensor, reference: torch.Tensor, workspace: Workspace | None = None) -> torch.Tensor:
    """Euclidean distances [n_query, n_reference] via one GEMM; clamped so rounding never gives NaN. On CPU the
    result may live in ``workspace``'s buffer (reused block after block)."""
    if query.shape[1] != reference.shape[1]:
        raise SeqvprError(
            f"descriptor dimensions differ: query has {query.shape[1]}, reference has {reference.shape[1]}"
        )
    if _fusable_gemm(query, reference):
        from seqvpr.sequences._fused import distances_from_dots_, squared_norms

        dots = workspace.matrix(len(query), len(reference), query) if workspace else None
        dots = torch.mm(query, reference.T, out=dots)
        distances_from_dots_(dots.numpy(), squared_norms(query.numpy()), squared_norms(reference.numpy()))
        return dots
    squared = torch.addmm(
        (query * query).sum(1, keepdim=True) + (reference * reference).sum(1)[None, :],
        query,
        reference.T,
        alpha=-2.0,
    )
    return squared.clamp_(min=1e-12).sqrt_()


class Workspace:
    """A buffer reused for the distance blocks of one top-K pass: a fresh large tensor per block costs its page
    faults every time (measured: a third of the GEMM's time at 1M references)."""

    def __init__(self) -> None:
        self._buffer: torch.Tensor | None = None

    def matrix(self, rows: int, columns: int, like: torch.Tensor) -> torch.Tensor:
        """A contiguous [rows, columns] tensor of ``like``'s dtype and device, from the buffer (grown if needed)."""
        size = rows * columns
        buffer = self._buffer
        if buffer is None or buffer.numel() < size or buffer.dtype != like.dtype or buffer.device != like.device:
            buffer = self._buffer = torch.empty(size, dtype=like.dtype, device=like.device)
        return buffer[:size].view(rows, columns)


def _fusable_gemm(query: torch.Tensor, reference: torch.Tensor) -> bool:
    """CPU float tensors without gradients: one GEMM, then norms, clamp and square root in one numba pass."""
    return (query.device.type == "cpu" and reference.device.type == "cpu" and query.dtype == reference.dtype
            and query.dtype in (torch.float32, torch.float64) and not (query.requires_grad or reference.requires_grad))


def aligned_sequence_distances(
    query_windows: torch.Tensor, reference_windows: torch.Tensor, frames: slice | None = None
) -> torch.Tensor:
    """Sequence distances of paired windows [..., L, D] -> [...]: the mean of order-aligned frame distances.

    The pairwise form of the kernel, for losses: differentiable, and the square root is clamped like
    ``frame_distances`` so identical windows give a finite (zero) gradient. ``frames`` picks a part of the
    window, e.g. the centre frame only.
    """
    if frames is not None:
        query_windows, reference_windows = query_windows[..., frames, :], reference_windows[..., frames, :]
    diff = query_windows - reference_windows
    return (diff * diff).sum(-1).clamp(min=1e-12).sqrt().mean(-1)


def window_means(frame_dist: torch.Tensor, spec: SequenceSpec, velocity: float = 1.0, *, inplace: bool = False) -> torch.Tensor:
    """Placed window means P [n, m]: ``P[r, j] = (1/L) sum_k d[r - a + k, j - c + step_k]`` or +inf if out of range.

    ``a`` is the query offset of ``spec`` and ``c`` the reference step at the current frame, so P holds each
    position's natural (unshifted) window; boundaries and segments are applied afterwards.
    """
    steps = velocity_steps(spec.length, velocity)
    a = spec.offset
    c = int(steps[a])
    if _can_fuse(frame_dist, steps, inplace):
        array = frame_dist.numpy()
        from seqvpr.sequences._fused import fused_window_means_

        fused_window_means_(array, spec.length, a)
        return frame_dist
    return _strided_window_means(frame_dist, steps, a, c)


def _can_fuse(frame_dist: torch.Tensor, steps: np.ndarray, inplace: bool) -> bool:
    """The fused CPU pass applies to contiguous CPU float matrices, slope 1, when the input may be overwritten."""
    return (
        inplace
        and frame_dist.device.type == "cpu"
        and frame_dist.dtype in (torch.float32, torch.float64)
        and frame_dist.is_contiguous()
        and not frame_dist.requires_grad
        and bool(np.array_equal(steps, np.arange(len(steps))))
    )


def _strided_window_means(d: torch.Tensor, steps: np.ndarray, a: int, c: int) -> torch.Tensor:
    """Window means with torch ops on any device: one strided reduction for slope 1, shifted sums otherwise."""
    n, m = d.shape
    length = len(steps)
    span = int(steps[-1]) + 1
    n1, m1 = n - length + 1, m - span + 1
    out = torch.full_like(d, float("inf"))
    if n1 <= 0 or m1 <= 0:
        return out
    d = d.contiguous()
    region = out[a : a + n1, c : c + m1]
    if np.array_equal(steps, np.arange(length)):
        s0, s1 = d.stride()
        diagonals = torch.as_strided(d, (n1, m1, length), (s0, s1, s0 + s1), d.storage_offset())
        region.copy_(diagonals.mean(-1))
        return out
    total = d[0:n1, int(steps[0]) : int(steps[0]) + m1].clone()
    for k in range(1, length):
        total = total + d[k : k + n1, int(steps[k]) : int(steps[k]) + m1]
    region.copy_(total / length)
    return out


def apply_window_starts(
    placed: torch.Tensor,
    rows: np.ndarray,
    query_starts: np.ndarray,
    reference_starts: np.ndarray,
    row_offset: int,
    column_offset: int,
) -> torch.Tensor:
    """Sequence distances for the given rows of ``placed`` honouring window starts (boundary mode, segments).

    Row ``rows[i]`` of ``placed`` holds the natural window of query i. A query whose start differs from natural
    takes the row of the frame whose natural window is its shifted window (or +inf without a window); columns
    likewise. Source rows and columns are always natural, so the fix-ups never read each other's output.
    """
    result = placed[rows[0] : rows[-1] + 1] if _is_range(rows) else placed[torch.as_tensor(rows)]
    _fix_windows(result, placed, 0, rows, query_starts, row_offset)
    _fix_windows(result, result, 1, np.arange(len(reference_starts)), reference_starts, column_offset)
    return result


def _is_range(rows: np.ndarray) -> bool:
    return len(rows) > 0 and bool(np.all(np.diff(rows) == 1))


def _fix_windows(
    result: torch.Tensor, source: torch.Tensor, dim: int, positions: np.ndarray, starts: np.ndarray, offset: int
) -> None:
    """Along ``dim``, replace each non-natural entry by the natural one of its window start, or +inf if none."""
    bad = np.flatnonzero(starts != positions - offset)
    if len(bad) == 0:
        return
    has_window = starts[bad] >= 0
    shifted, dropped = bad[has_window], bad[~has_window]
    device = result.device
    if len(shifted):
        picked = source.index_select(dim, torch.as_tensor(starts[shifted] + offset, device=device))
        result.index_copy_(dim, torch.as_tensor(shifted, device=device), picked)
    if len(dropped):
        result.index_fill_(dim, torch.as_tensor(dropped, device=device), float("inf"))


def sequence_distance_matrix(
    frame_dist: torch.Tensor,
    spec: SequenceSpec,
    query_segments: np.ndarray | None = None,
    reference_segments: np.ndarray | None = None,
    *,
    inplace: bool = False,
) -> torch.Tensor:
    """Full sequence-distance matrix [n_query, n_reference] (+inf where a window is missing).

    With several velocities the minimum over them is taken (SeqSLAM-style trajectory search). ``inplace`` lets
    the CPU fast path overwrite ``frame_dist`` (and return it).
    """
    n_q, n_r = frame_dist.shape
    q_starts = window_starts(_segments(query_segments, n_q), spec.length, spec.offset, spec.boundary)
    return sequence_rows(frame_dist, np.arange(n_q), q_starts, _segments(reference_segments, n_r), spec, inplace)


def _segments(segment_ids: np.ndarray | None, n: int) -> np.ndarray:
    return np.zeros(n, np.int64) if segment_ids is None else np.asarray(segment_ids)


def sequence_rows(
    d: torch.Tensor, rows: np.ndarray, q_starts: np.ndarray, r_seg: np.ndarray, spec: SequenceSpec, inplace: bool
) -> torch.Tensor:
    """Sequence distances of the queries at ``rows`` of d (starts index rows of d), minimum over velocities."""
    best: torch.Tensor | None = None
    for number, velocity in enumerate(spec.velocities):
        steps = velocity_steps(spec.length, velocity)
        c = int(steps[spec.offset])
        r_starts = window_starts(r_seg, int(steps[-1]) + 1, c, spec.boundary)
        placed = window_means(d, spec, velocity, inplace=inplace and number == len(spec.velocities) - 1)
        current = apply_window_starts(placed, rows, q_starts, r_starts, spec.offset, c)
        best = current if best is None else torch.minimum(best, current)
    assert best is not None
    return best


class WindowScorer(Protocol):
    """Turns a block's frame distances into window distances: the kernel's constant velocity by default, or another
    matcher beside it (``adaptive.AdaptiveScorer``); ``span`` is the reference frames one window may cover. A scorer
    that needs more than its block may also define ``prepare(query, reference, query_segments, reference_segments,
    memory_budget)`` (called once with the whole traversals) and ``locate(query_frames, reference_first)`` (called
    per block with its query frames and first reference row), each returning the bound scorer (SeqSLAM's hybrid)."""

    def span(self, spec: SequenceSpec) -> int: ...

    def __call__(self, d: torch.Tensor, rows: np.ndarray, query_starts: np.ndarray, reference_segments: np.ndarray,
                 spec: SequenceSpec, inplace: bool = False) -> torch.Tensor: ...


def max_span(spec: SequenceSpec) -> int:
    """Reference frames covered by the fastest velocity's window."""
    return max(int(velocity_steps(spec.length, v)[-1]) + 1 for v in spec.velocities)


def sequence_topk(
    query: torch.Tensor,
    reference: ReferenceRows,
    spec: SequenceSpec,
    k: int,
    query_segments: np.ndarray | None = None,
    reference_segments: np.ndarray | None = None,
    *,
    memory_budget: int | None = None,
    progress: ProgressFn | None = None,
    chunk: int | None = None,
    scorer: WindowScorer | None = None,
    limits: np.ndarray | None = None,
) -> TopK:
    """Top-K references per query by sequence distance, computed in query blocks (with a halo of L - 1 rows) and,
    when the budget asks for it, reference chunks (with a halo of the longest window on both sides).

    With ``memory_budget`` (bytes) no block's distance matrix exceeds the budget, so the full
    n_query x n_reference matrix is never held. ``reference`` is a tensor or an array of rows; an ``np.memmap``
    is read one chunk at a time (converted to the query's dtype and device), so a map on disk is never loaded
    whole; ``chunk`` fixes the reference frames per chunk. Descriptors are used as given (normalise them before).
    ``limits`` [n_query] (non-decreasing) keeps query i to windows ending before row ``limits[i]`` (a drive against
    its past: loop closures), each block reading up to its largest: the triangle, never the square.
    """
    n_q, n_r = len(query), len(reference)
    q_seg, r_seg = _segments(query_segments, n_q), _segments(reference_segments, n_r)
    q_starts = window_starts(q_seg, spec.length, spec.offset, spec.boundary)
    require_windows(q_starts, spec.length, "query", q_seg)
    require_windows(window_starts(r_seg, max_span(spec), 0, spec.boundary), max_span(spec), "reference", r_seg)
    if hasattr(scorer, "prepare"):
        scorer = scorer.prepare(query, reference, q_seg, r_seg, memory_budget)
    k = min(k, n_r)
    indices = np.full((n_q, k), -1, dtype=np.int64)
    distances = np.full((n_q, k), np.inf, dtype=np.float64)
    rows, columns = block_shape(n_q, n_r, spec, query.element_size(), memory_budget, in_memory=_in_memory(reference))
    if chunk is not None:
        columns = max(1, min(int(chunk), n_r))
    limits = None if limits is None else check_limits(limits, n_q, n_r)
    for begin in range(0, n_q, rows):
        end = min(begin + rows, n_q)
        starts = q_starts[begin:end]
        if (starts >= 0).any():
            values, picked = _chunked_topk(query, reference, spec, starts, r_seg, k, columns, scorer,
                                           None if limits is None else limits[begin:end])
            picked[~np.isfinite(values)] = -1
            indices[begin:end], distances[begin:end] = picked, values
        if progress is not None:
            progress(end - begin)
    return TopK(indices, distances, q_starts >= 0)


#: reference rows ``sequence_topk`` reads: a tensor, an array (an ``np.memmap`` is read chunk by chunk), or any
#: object whose slices are float arrays (a saved map's coded rows)
ReferenceRows = torch.Tensor | np.ndarray | Any
MIN_CHUNK = 8192  # reference columns a chunk keeps before query blocks are made smaller
MIN_ROWS = 256  # query rows a block needs for an efficient GEMM; fewer, and the reference is chunked instead
#: blocks larger than this are slower, not faster (cache misses, page faults of fresh allocations): a larger budget
#: is a ceiling, not a target
BLOCK_BYTES = 128 * 1024**2


def _in_memory(reference: ReferenceRows) -> bool:
    """A tensor or a plain array; a memory map or coded rows (anything else indexable) are read in chunks."""
    return isinstance(reference, torch.Tensor) or (isinstance(reference, np.ndarray)
                                                    and not isinstance(reference, np.memmap))


def block_shape(
    n_q: int, n_r: int, spec: SequenceSpec, itemsize: int, budget: int | None, *, in_memory: bool = True
) -> tuple[int, int]:
    """Query rows and reference columns per block so that a block's matrices (about two copies, halos included)
    fit in ``budget`` bytes (at most ``BLOCK_BYTES``): every column when the reference is in memory and
    ``MIN_ROWS`` query rows (or all of them) fit with all of them, or when all queries do; else chunks of at least
    ``MIN_CHUNK`` columns (fewer query rows per block if need be)."""
    length, halo = spec.length, 2 * max_span(spec)
    if budget is None:
        return n_q, n_r
    cells = min(budget, BLOCK_BYTES) // (2 * itemsize)
    whole = cells // max(n_r, 1) - 2 * (length - 1)
    if whole >= (min(n_q, MIN_ROWS) if in_memory else n_q):
        return int(min(whole, n_q)), n_r
    columns = min(n_r, MIN_CHUNK)
    rows = min(n_q, cells // (columns + halo) - 2 * (length - 1))
    if whole >= 1 and (columns == n_r or rows <= whole):  # chunks would not give larger blocks
        return int(min(whole, n_q)), n_r
    if rows < 1:  # a small budget: one query row over as many columns as fit
        columns = min(n_r, cells // (1 + 2 * (length - 1)) - halo)
        if columns < 1:
            raise SeqvprError(f"memory budget of {budget} bytes is too small for sequence length {length}")
        return 1, int(columns)
    columns = max(columns, min(n_r, cells // (rows + 2 * (length - 1)) - halo))
    return int(rows), int(columns)


def check_limits(limits: np.ndarray, n_query: int, n_reference: int) -> np.ndarray:
    """Per-query reference limits as int64 [n_query], non-decreasing, within [0, n_reference]; one line otherwise."""
    limits = np.asarray(limits, dtype=np.int64)
    if limits.shape != (n_query,) or (len(limits) and (limits.min() < 0 or limits.max() > n_reference
                                                       or (np.diff(limits) < 0).any())):
        raise SeqvprError(f"limits: expected {n_query} non-decreasing row limits within [0, {n_reference}]")
    return limits


def _chunked_topk(query, reference, spec, starts, r_seg, k, columns, scorer=None,
                  limits: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The K best (distances, reference rows) of a query block over reference chunks of ``columns`` frames; rows of
    queries without a window stay +inf / -1. Ties go to the lower reference row, whatever the chunking.

    A chunk is described with ``max_span`` frames of halo on each side, so every window of its own columns, and
    its place in the segment under ``drop`` or ``shift``, is what it is in the whole reference. With ``limits``
    (the block's), a query's columns from its limit on are +inf and no chunk past the largest limit is read."""
    n_r, halo = len(reference), (scorer.span(spec) if scorer is not None else max_span(spec))
    valid = np.flatnonzero(starts >= 0)
    merged = TopKMerge(len(valid), k)
    workspace = Workspace()
    stop = n_r if limits is None else int(limits[valid].max(initial=0))
    for first in range(0, stop, columns):
        last = min(first + columns, stop)
        lo, hi = max(0, first - halo), min(n_r, last + halo)
        block = reference_rows(reference, slice(lo, hi), query)
        rows = sequence_distance_rows(query, block, spec, starts[valid], r_seg[lo:hi], workspace, scorer, lo)
        part = rows[:, first - lo : last - lo]
        if limits is not None:
            beyond = np.arange(first, last)[None, :] >= limits[valid][:, None]
            part.masked_fill_(torch.from_numpy(beyond).to(part.device), float("inf"))
        merged.push_columns(part, first)
    values, picked = merged.values, merged.rows
    all_values = np.full((len(starts), k), np.inf)
    all_picked = np.full((len(starts), k), -1, dtype=np.int64)
    all_values[valid], all_picked[valid] = values, picked
    return all_values, all_picked


def reference_rows(reference: ReferenceRows, index: slice | np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """Reference rows at ``index`` (a slice or row numbers) as a tensor of ``like``'s dtype and device: a view when
    they already are (a writable float32 memory map on CPU too), else a converted copy of those rows. A reference
    already on a device is indexed there, never through NumPy."""
    if isinstance(reference, torch.Tensor):
        rows = reference[index if isinstance(index, slice) else torch.as_tensor(index, device=reference.device)]
        return rows.to(device=like.device, dtype=like.dtype)
    rows = reference[index]
    if isinstance(rows, torch.Tensor):
        return rows.to(device=like.device, dtype=like.dtype)
    if rows.flags.writeable and str(rows.dtype) == str(like.dtype).removeprefix("torch.") and like.device.type == "cpu":
        return torch.from_numpy(rows)
    return torch.as_tensor(np.array(rows), dtype=like.dtype, device=like.device)


def sequence_distance_rows(
    query: torch.Tensor,
    reference: torch.Tensor,
    spec: SequenceSpec,
    query_starts: np.ndarray,
    reference_segments: np.ndarray | None = None,
    workspace: Workspace | None = None,
    scorer: WindowScorer | None = None,
    reference_first: int = 0,
) -> torch.Tensor:
    """Sequence distances [len(query_starts), n_reference] of the query windows starting at ``query_starts``
    (computed in ``workspace``'s buffer when one is given); ``reference`` starts at row ``reference_first`` of the
    whole reference.

    Only the frames those windows cover are compared with the reference (one GEMM over their union, laid out as
    contiguous runs), so a scattered set of windows costs about its own frames, and a contiguous block its rows
    plus a halo of L - 1. Reference windows follow ``spec`` and ``reference_segments``; +inf where none exists.
    """
    starts = np.asarray(query_starts, dtype=np.int64)
    if len(starts) and int(starts.min()) < 0:
        raise SeqvprError("sequence_distance_rows: every query start must be a window start (>= 0)")
    covered = np.unique(window_frames(starts, spec.length).ravel())
    position = np.full(int(covered[-1]) + 1 if len(covered) else 0, -1, dtype=np.int64)
    position[covered] = np.arange(len(covered))
    index = torch.as_tensor(covered, device=query.device)
    d = frame_distances(query.index_select(0, index), reference, workspace)
    # runs of consecutive covered frames are contiguous in d, and each window lies inside one run
    local_starts = position[starts]
    r_seg = _segments(reference_segments, len(reference))
    score = scorer if scorer is not None else sequence_rows
    if hasattr(score, "locate"):
        score = score.locate(covered, reference_first)
    return score(d, local_starts + spec.offset, local_starts, r_seg, spec, inplace=not d.requires_grad)


def reference_squared_norms(reference: ReferenceRows, columns: int = 65536) -> np.ndarray:
    """Squared norms [N] of every reference row, read chunk by chunk, summed in float64 and rounded once to the
    float32 the distance pass uses: computed once by a caller that measures many single frames against the same
    rows (``distances_to_reference``)."""
    from seqvpr.sequences._fused import squared_norms

    parts = []
    for lo in range(0, len(reference), columns):
        rows = reference[lo : lo + columns]
        parts.append(squared_norms(np.asarray(rows.cpu() if isinstance(rows, torch.Tensor) else rows, np.float32)))
    return np.concatenate(parts).astype(np.float32) if parts else np.zeros(0, np.float32)


def distances_to_reference(
    query: torch.Tensor, reference: ReferenceRows, norms: np.ndarray, columns: int = 65536,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Frame distances [b, N] (float32) of a few query rows to every reference row, read chunk by chunk (a saved
    map's memory map is never loaded whole), with the rows' squared ``norms`` given (one pass over the rows, not
    two), into ``out`` when given (a buffer reused frame after frame). The same values as ``frame_distances``."""
    from seqvpr.sequences._fused import distances_from_dots_, squared_norms

    query = query.float().cpu()
    out = np.empty((len(query), len(reference)), dtype=np.float32) if out is None else out
    query_sq = squared_norms(query.numpy())
    for lo in range(0, len(reference), columns):
        hi = min(lo + columns, len(reference))
        dots = torch.from_numpy(out[:, lo:hi]) if len(query) == 1 else torch.empty(len(query), hi - lo)
        torch.mm(query, reference_rows(reference, slice(lo, hi), query).T, out=dots)
        values = dots.numpy()
        distances_from_dots_(values, query_sq, norms[lo:hi])
        if len(query) > 1:  # one frame's distances were measured in place
            out[:, lo:hi] = values
    return out
