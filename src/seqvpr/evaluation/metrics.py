"""Recall@K and precision-recall from top-K predictions, with an explicit policy for queries without positives.

Queries without a window (sequence longer than the frames around them) have no prediction and are never scored.
Queries without any positive reference are excluded from the denominator by default, as the papers do
(``no_positive="exclude"``), or counted as misses (``"miss"``, as CosPlace does). Both counts are reported.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from seqvpr.data.ground_truth import GroundTruth
from seqvpr.errors import SeqvprError, SettingError

NoPositivePolicy = Literal["exclude", "miss"]
DEFAULT_KS = (1, 5, 10, 20)


@dataclass(frozen=True)
class PRCurve:
    """Precision and recall of accepting best matches below a distance threshold, swept over all thresholds.

    ``auc`` is the step-wise area (average precision); ``recall_at_100_precision`` the largest recall reached
    while every accepted match is right.
    """

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    auc: float
    recall_at_100_precision: float


@dataclass(frozen=True)
class Evaluation:
    """Recall@K per K, the PR curve, and how many queries were scored or excluded and why."""

    recall: dict[int, float]
    pr: PRCurve
    queries_evaluated: int
    excluded_no_window: int
    excluded_no_positive: int
    no_positive: NoPositivePolicy
    correct: np.ndarray = field(repr=False)
    frame_precision: float = float("nan")  # per-frame correspondences of the top-1 matches that are right

    @property
    def queries_excluded(self) -> int:
        return self.excluded_no_window + self.excluded_no_positive


def hit_matrix(predictions: np.ndarray, query_rows: np.ndarray, gt: GroundTruth) -> np.ndarray:
    """Boolean [n, K]: prediction k of query ``query_rows[i]`` is a positive (-1 entries are never)."""
    return gt.contains(query_rows[:, None], predictions)


def recall_at_k(hits: np.ndarray, ks: Sequence[int]) -> dict[int, float]:
    """Fraction of rows with a hit among the first k columns, for each k (k beyond K uses all K)."""
    if len(hits) == 0:
        return {int(k): float("nan") for k in ks}
    first_hit = np.where(hits.any(axis=1), hits.argmax(axis=1), np.iinfo(np.int64).max)
    return {int(k): float(np.mean(first_hit < k)) for k in ks}


def pr_curve(best_distances: np.ndarray, correct: np.ndarray, n_positive_queries: int, ignore: np.ndarray | None = None) -> PRCurve:
    """PR over thresholds on the best-match distance; ``ignore`` marks matches that are neither right nor wrong."""
    keep = np.isfinite(best_distances) if ignore is None else np.isfinite(best_distances) & ~ignore
    dist, ok = best_distances[keep], correct[keep]
    order = np.argsort(dist, kind="stable")
    dist, ok = dist[order], ok[order]
    last_of_tie = np.append(dist[1:] != dist[:-1], True) if len(dist) else np.zeros(0, bool)
    tp = np.cumsum(ok)[last_of_tie]
    accepted = (np.arange(len(dist)) + 1)[last_of_tie]
    precision = tp / np.maximum(accepted, 1)
    recall = tp / n_positive_queries if n_positive_queries else np.zeros(len(tp))
    thresholds = dist[last_of_tie]
    auc = float(np.sum(np.diff(np.concatenate([[0.0], recall])) * precision))
    perfect = recall[precision >= 1.0]
    return PRCurve(thresholds, precision, recall, auc, float(perfect.max()) if len(perfect) else 0.0)


def evaluate(
    predictions: np.ndarray,
    distances: np.ndarray,
    has_window: np.ndarray,
    gt: GroundTruth,
    ks: Sequence[int] = DEFAULT_KS,
    no_positive: NoPositivePolicy = "exclude",
) -> Evaluation:
    """Score top-K ``predictions`` [n_query, K] (reference rows, -1 = none) against ``gt``."""
    if no_positive not in ("exclude", "miss"):
        raise SettingError(f"{{no_positive}} must be 'exclude' or 'miss', got {no_positive!r}")
    if gt.shape[0] != len(predictions):
        raise SeqvprError(f"ground truth has {gt.shape[0]} queries but there are {len(predictions)} predictions")
    has_positive = gt.has_positive()
    scored = has_window & (has_positive | (no_positive == "miss"))
    rows = np.flatnonzero(scored)
    hits = hit_matrix(predictions[rows], rows, gt)
    best = predictions[rows, 0]
    ignore = gt.soft_contains(rows, best) & ~hits[:, 0] if gt.soft is not None else None
    pr = pr_curve(distances[rows, 0], hits[:, 0], int(np.count_nonzero(has_positive[rows])), ignore)
    return Evaluation(
        recall=recall_at_k(hits, ks),
        pr=pr,
        queries_evaluated=len(rows),
        excluded_no_window=int(np.count_nonzero(~has_window)),
        excluded_no_positive=int(np.count_nonzero(has_window & ~has_positive)) if no_positive == "exclude" else 0,
        no_positive=no_positive,
        correct=hits[:, 0],
    )


def frame_precision(query_rows: np.ndarray, reference_rows: np.ndarray, gt: GroundTruth) -> float:
    """The share of per-frame correspondences (query row, reference row; -1 = none) whose reference frame is a
    positive of its query frame, over the query frames that have a positive (NaN when none is counted)."""
    q, r = np.asarray(query_rows).ravel(), np.asarray(reference_rows).ravel()
    keep = (q >= 0) & (r >= 0)
    q, r = q[keep], r[keep]
    counted = gt.has_positive()[q]
    if not counted.any():
        return float("nan")
    return float(gt.contains(q[counted], r[counted]).mean())


