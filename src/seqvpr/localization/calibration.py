"""A threshold a robot can trust: the lowest score threshold whose accepted estimates reach a target precision on a
calibration traversal with ground truth (recall is what is left to maximise)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seqvpr.errors import SeqvprError, SettingError


@dataclass(frozen=True)
class Threshold:
    """The chosen threshold, the precision and recall it gives where it was chosen, and whether the target was met
    (when no threshold meets it, the threshold accepts nothing: above every score)."""

    threshold: float
    precision: float
    recall: float
    reached: bool


def find_threshold(scores: np.ndarray, correct: np.ndarray, target: float, positives: int | None = None) -> Threshold:
    """Over the scored frames' ``scores`` and whether their best match was right, the smallest threshold whose
    accepted frames (score >= threshold) are right at least ``target`` of the time. Recall is over ``positives``
    frames (those with a true place; default: every frame given), since accepting a frame with none is wrong."""
    if not 0.0 < target <= 1.0:
        raise SettingError(f"{{target_precision}} must be in (0, 1], got {target}")
    scores, correct = np.asarray(scores, np.float64), np.asarray(correct, bool)
    if not len(scores):
        raise SeqvprError("cannot calibrate: no frame of the calibration traversal was scored")
    order = np.argsort(-scores, kind="stable")
    ranked, right = scores[order], correct[order]
    last_of_tie = np.append(ranked[1:] != ranked[:-1], True)
    accepted = np.arange(1, len(ranked) + 1)[last_of_tie]
    hits = np.cumsum(right)[last_of_tie]
    precision, recall = hits / accepted, hits / max(len(ranked) if positives is None else positives, 1)
    meets = np.flatnonzero(precision >= target - 1e-12)
    if not len(meets):
        return Threshold(float(np.nextafter(ranked[0], np.inf)), 0.0, 0.0, False)
    best = meets[-1]  # the lowest threshold (most accepted) that still meets the target
    return Threshold(float(ranked[last_of_tie][best]), float(precision[best]), float(recall[best]), True)


def precision_at(scores: np.ndarray, correct: np.ndarray, threshold: float,
                 positives: int | None = None) -> tuple[float, float]:
    """Precision and recall (over ``positives`` frames, default all) of accepting the frames whose score reaches
    ``threshold`` (precision 1 if none is)."""
    accepted = np.asarray(scores) >= threshold
    return precision_recall(accepted, np.asarray(correct), len(accepted) if positives is None else positives)


def precision_recall(accepted: np.ndarray, correct: np.ndarray, positives: int) -> tuple[float, float]:
    """Precision of the accepted frames (1 if none is) and their correct share of ``positives``."""
    n, right = int(accepted.sum()), int((accepted & correct).sum())
    return (right / n if n else 1.0), (right / positives if positives else 0.0)
