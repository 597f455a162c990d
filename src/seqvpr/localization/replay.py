"""A recorded query traversal replayed as a stream through a localiser, and what a robot would want to know of it:
Recall@K, PR over the score, recall at 100 % precision, precision at the threshold, time to the first correct
confident estimate after each start, and latency percentiles."""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from seqvpr.data.groundtruth import GroundTruth
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation, evaluate
from seqvpr.io import atomic_write
from seqvpr.localization.calibration import precision_at
from seqvpr.localization.localizer import Estimate, Localizer

STAGES = ("describe", "distance", "sequence", "total")


@dataclass(frozen=True)
class Replay:
    """Per query frame: the trusted estimate (-1: none), the best map frame, score, status, top-K, latency [n, 4]
    in ms (``STAGES``), whether keyframe gating kept it, and the query traversal."""

    query: Traversal
    index: np.ndarray
    best: np.ndarray
    score: np.ndarray
    status: np.ndarray
    indices: np.ndarray
    distances: np.ndarray
    latency: np.ndarray
    kept: np.ndarray
    starts: np.ndarray = field(repr=False)  # frames where the localiser (re)started: 0 and each segment break

    @property
    def scored(self) -> np.ndarray:
        return self.status != "warming up"


def replay(localizer: Localizer, query: Traversal, progress: Callable[[int], None] | None = None) -> Replay:
    """Feed the query's frames (descriptors, else images) one by one; reset at each query segment break."""
    frames = query.descriptors if query.descriptors is not None else query.image_paths
    if frames is None or not len(query):
        raise SeqvprError(f"{query.source or query.name}: no frames to localise")
    segments, stamps = query.segment_ids, query.timestamps
    estimates: list[Estimate] = []
    for i in range(len(query)):
        if i and segments[i] != segments[i - 1]:
            localizer.reset()
        estimates.append(localizer.update(frames[i], None if stamps is None else float(stamps[i])))
        if progress is not None:
            progress(1)
    return _collect(query, estimates, localizer.settings.k)


def _collect(query: Traversal, estimates: Sequence[Estimate], k: int) -> Replay:
    n = len(estimates)
    indices, distances = np.full((n, k), -1, np.int64), np.full((n, k), np.inf)
    for i, e in enumerate(estimates):
        indices[i, : len(e.indices)], distances[i, : len(e.distances)] = e.indices, e.distances
    starts = np.flatnonzero(np.r_[True, np.diff(query.segment_ids) != 0])
    return Replay(query, np.array([e.index for e in estimates]), np.array([e.best for e in estimates]),
                  np.array([e.score for e in estimates]), np.array([e.status for e in estimates]), indices, distances,
                  np.array([[e.latency.get(s, 0.0) for s in STAGES] for e in estimates]),
                  np.array([e.kept for e in estimates]), starts)


@dataclass(frozen=True)
class ReplayScores:
    """Recall@K and PR (over the score) of the scored frames, precision and recall at the threshold, frames and
    seconds to the first correct localised estimate after each start (None: never), latency percentiles (ms)."""

    evaluation: Evaluation
    threshold: float
    precision: float
    recall: float
    time_to_correct: list[tuple[int | None, float | None]]
    latency: dict[str, dict[str, float]]


def score_replay(run: Replay, gt: GroundTruth, threshold: float, ks: Sequence[int] = (1, 5, 10, 20)) -> ReplayScores:
    """What the replay got right, the score ranking the best matches for the PR curve."""
    ranked = run.distances.copy()
    ranked[:, 0] = -run.score  # PR sweeps the score, highest first
    evaluation = evaluate(run.indices, ranked, run.scored, gt, ks)
    usable = run.scored & gt.has_positive()
    right = correct_best(run, gt)
    precision, recall = precision_at(run.score[usable], right[usable], threshold)
    return ReplayScores(evaluation, threshold, precision, recall, time_to_correct(run, right), latency_percentiles(run))


def correct_best(run: Replay, gt: GroundTruth) -> np.ndarray:
    """Whether each frame's best map frame is a true place."""
    rows = np.arange(len(run.best))
    return np.asarray(gt.contains(rows, run.best)) & (run.best >= 0)


def time_to_correct(run: Replay, right: np.ndarray) -> list[tuple[int | None, float | None]]:
    """Per start, frames (and seconds, with timestamps) until the first localised and correct estimate."""
    out = []
    ends = np.r_[run.starts[1:], len(run.best)]
    stamps = run.query.timestamps
    for start, end in zip(run.starts, ends):
        good = np.flatnonzero((run.status[start:end] == "localised") & right[start:end])
        if not len(good):
            out.append((None, None))
            continue
        frames = int(good[0])
        seconds = None if stamps is None else float(stamps[start + frames] - stamps[start])
        out.append((frames, seconds))
    return out


def latency_percentiles(run: Replay) -> dict[str, dict[str, float]]:
    """p50/p95/p99 (ms) of each stage over the frames that were processed (not skipped by keyframe gating)."""
    rows = run.latency[run.kept]
    if not len(rows):
        return {}
    return {stage: {f"p{q}": float(np.percentile(rows[:, i], q)) for q in (50, 95, 99)}
            for i, stage in enumerate(STAGES)}


def write_stream(path: str | Path, run: Replay, reference: Traversal, right: np.ndarray | None = None) -> None:
    """One row per query frame: status and score, the trusted and the best map frame (as map rows and as frames of
    their source, the numbering ``predictions.csv`` uses), the best one's position, latencies, and correctness."""
    with atomic_write(path, newline="") as handle:
        out = csv.writer(handle)
        out.writerow(["frame", "query_frame", "timestamp", "status", "score", "estimate_row", "estimate_frame",
                      "best_row", "best_frame", "x", "y", "kept", *(f"{s}_ms" for s in STAGES), "correct"])
        for i in range(len(run.best)):
            out.writerow(_stream_row(run, reference, right, i))


def _stream_row(run: Replay, reference: Traversal, right: np.ndarray | None, i: int) -> list:
    stamp = "" if run.query.timestamps is None else f"{run.query.timestamps[i]:.6f}"
    estimate, best = int(run.index[i]), int(run.best[i])
    source = lambda row: int(reference.frame_index[row]) if row >= 0 else -1  # noqa: E731
    where = ["", ""] if best < 0 or reference.positions is None else [f"{v:.3f}" for v in reference.positions[best][:2]]
    ok = "" if right is None or not run.scored[i] else int(right[i])
    return [i, int(run.query.frame_index[i]), stamp, run.status[i], f"{run.score[i]:.6f}", estimate, source(estimate),
            best, source(best), *where, int(run.kept[i]), *(f"{v:.3f}" for v in run.latency[i]), ok]
