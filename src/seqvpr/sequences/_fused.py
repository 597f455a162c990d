"""Fused CPU kernel: order-aligned window means of a distance matrix in one in-place pass (numba).

For a matrix d [n, m] and window length L it overwrites d with
``P[r, j] = (1/L) * sum_k d[r - a + k, j - a + k]`` where the window fits, +inf elsewhere. Along each diagonal a
running sum (float64) adds the entering element and removes the leaving one, so each element of d is read
from memory about once whatever L is. Original rows that the pass overwrites before it has finished with them
are kept in a ring of L + 1 rows; the rows where two parallel chunks meet are copied before the chunks start.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True)
def _chunk(d, length, a, s_begin, s_end, head, tail):
    """Rows s_begin..s_end-1 of window sums (written to rows s + a); head/tail are pre-copied original rows."""
    m = d.shape[1]
    m1 = m - length + 1
    slots = length + 1
    ring = np.empty((slots, m), dtype=d.dtype)
    acc = np.empty(m1, dtype=np.float64)
    nxt = np.empty(m1, dtype=np.float64)
    inv = 1.0 / length

    for k in range(length):
        ring[(s_begin + k) % slots, :] = head[k, :]
    for t in range(m1):
        total = 0.0
        for k in range(length):
            total += ring[(s_begin + k) % slots, t + k]
        acc[t] = total

    for s in range(s_begin, s_end):
        if s > s_begin:
            r = s + length - 1
            slot = r % slots
            if r >= s_end:
                ring[slot, :] = tail[r - s_end, :]
            else:
                ring[slot, :] = d[r, :]
            old = ring[(s - 1) % slots]
            new = ring[slot]
            total = 0.0
            for k in range(length):
                total += ring[(s + k) % slots, k]
            nxt[0] = total
            for t in range(1, m1):
                nxt[t] = acc[t - 1] - old[t - 1] + new[t + length - 1]
            acc, nxt = nxt, acc
        row = s + a
        d[row, :a] = np.inf
        for t in range(m1):
            d[row, t + a] = acc[t] * inv
        d[row, a + m1 :] = np.inf


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
