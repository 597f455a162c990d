"""The K best reference rows per query, and the one rule that orders them: by distance, equal distances to the lower
reference row, empty entries (row -1, distance +inf) last. Every top-K in seqvpr (kernel blocks, reference chunks,
shard merges, re-ranked shortlists, the online step) is ranked by ``rank_order`` or merged by ``TopKMerge``, so a
match split into any chunks, shards or streams is the match done whole. ``other_place`` is the one definition of
"the best match of another place" behind the two uniqueness scores: ``uniqueness_ratio`` (online, higher: surer) and
``uniqueness_margins`` (offline, lower: more unique, ranked like a distance).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from seqvpr import sequences
from seqvpr.results import TopK

NO_ROW = -1  # an empty entry's row (its distance is +inf)
_LAST = np.iinfo(np.int64).max  # where the tie rule puts an empty entry's row


def rank_order(rows: np.ndarray, distances: np.ndarray, k: int | None = None) -> np.ndarray:
    """Positions (along the last axis) of the ``k`` best entries, best first: by distance, ties to the lower row,
    empty rows (< 0) after every real one. The tie rule; everything else that ranks calls it."""
    order = np.lexsort((np.where(rows >= 0, rows, _LAST), distances), axis=-1)
    return order if k is None else order[..., :k]


def best_of(rows: np.ndarray, distances: np.ndarray, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` best (rows, distances) of candidate lists by ``rank_order``; a non-finite distance is an empty
    entry (-1, +inf)."""
    order = rank_order(rows, distances, k)
    picked = np.take_along_axis(np.asarray(rows), order, -1)
    values = np.take_along_axis(np.asarray(distances, dtype=np.float64), order, -1)
    finite = np.isfinite(values)
    return np.where(finite, picked, NO_ROW), np.where(finite, values, np.inf)


def best_k(values: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` best rows of one dense vector of distances (row r's distance at ``values[r]``), ranked by
    ``rank_order``: one scan that keeps a running top-K (``TopKMerge``'s, the tie rule), so a step over a large map
    costs one pass and allocates nothing of the map's size; -1/+inf pad."""
    k = min(k, len(values))
    if k == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float64)
    merged = TopKMerge(1, k)
    merged.push_columns(torch.from_numpy(np.ascontiguousarray(values, dtype=np.float64))[None], 0, scan=True)
    found = merged.result(np.ones(1, bool))
    return found.indices[0], found.distances[0]


class TopKMerge:
    """A running top-K of ``n`` queries, filled by blocks of columns or by lists of candidates in any order and any
    split: the result is ``rank_order``'s over everything pushed (a faiss-style result heap for every search)."""

    def __init__(self, n: int, k: int) -> None:
        self.values = np.full((n, k), np.inf, dtype=np.float64)
        self.rows = np.full((n, k), NO_ROW, dtype=np.int64)

    def push_columns(self, block: torch.Tensor, first: int, scan: bool | None = None) -> None:
        """Merge a dense block [n, w] whose column j is reference row ``first + j``. On CPU one numba scan (columns
        in row order, entering only below the K-th: the tie rule, for blocks pushed in row order); elsewhere, or
        with ``scan=False``, the block's own top-K merged by ``push``."""
        if scan if scan is not None else block.device.type == "cpu":
            from seqvpr.sequences._fused import topk_update_

            topk_update_(block.numpy(), first, self.values, self.rows)
            return
        k = min(self.values.shape[1], block.shape[1])
        values, columns = torch.sort(block, dim=1, stable=True)
        self.push(columns[:, :k].cpu().numpy() + first, values[:, :k].double().cpu().numpy())

    def push(self, rows: np.ndarray, distances: np.ndarray) -> None:
        """Merge candidate lists [n, c] (rows -1 / distances +inf for none), in any order."""
        both_rows = np.concatenate([self.rows, rows], 1)
        both_values = np.concatenate([self.values, distances], 1)
        self.rows, self.values = best_of(both_rows, both_values, self.values.shape[1])

    def result(self, has_window: np.ndarray) -> TopK:
        """The top-K so far (empty entries -1 / +inf)."""
        rows = np.where(np.isfinite(self.values), self.rows, NO_ROW)
        return TopK(rows, self.values, has_window)


def merge_topks(parts: Sequence[TopK], k: int) -> TopK:
    """The best ``k`` of several top-K lists of the same queries (over disjoint rows: shards, chunks)."""
    merged = TopKMerge(len(parts[0].indices), k)
    merged.push(np.concatenate([p.indices for p in parts], 1), np.concatenate([p.distances for p in parts], 1))
    return merged.result(parts[0].has_window)


def other_place(indices: np.ndarray, distances: np.ndarray, exclusion: int) -> np.ndarray:
    """Per ranked list [n, K] (best first), the column of the best match more than ``exclusion`` rows from the best
    one (another place), or -1 when the list holds none: the rival every uniqueness score compares against."""
    indices = np.atleast_2d(indices)
    outside = (np.abs(indices - indices[:, :1]) > exclusion) & (indices >= 0) & np.isfinite(np.atleast_2d(distances))
    outside[:, 0] = False
    return np.where(outside.any(1), outside.argmax(1), -1)


def uniqueness_ratio(indices: np.ndarray, distances: np.ndarray, exclusion: int) -> float:
    """The online score (a localiser's, a stream's), how much one ranked list's best match stands out: 1 - best / (the best of another place, ``other_place``), in
    [0, 1]; 0 with no match, 1 when no other place is in the list (SeqSLAM's ratio test as a score). A list of the
    best 2 x ``exclusion`` + 2 rows holds the best other place of the whole map when one exists."""
    return sequences._fused.uniqueness_score(np.asarray(indices, dtype=np.int64),  # compiled: scored every frame
                                             np.asarray(distances, dtype=np.float64), exclusion)


def uniqueness_margins(indices: np.ndarray, distances: np.ndarray, exclusion: int) -> np.ndarray:
    """The offline score (``--uniqueness E``, for PR curves): SeqSLAM's windowed uniqueness from a top-K list [n, K]: the best distance minus the best one outside
    ``exclusion`` frames of it (the K-th when none in the list is outside: a bound), so lower is more unique and it
    ranks like a distance for PR curves. A margin, not OpenSeqSLAM2's ratio min1/min2: contrast-enhanced distances
    can be negative, where the ratio means nothing. +inf where a query has no match."""
    column = other_place(indices, distances, exclusion)
    first = np.where(column >= 0, column, distances.shape[1] - 1)
    second = distances[np.arange(len(distances)), first]
    matched = (indices[:, 0] >= 0) & np.isfinite(distances[:, 0])
    margin = np.full(len(distances), np.inf)
    margin[matched] = distances[matched, 0] - second[matched]  # -inf when no second exists: as unique as can be
    return margin
