"""Per-query predictions as CSV: query, its top-K references (source indices) and distances, and correctness.

Columns: ``query`` (source frame index), ``query_name``, ``references`` and ``distances`` (space-separated,
best first), ``correct`` (1 if the best match is a positive, 0 if not, empty when the query has no positive).
Queries without a window are not written. The file is written atomically.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from seqvpr.data.ground_truth import GroundTruth
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError, reading
from seqvpr.evaluation.metrics import DEFAULT_KS, Evaluation, NoPositivePolicy, evaluate
from seqvpr.io import atomic_write

if TYPE_CHECKING:
    from seqvpr.results import MatchResult

COLUMNS = ("query", "query_name", "references", "distances", "correct")


@dataclass(frozen=True)
class PredictionsFile:
    """Predictions read back: source query indices, [n, K] source reference indices (-1 pad) and distances."""

    query: np.ndarray
    references: np.ndarray
    distances: np.ndarray


def write_predictions(
    path: str | Path,
    query_frames: np.ndarray,
    query_names: list[str],
    references: np.ndarray,
    distances: np.ndarray,
    correct: np.ndarray,
    has_positive: np.ndarray,
    sessions: list[str] | None = None,
) -> None:
    """Write one row per query; ``references`` hold source frame indices (-1 entries are dropped); with ``sessions``
    (a map's), a last column names the session of each query's best map frame."""
    with atomic_write(path, newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow([*COLUMNS, *(["reference_session"] if sessions is not None else [])])
        for i in range(len(query_frames)):
            ok = references[i] >= 0
            writer.writerow(
                [
                    int(query_frames[i]),
                    query_names[i],
                    " ".join(str(int(r)) for r in references[i][ok]),
                    " ".join(f"{d:.6g}" for d in distances[i][ok]),
                    (str(int(correct[i])) if has_positive[i] else ""),
                    *([sessions[i]] if sessions is not None else []),
                ]
            )


def read_predictions(path: str | Path) -> PredictionsFile:
    """Read a predictions CSV written by ``write_predictions`` (or by hand in the same columns)."""
    path = Path(path)
    if not path.exists():
        raise SeqvprError(f"{path}: predictions file not found")
    from seqvpr.arrays import check_regular_file

    check_regular_file(path, "a predictions CSV")
    with reading(path, "a predictions CSV (UTF-8 text)"):
        return _read_predictions(path)


def _read_predictions(path: Path) -> PredictionsFile:
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        missing = [c for c in ("query", "references") if c not in (reader.fieldnames or [])]
        if missing:
            raise SeqvprError(f"{path}: missing column(s) {', '.join(missing)} (expected {', '.join(COLUMNS)})")
        rows = list(enumerate(reader, start=2))
    if not rows:
        raise SeqvprError(f"{path}: no prediction rows")
    queries, refs, dists = [], [], []
    for line, row in rows:
        try:
            queries.append(int(row["query"]))
            refs.append([int(x) for x in (row["references"] or "").split()])
            dists.append([float(x) for x in (row.get("distances") or "").split()] or [np.nan] * len(refs[-1]))
        except ValueError:
            raise SeqvprError(f"{path}: line {line}: query, references and distances must be numbers") from None
        if len(dists[-1]) != len(refs[-1]):
            raise SeqvprError(f"{path}: line {line}: {len(refs[-1])} references but {len(dists[-1])} distances")
        if row.get("distances") and not all(np.isfinite(d) or d == np.inf for d in dists[-1]):
            raise SeqvprError(f"{path}: line {line}: distances must be numbers (found NaN or -inf)")
    _check_unique_queries(path, queries, [line for line, _ in rows])
    k = max(len(r) for r in refs)
    references = np.full((len(rows), max(k, 1)), -1, dtype=np.int64)
    distances = np.full((len(rows), max(k, 1)), np.inf)
    if min(queries) < 0 or min((min(r) for r in refs if r), default=0) < 0:
        raise SeqvprError(f"{path}: query and reference rows must be >= 0")
    for i, (r, d) in enumerate(zip(refs, dists)):
        references[i, : len(r)] = r
        distances[i, : len(d)] = d
    return PredictionsFile(np.array(queries, dtype=np.int64), references, distances)


def _check_unique_queries(path: Path, queries: list[int], lines: list[int]) -> None:
    """Each query once: a second row for a query would silently replace the first."""
    seen: dict[int, int] = {}
    for query, line in zip(queries, lines):
        if query in seen:
            raise SeqvprError(f"{path}: line {line}: query {query} again (first on line {seen[query]}); one row a query")
        seen[query] = line


def save_match_predictions(path: str | Path, result: MatchResult, gt: GroundTruth) -> None:
    """A match result's predictions CSV in source frame indices, for the queries that have a window."""
    top = result.topk
    rows = np.flatnonzero(top.has_window)
    ref_frames = result.reference.frame_index
    refs = np.where(top.indices[rows] >= 0, ref_frames[np.maximum(top.indices[rows], 0)], -1)
    names = result.query.frame_names()
    correct = gt.contains(rows, top.indices[rows, 0])
    sessions = getattr(result.reference, "sessions_of_rows", None)  # a saved map's: each row's session
    write_predictions(path, result.query.frame_index[rows], [names[i] for i in rows], refs, top.distances[rows],
                      correct, gt.has_positive()[rows], sessions(top.indices[rows, 0]) if sessions else None)


CORRESPONDENCE_COLUMNS = ("query", "position", "query_frame", "reference_frame", "correct")


def save_correspondences(path: str | Path, result: MatchResult, pairs: tuple[np.ndarray, np.ndarray],
                         gt: GroundTruth) -> None:
    """The top-1 matches' per-frame correspondences as CSV, one row per pair: the query (source frame index of the
    frame whose window it is), the pair's position in the window, the query and reference source frames, and
    ``correct`` (1 / 0; empty where that query frame has no positive). Queries without a match are not written."""
    table = correspondence_rows(result, pairs, gt)
    with atomic_write(path, newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(CORRESPONDENCE_COLUMNS)
        writer.writerows(table)


def correspondence_rows(result: MatchResult, pairs: tuple[np.ndarray, np.ndarray], gt: GroundTruth) -> list[list]:
    """The rows of ``save_correspondences`` (query by query, window position in order), found with one
    ground-truth lookup for all pairs: per-pair lookups cost many times the matching at tens of thousands of queries."""
    q_rows, r_rows = (np.asarray(a, dtype=np.int64) for a in pairs)
    query, position = np.nonzero((q_rows >= 0) & (r_rows >= 0))
    q, r = q_rows[query, position], r_rows[query, position]
    correct = np.where(gt.has_positive()[q], gt.contains(q, r).astype(np.int64).astype(str), "")
    columns = (result.query.frame_index[query], position, result.query.frame_index[q],
               result.reference.frame_index[r])
    return [[*row, flag] for row, flag in zip(np.stack(columns, 1).astype(np.int64).tolist(), correct.tolist())]


def evaluate_predictions(
    path: str | Path, reference: Traversal, query: Traversal, gt: GroundTruth, ks: Sequence[int] = DEFAULT_KS,
    no_positive: NoPositivePolicy = "exclude",
) -> Evaluation:
    """Recall@K and PR of a predictions CSV against ground truth between the two traversals it indexes."""
    table = read_predictions(path)
    q_rows = _rows_of(query.frame_index, table.query, path, "query")
    r_rows = _rows_of(reference.frame_index, table.references, path, "reference")
    indices = np.full((len(query), table.references.shape[1]), -1, dtype=np.int64)
    distances = np.full(indices.shape, np.inf)
    indices[q_rows], distances[q_rows] = r_rows, table.distances
    has_window = np.zeros(len(query), dtype=bool)
    has_window[q_rows] = True
    return evaluate(indices, distances, has_window, gt, ks, no_positive)


def _rows_of(frame_index: np.ndarray, wanted: np.ndarray, path: str | Path, what: str) -> np.ndarray:
    """Rows of a traversal holding the given source frame indices (-1 stays -1); unknown indices are an error."""
    lookup = {int(f): row for row, f in enumerate(frame_index)}
    flat = wanted.ravel()
    rows = np.array([lookup.get(int(f), -2) if f >= 0 else -1 for f in flat], dtype=np.int64)
    if (rows == -2).any():
        missing = int(flat[np.flatnonzero(rows == -2)[0]])
        raise SeqvprError(f"{path}: {what} frame {missing} is not in the {what} traversal")
    return rows.reshape(wanted.shape)
