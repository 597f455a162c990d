"""A recorded query traversal replayed as a stream through a localiser, and what a robot would want to know of it:
Recall@K, PR over the score, recall at 100 % precision, precision at the threshold, time to the first correct
confident estimate after each start, and latency percentiles."""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from seqvpr.data.geo import utm_to_latlon
from seqvpr.data.ground_truth import GroundTruth
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation, evaluate
from seqvpr.io import atomic_write
from seqvpr.localization.calibration import precision_recall
from seqvpr.localization.localizer import Estimate, Localizer, next_status

STAGES = ("describe", "distance", "sequence", "total")


@dataclass(frozen=True)
class Replay:
    """Per query frame: the localised map frame (-1: none, the frame is not ``localised``), the best map frame (-1
    while warming up), score (NaN while warming up), status, top-K, latency [n, 4] in ms (``STAGES``), whether
    keyframe gating kept it, and the query traversal; with the threshold the statuses were decided at and where
    it came from."""

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
    threshold: float = float("nan")
    threshold_source: str = ""

    @property
    def scored(self) -> np.ndarray:
        return self.status != "warming up"

    @property
    def localized(self) -> np.ndarray:
        """The frames whose estimate the localiser stands behind."""
        return self.status == "localised"


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
    run = _collect(query, estimates, localizer.settings.k)
    return replace(run, threshold=localizer.threshold, threshold_source=localizer.threshold_source)


def _collect(query: Traversal, estimates: Sequence[Estimate], k: int) -> Replay:
    n = len(estimates)
    indices, distances = np.full((n, k), -1, np.int64), np.full((n, k), np.inf)
    for i, e in enumerate(estimates):
        indices[i, : len(e.indices)], distances[i, : len(e.distances)] = e.indices, e.distances
    starts = np.flatnonzero(np.r_[True, np.diff(query.segment_ids) != 0])
    row = lambda value: -1 if value is None else value  # noqa: E731
    return Replay(query, np.array([row(e.index) for e in estimates]), np.array([row(e.best) for e in estimates]),
                  np.array([e.score for e in estimates], np.float64), np.array([e.status for e in estimates]),
                  indices, distances, np.array([[e.latency.get(s, 0.0) for s in STAGES] for e in estimates]),
                  np.array([e.kept for e in estimates]), starts)


def at_threshold(run: Replay, threshold: float, lost_after: int, source: str) -> Replay:
    """The replay as it would have gone at another threshold (``--calibrate`` reports at the threshold it chose):
    each frame's status from the scores, as the localiser decides it, and the localised frames with it."""
    status, misses, starts = run.status.copy(), 0, set(run.starts.tolist())
    for i in range(len(status)):
        if i in starts:
            misses = 0
        if run.status[i] == "warming up":
            continue
        if not run.kept[i]:  # keyframe gating repeats the previous estimate
            status[i] = status[i - 1]
            continue
        status[i], misses = next_status(float(run.score[i]), threshold, misses, lost_after)
    index = np.where(status == "localised", run.best, -1)
    return replace(run, status=status, index=index, threshold=threshold, threshold_source=source)


@dataclass(frozen=True)
class ReplayScores:
    """Recall@K and PR (over the score) of the scored frames; the precision of the localised estimates (a frame
    localised where the map holds no true place counts as wrong) and their recall (over the frames with a true
    place); frames and seconds to the first correct localised estimate after each start (None: never); latency
    percentiles (ms); the frames in each status."""

    evaluation: Evaluation
    threshold: float
    precision: float
    recall: float
    time_to_correct: list[tuple[int | None, float | None]]
    latency: dict[str, dict[str, float]]
    localized_correct: int
    localized_wrong: int


def score_replay(run: Replay, gt: GroundTruth, ks: Sequence[int] = (1, 5, 10, 20)) -> ReplayScores:
    """What the replay got right, the score ranking the best matches for the PR curve."""
    ranked = run.distances.copy()
    ranked[:, 0] = -np.nan_to_num(run.score, nan=-np.inf)  # PR sweeps the score, highest first
    evaluation = evaluate(run.indices, ranked, run.scored, gt, ks)
    right = correct_best(run, gt)
    positives = int((run.scored & gt.has_positive()).sum())
    precision, recall = precision_recall(run.localized, right, positives)
    correct = int((run.localized & right).sum())
    return ReplayScores(evaluation, run.threshold, precision, recall, time_to_correct(run, right),
                        latency_percentiles(run), correct, int(run.localized.sum()) - correct)


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


STREAM_COLUMNS = ("frame", "query_frame", "timestamp", "status", "score", "localised_row", "localised_frame", "x", "y",
                  "latitude", "longitude", "best_row", "best_frame", "kept", *(f"{s}_ms" for s in STAGES), "correct",
                  "best_session")


def write_stream(path: str | Path, run: Replay, reference: Traversal, right: np.ndarray | None = None,
                 sessions_of=None) -> None:
    """One row per query frame: status and score; the localised map frame (as a map row and as a frame of its
    source, the numbering ``predictions.csv`` uses) and its position (and latitude/longitude when the map's
    positions are UTM), empty unless the frame is localised; the
    best-scoring map frame whatever the status (empty while warming up); latencies; whether the best is right; the
    session of the best map frame (``sessions_of(rows)``: the map's, ``SavedMap.sessions_of_rows``)."""
    with atomic_write(path, newline="") as handle:
        out = csv.writer(handle)
        out.writerow(STREAM_COLUMNS)
        latlon = None if reference.positions is None else utm_to_latlon(reference.positions, reference.crs)
        sessions = sessions_of or (lambda rows: [""] * len(rows))
        for i, session in enumerate(sessions(np.asarray(run.best))):
            out.writerow([*_stream_row(run, reference, latlon, right, i), session])


def _stream_row(run: Replay, reference: Traversal, latlon: np.ndarray | None, right: np.ndarray | None, i: int) -> list:
    stamp = "" if run.query.timestamps is None else f"{run.query.timestamps[i]:.6f}"
    localized, best = int(run.index[i]), int(run.best[i])
    row = lambda r: "" if r < 0 else r  # noqa: E731
    source = lambda r: "" if r < 0 else int(reference.frame_index[r])  # noqa: E731
    where = ["", ""] if localized < 0 or reference.positions is None else \
        [f"{v:.3f}" for v in reference.positions[localized][:2]]
    where += ["", ""] if localized < 0 or latlon is None else [f"{v:.8f}" for v in latlon[localized]]
    score = "" if not run.scored[i] else f"{run.score[i]:.6f}"
    ok = "" if right is None or not run.scored[i] else int(right[i])
    return [i, int(run.query.frame_index[i]), stamp, run.status[i], score, row(localized), source(localized), *where,
            row(best), source(best), int(run.kept[i]), *(f"{v:.3f}" for v in run.latency[i]), ok]
