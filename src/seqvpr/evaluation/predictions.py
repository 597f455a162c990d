"""Per-query predictions as CSV: query, its top-K references (source indices) and distances, and correctness.

Columns: ``query`` (source frame index), ``query_name``, ``references`` and ``distances`` (space-separated,
best first), ``correct`` (1 if the best match is a positive, 0 if not, empty when the query has no positive).
Queries without a window are not written. The file is written atomically.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seqvpr.errors import SeqvprError
from seqvpr.io import atomic_write

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
) -> None:
    """Write one row per query; ``references`` hold source frame indices (-1 entries are dropped)."""
    with atomic_write(path, newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for i in range(len(query_frames)):
            ok = references[i] >= 0
            writer.writerow(
                [
                    int(query_frames[i]),
                    query_names[i],
                    " ".join(str(int(r)) for r in references[i][ok]),
                    " ".join(f"{d:.6g}" for d in distances[i][ok]),
                    (str(int(correct[i])) if has_positive[i] else ""),
                ]
            )


def read_predictions(path: str | Path) -> PredictionsFile:
    """Read a predictions CSV written by ``write_predictions`` (or by hand in the same columns)."""
    path = Path(path)
    if not path.exists():
        raise SeqvprError(f"{path}: predictions file not found")
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
    k = max(len(r) for r in refs)
    references = np.full((len(rows), max(k, 1)), -1, dtype=np.int64)
    distances = np.full((len(rows), max(k, 1)), np.inf)
    for i, (r, d) in enumerate(zip(refs, dists)):
        references[i, : len(r)] = r
        distances[i, : len(d)] = d
    return PredictionsFile(np.array(queries, dtype=np.int64), references, distances)
