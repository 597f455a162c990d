"""Scoring a match result: Recall@K and PR against ground truth, and the precision of its top-1 matches'
per-frame correspondences."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from seqvpr.data.ground_truth import GroundTruth
from seqvpr.evaluation.metrics import DEFAULT_KS, Evaluation, NoPositivePolicy, evaluate

if TYPE_CHECKING:
    from seqvpr.results import MatchResult


def evaluate_match(
    result: MatchResult, gt: GroundTruth, ks: Sequence[int] = DEFAULT_KS, no_positive: NoPositivePolicy = "exclude",
    uniqueness: int | None = None,
) -> Evaluation:
    """Recall@K and PR of a match result, and the precision of its top-1 matches' per-frame correspondences. With
    ``uniqueness`` E, PR ranks the queries by SeqSLAM's windowed uniqueness (exclusion E frames), not by distance."""
    from seqvpr.evaluation.metrics import frame_precision
    from seqvpr.sequences.topk import uniqueness_margins

    top = result.topk
    scores = top.distances
    if uniqueness is not None:
        scores = uniqueness_margins(top.indices, top.distances, uniqueness)[:, None]
    evaluation = evaluate(top.indices, scores, top.has_window, gt, ks, no_positive)
    pairs = match_correspondences(result)
    return evaluation if pairs is None else replace(evaluation, frame_precision=frame_precision(*pairs, gt))


def match_correspondences(result: MatchResult) -> tuple[np.ndarray, np.ndarray] | None:
    """The per-frame correspondences (query rows, reference rows [n_query, L]) of a result's top-1 matches: the
    matcher's own (an adaptive path), else the windows' alignment at slope 1 (None with other velocities)."""
    from seqvpr.sequences.correspondences import window_correspondences

    if result.correspondences is not None:
        return result.correspondences
    spec = result.settings.sequence
    if tuple(spec.velocities) != (1.0,) or result.topk.indices.shape[1] == 0:
        return None
    return window_correspondences(result.topk.indices[:, 0], spec, result.query.segment_ids,
                                  result.reference.segment_ids)
