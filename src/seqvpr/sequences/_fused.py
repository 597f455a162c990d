"""Fused CPU kernel: order-aligned window means of a distance matrix in one in-place pass (numba).

For a matrix d [n, m] and window length L it overwrites d with
``P[r, j] = (1/L) * sum_k d[r - a + k, j - a + k]`` where the window fits, +inf elsewhere. One float64 running sum
per diagonal (``acc``, indexed by diagonal, so each update is in place) adds the element entering the window and
removes the one leaving it, so each element of d is read from memory about once whatever L is. Each row step is a
single vectorised loop over the columns that reads the entering row, saves it to a ring of the L + 1 most recent
original rows (the pass overwrites rows before it has finished with them), updates the sums and writes the output
row. The loops live in small helpers that take 1-D row views starting at index 0, so numba emits no negative-index
wraparound and LLVM vectorises them. The rows where two parallel chunks meet are copied before the chunks start.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, boundscheck=False)
def _enter(acc, src, ring_row):
    """Add an entering row to diagonals that are not output yet; save it to the ring."""
    for t in range(acc.shape[0]):
        x = src[t]
        ring_row[t] = x
        acc[t] += x


@njit(cache=True, nogil=True, boundscheck=False)
def _enter_out(acc, src, ring_row, out, inv):
    """First step of a chunk: add the entering row, save it, write the means (nothing leaves yet)."""
    for t in range(acc.shape[0]):
        x = src[t]
        ring_row[t] = x
        v = acc[t] + x
        acc[t] = v
        out[t] = v * inv


@njit(cache=True, nogil=True, boundscheck=False)
def _slide_out(acc, src, ring_row, old, out, inv):
    """One step: add the entering row, save it, remove the leaving row, write the means."""
    for t in range(acc.shape[0]):
        x = src[t]
        ring_row[t] = x
        v = acc[t] + x - old[t]
        acc[t] = v
        out[t] = v * inv


@njit(cache=True, nogil=True, boundscheck=False)
def _slide_same(acc, row, ring_row, old, inv):
    """As ``_slide_out`` when the output row is the entering row (a = L - 1): each element read, then overwritten."""
    for t in range(acc.shape[0]):
        x = row[t]
        ring_row[t] = x
        v = acc[t] + x - old[t]
        acc[t] = v
        row[t] = v * inv


@njit(cache=True, nogil=True, boundscheck=False)
def _chunk(d, length, a, s_begin, s_end, head, tail):
    """Rows s_begin..s_end-1 of window sums (written to rows s + a); head/tail are pre-copied original rows.

    ``acc[base - (r - s_begin) + c]`` is the running sum of the diagonal through (r, c); at step s it holds, for
    the window starting at (s, t), the sum of rows s..s+L-1 (columns of diagonals not yet output start at 0).
    """
    m = d.shape[1]
    m1 = m - length + 1
    slots = length + 1
    ring = np.empty((slots, m), dtype=d.dtype)
    base = (s_end - s_begin) + length - 1
    acc = np.zeros(base + m, dtype=np.float64)
    inv = 1.0 / length

    for k in range(length - 1):
        j = base - k
        _enter(acc[j : j + m], head[k], ring[(s_begin + k) % slots])

    for s in range(s_begin, s_end):
        r = s + length - 1
        if s == s_begin:
            src = head[length - 1]
        elif r >= s_end:
            src = tail[r - s_end]
        else:
            src = d[r]
        saved = ring[r % slots]
        j0 = base - (s - s_begin)
        out = d[s + a]
        # columns 0..L-2 of the entering row lie on diagonals whose first window is still to come
        _enter(acc[j0 - (length - 1) : j0], src[: length - 1], saved[: length - 1])
        if s == s_begin:
            _enter_out(acc[j0 : j0 + m1], src[length - 1 :], saved[length - 1 :], out[a : a + m1], inv)
        else:
            # column t = 0 starts a new diagonal: nothing leaves it
            x = src[length - 1]
            saved[length - 1] = x
            v = acc[j0] + x
            acc[j0] = v
            out[a] = v * inv
            old = ring[(s - 1) % slots]
            if a == length - 1 and r < s_end:
                _slide_same(acc[j0 + 1 : j0 + m1], out[length:], saved[length:], old[: m1 - 1], inv)
            else:
                _slide_out(
                    acc[j0 + 1 : j0 + m1], src[length:], saved[length:], old[: m1 - 1], out[a + 1 : a + m1], inv
                )
        out[:a] = np.inf
        out[a + m1 :] = np.inf


@njit(cache=True, parallel=True)
def _fused_parallel(d, length, a, bounds, heads, tails):
    for c in prange(len(bounds) - 1):
        _chunk(d, length, a, bounds[c], bounds[c + 1], heads[c], tails[c])


def fused_window_means_(d: np.ndarray, length: int, a: int, n_chunks: int = 0) -> None:
    """Overwrite the C-contiguous float matrix ``d`` with its placed window means (see module docstring)."""
    n, m = d.shape
    n1 = n - length + 1
    if n1 <= 0 or m < length:
        d.fill(np.inf)
        return
    if n_chunks <= 0:
        n_chunks = numba.get_num_threads()
    n_chunks = max(1, min(n_chunks, n1 // (4 * length) or 1))
    bounds = np.linspace(0, n1, n_chunks + 1).astype(np.int64)
    heads = np.stack([d[b : b + length].copy() for b in bounds[:-1]])
    tails = np.stack([_rows_or_pad(d, b, length) for b in bounds[1:]])
    _fused_parallel(d, length, a, bounds, heads, tails)
    d[:a] = np.inf
    d[a + n1 :] = np.inf


def _rows_or_pad(d: np.ndarray, start: int, length: int) -> np.ndarray:
    """Rows ``[start, start + length)`` of d, zero-padded past its end (the last chunk reads no row past n)."""
    block = np.zeros((length, d.shape[1]), dtype=d.dtype)
    rows = d[start : start + length]
    block[: len(rows)] = rows
    return block


@njit(cache=True, nogil=True, boundscheck=False)
def _distances_row(row, qi, reference_sq, floor):
    for j in range(row.shape[0]):
        v = qi + reference_sq[j] - 2.0 * row[j]
        row[j] = np.sqrt(v if v > floor else floor)


@njit(cache=True, parallel=True, boundscheck=False)
def _distances_from_dots(g, query_sq, reference_sq, floor):
    for i in prange(g.shape[0]):
        _distances_row(g[i], query_sq[i], reference_sq, floor)


@njit(cache=True, nogil=True, boundscheck=False)
def _distances_from_dots_serial(g, query_sq, reference_sq, floor):
    for i in range(g.shape[0]):
        _distances_row(g[i], query_sq[i], reference_sq, floor)


def distances_from_dots_(g: np.ndarray, query_sq: np.ndarray, reference_sq: np.ndarray, floor: float = 1e-12) -> None:
    """Overwrite the dot products ``g`` [n, m] with Euclidean distances ``sqrt(max(|q|^2 + |r|^2 - 2 g, floor))``
    in one pass (no n x m temporary of squared norms): parallel over rows; one row (a localiser's frame) in this
    thread, so its pool never wakes beside torch's."""
    kernel = _distances_from_dots if g.shape[0] > 1 else _distances_from_dots_serial
    kernel(g, np.asarray(query_sq, g.dtype), np.asarray(reference_sq, g.dtype), g.dtype.type(floor))


@njit(cache=True, nogil=True, boundscheck=False)
def _frame_distances(dots, query, reference_sq, floor):
    _distances_row(dots, np.float32(_squared_norm(query)), reference_sq, floor)


def frame_distances_(dots: np.ndarray, query: np.ndarray, reference_sq: np.ndarray, floor: float = 1e-12) -> None:
    """``distances_from_dots_`` of one frame's dot products ``dots`` [m] (float32) with its own squared norm
    computed on the way (as ``squared_norms`` sums it, rounded to float32): one call in this thread."""
    _frame_distances(dots, query, reference_sq, np.float32(floor))


@njit(cache=True, nogil=True, boundscheck=False)
def scale_by_peak_(x, out, tiny):
    """``out = x / max(max |x|, tiny)``, each a float32 division (``unit_rows``' first step: a NaN anywhere makes
    the peak NaN, as torch's ``amax`` and ``clamp_min`` do)."""
    peak = np.float32(0)
    for i in range(x.shape[0]):
        a = abs(x[i])
        if np.isnan(a):
            peak = a
            break
        if a > peak:
            peak = a
    if peak < tiny:
        peak = tiny
    for i in range(x.shape[0]):
        out[i] = x[i] / peak


@njit(cache=True, nogil=True, boundscheck=False)
def divide_(x, by):
    """``x /= by`` in place, a float32 division each."""
    for i in range(x.shape[0]):
        x[i] = x[i] / by


@njit(cache=True, nogil=True, boundscheck=False)
def all_finite(x):
    """Whether no value of ``x`` [D] is NaN or infinite (one pass, no temporary)."""
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return False
    return True


@njit(cache=True, nogil=True, boundscheck=False)
def uniqueness_score(rows, values, exclusion):
    """``seqvpr.sequences.topk.uniqueness_ratio`` on a ranked list (rows int64, values float64)."""
    if rows.shape[0] == 0 or rows[0] < 0 or not np.isfinite(values[0]):
        return 0.0
    second = np.inf
    for i in range(1, rows.shape[0]):
        if rows[i] >= 0 and np.isfinite(values[i]) and abs(rows[i] - rows[0]) > exclusion:
            second = values[i]
            break
    if not np.isfinite(second):
        return 1.0
    if second <= 0:
        return 0.0
    return min(max(1.0 - values[0] / second, 0.0), 1.0)


@njit(cache=True, nogil=True, boundscheck=False)
def _squared_norm(row):
    total = 0.0
    for j in range(row.shape[0]):
        total += row[j] * row[j]
    return total


@njit(cache=True, parallel=True, boundscheck=False)
def _squared_norms(x, out):
    for i in prange(x.shape[0]):
        out[i] = _squared_norm(x[i])


@njit(cache=True, nogil=True, boundscheck=False)
def _squared_norms_serial(x, out):
    for i in range(x.shape[0]):
        out[i] = _squared_norm(x[i])


SERIAL_ROWS = 64  # rows below which a pass runs in the calling thread (a parallel launch costs more)


def squared_norms(x: np.ndarray) -> np.ndarray:
    """Row sums of squares [n] of a C-contiguous [n, d] matrix, summed in float64 without a temporary matrix."""
    out = np.empty(len(x), dtype=np.float64)
    (_squared_norms if len(x) >= SERIAL_ROWS else _squared_norms_serial)(np.ascontiguousarray(x), out)
    return out


@njit(cache=True, nogil=True, boundscheck=False)
def enter_ranked(v, r, best, where):
    """The tie rule, compiled (``topk.rank_order`` in numpy; tested bit for bit against it): insert value ``v`` of
    row ``r`` into the sorted running top-K ``best``/``where`` (called only when ``v`` beats the K-th), after any
    equal value, so rows met in order keep the lower row on a tie. Every compiled top-K enters through it."""
    p = best.shape[0] - 1
    while p > 0 and best[p - 1] > v:
        best[p] = best[p - 1]
        where[p] = where[p - 1]
        p -= 1
    best[p] = v
    where[p] = r


@njit(cache=True, parallel=True, boundscheck=False)
def _topk_update(rows, first, values, indices):
    k = values.shape[1]
    for i in prange(rows.shape[0]):
        row = rows[i]
        best, where = values[i], indices[i]
        threshold = best[k - 1]
        for j in range(row.shape[0]):
            v = row[j]
            if v < threshold:
                enter_ranked(v, first + j, best, where)
                threshold = best[k - 1]


def topk_update_(rows: np.ndarray, first: int, values: np.ndarray, indices: np.ndarray) -> None:
    """Merge the columns of ``rows`` [n, w] (column j is index ``first + j``) into the running K smallest
    ``values``/``indices`` [n, K] (sorted ascending; +inf/-1 where empty). A value enters only if strictly smaller
    than the K-th, and columns come in index order, so ties keep the lower index whatever the chunking."""
    _topk_update(rows, first, values, indices)


@njit(cache=True, nogil=True, boundscheck=False)
def _window_row(query, reference, qs, starts, length, out):
    """One query window (from ``qs``) against its candidates (from ``starts[c]``; -1: +inf), float64 sums."""
    for c in range(starts.shape[0]):
        rs = starts[c]
        if rs < 0:
            out[c] = np.inf
            continue
        total = 0.0
        for k in range(length):
            q = query[qs + k]
            r = reference[rs + k]
            squared = 0.0
            for d in range(q.shape[0]):
                diff = np.float64(q[d]) - np.float64(r[d])
                squared += diff * diff
            total += np.sqrt(max(squared, 1e-12))
        out[c] = total / length


@njit(cache=True, parallel=True, boundscheck=False)
def _window_distances(query, reference, query_starts, reference_starts, length, out):
    for i in prange(reference_starts.shape[0]):
        _window_row(query, reference, query_starts[i], reference_starts[i], length, out[i])


@njit(cache=True, nogil=True, boundscheck=False)
def _window_distances_serial(query, reference, query_starts, reference_starts, length, out):
    for i in range(reference_starts.shape[0]):
        _window_row(query, reference, query_starts[i], reference_starts[i], length, out[i])


SERIAL_WINDOWS = 4096  # fewer windows are scored in the calling thread (a stream's: no pool contending with faiss)


def window_distances(query: np.ndarray, reference: np.ndarray, query_starts: np.ndarray,
                     reference_starts: np.ndarray, length: int) -> np.ndarray:
    """Sequence distances [n, C] between the query window starting at ``query_starts[i]`` and the reference windows
    starting at ``reference_starts[i, c]`` (-1: +inf), read straight from the (memory-mapped) rows: no [n, C, L, D]
    gather. Few windows are scored serially, many in parallel: the same numbers either way."""
    out = np.empty(reference_starts.shape, dtype=np.float64)
    kernel = _window_distances_serial if reference_starts.size < SERIAL_WINDOWS else _window_distances
    kernel(query, reference, np.ascontiguousarray(query_starts, dtype=np.int64),
           np.ascontiguousarray(reference_starts, dtype=np.int64), length, out)
    return out


DIAGONAL_BLOCK = 4096  # rows summed at a time: a float64 block that stays in cache


@njit(cache=True, nogil=True, boundscheck=False)
def _diagonal_term(ring, newest, length, j, lo, hi):
    """The ring row ``j`` frames before the newest, over the columns its diagonals from rows ``lo .. hi - 1`` cross
    (a slice, so each loop indexes from 0 and vectorises)."""
    slot = newest - j
    if slot < 0:
        slot += length
    return ring[slot, lo - j : hi - j]


@njit(cache=True, nogil=True, boundscheck=False)
def _add_terms(out, a, b, c, d, count, first):
    """``out`` = (((out + a) + b) + c) + d over the first ``count`` of a .. d (from a alone when ``first``), in
    float64: up to four terms a pass, so the block is read and written once for four rows of the ring."""
    if first:
        if count == 1:
            for i in range(out.shape[0]):
                out[i] = np.float64(a[i])
        elif count == 2:
            for i in range(out.shape[0]):
                out[i] = np.float64(a[i]) + np.float64(b[i])
        elif count == 3:
            for i in range(out.shape[0]):
                out[i] = (np.float64(a[i]) + np.float64(b[i])) + np.float64(c[i])
        else:
            for i in range(out.shape[0]):
                out[i] = ((np.float64(a[i]) + np.float64(b[i])) + np.float64(c[i])) + np.float64(d[i])
    elif count == 1:
        for i in range(out.shape[0]):
            out[i] = out[i] + np.float64(a[i])
    elif count == 2:
        for i in range(out.shape[0]):
            out[i] = (out[i] + np.float64(a[i])) + np.float64(b[i])
    elif count == 3:
        for i in range(out.shape[0]):
            out[i] = ((out[i] + np.float64(a[i])) + np.float64(b[i])) + np.float64(c[i])
    else:
        for i in range(out.shape[0]):
            out[i] = (((out[i] + np.float64(a[i])) + np.float64(b[i])) + np.float64(c[i])) + np.float64(d[i])


@njit(cache=True, nogil=True, boundscheck=False)
def _diagonal_block(ring, newest, length, lo, hi, out):
    """``out[:hi - lo]`` = the means of the causal windows ending at reference rows ``lo .. hi - 1`` (``lo`` at
    least L - 1): the last ``length`` distance rows of the ring (``newest`` its latest slot) along each diagonal,
    summed oldest first in float64 (exact for float32 terms), over the block in vectorised passes."""
    view = out[: hi - lo]
    j = length - 1  # the oldest term's lag
    while j >= 0:
        count = min(4, j + 1)
        _add_terms(view, _diagonal_term(ring, newest, length, j, lo, hi),
                   _diagonal_term(ring, newest, length, max(j - 1, 0), lo, hi),
                   _diagonal_term(ring, newest, length, max(j - 2, 0), lo, hi),
                   _diagonal_term(ring, newest, length, max(j - 3, 0), lo, hi), count, j == length - 1)
        j -= count
    divisor = np.float64(length)
    for i in range(view.shape[0]):
        view[i] /= divisor


@njit(cache=True, parallel=True, boundscheck=False)
def _diagonal_means(ring, newest, length, exists, out):
    n = exists.shape[0]
    start = length - 1
    for r in range(min(start, n)):
        out[r] = np.inf
    blocks = (n - start + DIAGONAL_BLOCK - 1) // DIAGONAL_BLOCK if n > start else 0
    for b in prange(blocks):
        lo = start + b * DIAGONAL_BLOCK
        hi = min(lo + DIAGONAL_BLOCK, n)
        _diagonal_block(ring, newest, length, lo, hi, out[lo:hi])
        for r in range(lo, hi):
            if not exists[r]:
                out[r] = np.inf


def diagonal_means_(ring: np.ndarray, newest: int, exists: np.ndarray, out: np.ndarray) -> None:
    """The causal window means [N] of a ring of the last L distance rows [L, N] into ``out`` (+inf where no window
    ends: ``exists`` False)."""
    _diagonal_means(ring, newest, ring.shape[0], exists, out)


@njit(cache=True, nogil=True, boundscheck=False)
def _diagonal_scan(ring, newest, length, exists, lo, hi, best, where, convert, query, norms, floor):
    """Rank the windows ending at rows ``lo .. hi - 1`` into ``best``/``where``; with ``convert``, the newest row
    holds dot products, turned into distances (``_distances_row``) a block at a time just before it is summed."""
    buffer = np.empty(DIAGONAL_BLOCK)
    threshold = best[best.shape[0] - 1]
    query_sq = np.float32(_squared_norm(query))  # as _frame_distances rounds it
    start = max(lo, length - 1)
    if convert and start > lo:
        _distances_row(ring[newest, lo:start], query_sq, norms[lo:start], floor)
    for b in range(start, hi, DIAGONAL_BLOCK):
        e = min(b + DIAGONAL_BLOCK, hi)
        if convert:
            _distances_row(ring[newest, b:e], query_sq, norms[b:e], floor)
        _diagonal_block(ring, newest, length, b, e, buffer)
        for i in range(e - b):
            v = buffer[i]
            if v < threshold and exists[b + i]:
                enter_ranked(v, b + i, best, where)
                threshold = best[best.shape[0] - 1]


@njit(cache=True, parallel=True, boundscheck=False)
def _diagonal_topk_parts(ring, newest, length, exists, parts_best, parts_where, best, where, convert, query, norms,
                         floor):
    parts, n = parts_best.shape[0], exists.shape[0]
    for c in prange(parts):
        _diagonal_scan(ring, newest, length, exists, n * c // parts, n * (c + 1) // parts, parts_best[c],
                       parts_where[c], convert, query, norms, floor)
    threshold = best[best.shape[0] - 1]
    for c in range(parts):  # parts in row order, each ranked: ties still keep the lower row
        for i in range(parts_best.shape[1]):
            v = parts_best[c, i]
            if v < threshold:
                enter_ranked(v, parts_where[c, i], best, where)
                threshold = best[best.shape[0] - 1]


@njit(cache=True, nogil=True, boundscheck=False)
def _diagonal_topk_serial(ring, newest, length, exists, k, convert, query, norms, floor):
    best, where = np.full(k, np.inf), np.full(k, -1, np.int64)  # made here: a Python-side array costs more
    _diagonal_scan(ring, newest, length, exists, 0, exists.shape[0], best, where, convert, query, norms, floor)
    return where, best


PART_ROWS = 65_536  # rows a thread scans at least: below this a parallel launch costs more than it saves
FLOOR32 = np.float32(1e-12)
NOTHING = np.zeros(0, np.float32)  # the query and norms of a ring that holds distances already


def diagonal_topk(ring: np.ndarray, newest: int, exists: np.ndarray, k: int, query: np.ndarray | None = None,
                  norms: np.ndarray | None = None, floor: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` best causal windows (rows, means ascending; -1/+inf pad) of a ring of the last L distance rows
    [L, N], without writing the N means: one pass, split over the thread pool in runs of rows whose top-Ks merge
    in row order (the same rows and ties as one scan, ``best_k``'s). Given the frame's ``query`` row [D] and the
    reference rows' squared ``norms`` [N] (float32), the newest row holds its dot products, which become its
    distances (``frame_distances_``'s values) in the same pass, each block while it is in cache."""
    convert = query is not None
    query, norms = (query, norms) if convert else (NOTHING, NOTHING)
    floor = FLOOR32 if floor == 1e-12 else np.float32(floor)
    n = exists.shape[0]
    parts = 1 if n < 2 * PART_ROWS else max(1, min(numba.get_num_threads(), n // PART_ROWS))
    if parts == 1:
        return _diagonal_topk_serial(ring, newest, ring.shape[0], exists, k, convert, query, norms, floor)
    best, where = np.full(k, np.inf), np.full(k, -1, np.int64)
    parts_best, parts_where = np.full((parts, k), np.inf), np.full((parts, k), -1, np.int64)
    _diagonal_topk_parts(ring, newest, ring.shape[0], exists, parts_best, parts_where, best, where, convert, query,
                         norms, floor)
    return where, best
