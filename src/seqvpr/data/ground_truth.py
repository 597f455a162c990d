"""Ground truth: for each query frame, the reference frames that show the same place, held sparsely.

A ``GroundTruth`` is a boolean sparse matrix laid out [n_query, n_reference] over the rows of two traversals.
It is built from a radius (metres on positions, or frames on frame indices) or read from a file, and never held
as a dense n_query x n_reference array.

Same name as ``seqvpr.evaluation.ground_truth``: the ground-truth type and radii; resolving a match's there.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from seqvpr.data.traversal import Traversal
from seqvpr.data.geo import positions_in
from seqvpr.errors import SeqvprError

RadiusUnit = Literal["m", "frames"]


@dataclass(frozen=True)
class Radius:
    """A ground-truth tolerance: metres between positions, or frames between frame indices."""

    value: float
    unit: RadiusUnit

    def __str__(self) -> str:
        return f"{self.value:g}m" if self.unit == "m" else f"{self.value:g}f"


_RADIUS = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(m|metres|meters|f|frames?)?\s*$", re.IGNORECASE)


def parse_radius(text: str) -> Radius:
    """Parse ``25m``, ``25`` (metres) or ``2f`` / ``2frames`` (frames)."""
    match = _RADIUS.match(str(text))
    if not match:
        raise SeqvprError(f"radius {text!r}: expected a number with unit m (metres) or f (frames), e.g. 25m or 2f")
    unit = (match.group(2) or "m").lower()
    return Radius(float(match.group(1)), "m" if unit.startswith("m") else "frames")


@dataclass(frozen=True)
class GroundTruth:
    """Positives per query as a sparse boolean matrix [n_query, n_reference].

    ``soft`` optionally marks matches that are neither right nor wrong (the GTsoft convention): the PR curve
    ignores a best match that is soft but not a positive.
    """

    positives: sp.csr_array
    soft: sp.csr_array | None = None
    description: str = ""

    @property
    def shape(self) -> tuple[int, int]:
        return self.positives.shape

    def has_positive(self) -> np.ndarray:
        """Boolean [n_query]: the query has at least one positive reference frame."""
        return np.diff(self.positives.indptr) > 0

    def positives_of(self, query: int) -> np.ndarray:
        """Sorted reference rows that are positives of one query row."""
        start, stop = self.positives.indptr[query], self.positives.indptr[query + 1]
        return self.positives.indices[start:stop]

    def contains(self, query_rows: np.ndarray, reference_rows: np.ndarray) -> np.ndarray:
        """Elementwise: is reference_rows[..] a positive of query_rows[..]? Negative reference rows are False."""
        return _sparse_contains(self.positives, query_rows, reference_rows)

    def soft_contains(self, query_rows: np.ndarray, reference_rows: np.ndarray) -> np.ndarray:
        """Like ``contains`` for the soft matrix (all False when there is none)."""
        if self.soft is None:
            return np.zeros(np.broadcast(query_rows, reference_rows).shape, dtype=bool)
        return _sparse_contains(self.soft, query_rows, reference_rows)

    def restrict(self, query_rows: np.ndarray, reference_rows: np.ndarray) -> GroundTruth:
        """Ground truth between subsets of the rows (e.g. source indices of sliced traversals)."""
        n_q, n_r = self.shape
        for name, rows, n in (("query", query_rows, n_q), ("reference", reference_rows, n_r)):
            if len(rows) and (rows.min() < 0 or rows.max() >= n):
                raise SeqvprError(
                    f"ground truth covers {n} {name} frames, but frame {int(rows.max())} was asked for"
                )
        pick = lambda m: None if m is None else sp.csr_array(m[query_rows][:, reference_rows])  # noqa: E731
        return GroundTruth(pick(self.positives), pick(self.soft), self.description)


def _sparse_contains(matrix: sp.csr_array, query_rows: np.ndarray, reference_rows: np.ndarray) -> np.ndarray:
    """Membership test of (row, col) pairs in a CSR matrix via sorted pair codes (no dense matrix)."""
    q, r = np.broadcast_arrays(np.asarray(query_rows, dtype=np.int64), np.asarray(reference_rows, dtype=np.int64))
    n_cols = matrix.shape[1]
    coo = matrix.tocoo()
    codes = np.sort(coo.row.astype(np.int64) * n_cols + coo.col.astype(np.int64))
    wanted = q * n_cols + r
    if len(codes) == 0:
        return np.zeros(q.shape, dtype=bool)
    pos = np.clip(np.searchsorted(codes, wanted), 0, len(codes) - 1)
    return (codes[pos] == wanted) & (r >= 0)


def ground_truth_within_radius(query: Traversal, reference: Traversal, radius: Radius) -> GroundTruth:
    """Positives = reference frames within ``radius`` of each query frame (distance <= radius)."""
    if radius.unit == "frames":
        return GroundTruth(
            _within_frames(query.frame_index, reference.frame_index, radius.value),
            description=f"within {radius.value:g} frames (frame-aligned)",
        )
    for traversal in (query, reference):
        if traversal.positions is None:
            raise SeqvprError(
                f"{traversal.source or traversal.name}: a metric radius ({radius}) needs positions; "
                "give positions or use a frame radius such as 2f for frame-aligned traversals"
            )
    query_positions = positions_in(query.positions, query.crs, reference.crs,  # one planar frame for the pair
                                   f"{query.source or query.name} against {reference.source or reference.name}")
    return GroundTruth(
        _within_metres(query_positions, reference.positions, radius.value),
        description=f"within {radius.value:g} m",
    )


def _within_frames(query_frames: np.ndarray, reference_frames: np.ndarray, radius: float) -> sp.csr_array:
    """CSR of |f_q - f_r| <= radius, from sorted reference frame indices (ranges per query, no dense matrix)."""
    order = np.argsort(reference_frames, kind="stable")
    sorted_frames = reference_frames[order]
    lo = np.searchsorted(sorted_frames, query_frames - radius, side="left")
    hi = np.searchsorted(sorted_frames, query_frames + radius, side="right")
    counts = hi - lo
    indptr = np.concatenate([[0], np.cumsum(counts)])
    flat = np.repeat(lo - indptr[:-1], counts) + np.arange(indptr[-1])
    indices = order[flat]
    matrix = sp.csr_array(
        (np.ones(len(indices), dtype=bool), indices, indptr), shape=(len(query_frames), len(reference_frames))
    )
    matrix.sort_indices()
    return matrix


def _within_metres(query_positions: np.ndarray, reference_positions: np.ndarray, radius: float) -> sp.csr_array:
    """CSR of Euclidean distance <= radius between 2-D positions, through a k-d tree."""
    tree = cKDTree(reference_positions)
    neighbors = tree.query_ball_point(query_positions, r=radius)
    counts = np.array([len(n) for n in neighbors], dtype=np.int64)
    indptr = np.concatenate([[0], np.cumsum(counts)])
    indices = np.concatenate([np.asarray(n, dtype=np.int64) for n in neighbors]) if indptr[-1] else np.zeros(0, np.int64)
    matrix = sp.csr_array(
        (np.ones(len(indices), dtype=bool), indices, indptr), shape=(len(query_positions), len(reference_positions))
    )
    matrix.sort_indices()
    return matrix
