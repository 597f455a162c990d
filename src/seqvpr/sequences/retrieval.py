"""Retrieval over sequence descriptors with faiss: top-K reference frames per query frame, as a ``TopK``.

Window ids are mapped back to frame rows (``SequenceDescriptors.rows``), so the result plugs into
``evaluation.metrics.evaluate`` like the matching kernel's. Distances are Euclidean (not squared).

Same name as ``seqvpr.matchers.retrieval``: retrieval's faiss search; its matcher there.
"""

from __future__ import annotations

import faiss
import numpy as np

from seqvpr.errors import SeqvprError, SettingError
from seqvpr.sequences.descriptors import SequenceDescriptors
from seqvpr.results import TopK

INDEX_KINDS = ("flat", "hnsw")
HNSW_M = 32
HNSW_EF_SEARCH = 64


def build_index(vectors: np.ndarray, kind: str = "flat") -> faiss.Index:
    """A faiss index over ``vectors``: "flat" (IndexFlatL2, exact, the default) or "hnsw" (IndexHNSWFlat, M=32,
    approximate; built on one thread so the graph, hence every result, is reproducible)."""
    if kind not in INDEX_KINDS:
        raise SeqvprError(f"index kind {kind!r} is not known (choose from: {', '.join(INDEX_KINDS)})")
    data = _as_faiss(vectors, "reference")
    if kind == "flat":
        index = faiss.IndexFlatL2(data.shape[1])
        index.add(data)
        return index
    index = faiss.IndexHNSWFlat(data.shape[1], HNSW_M)
    index.hnsw.efSearch = HNSW_EF_SEARCH
    threads = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        index.add(data)
    finally:
        faiss.omp_set_num_threads(threads)
    return index


def retrieve(
    query: SequenceDescriptors,
    reference: SequenceDescriptors,
    k: int,
    *,
    index: faiss.Index | None = None,
    kind: str = "flat",
) -> TopK:
    """Top-``k`` reference frame rows per query frame by Euclidean distance between sequence descriptors.

    Frames without a window get -1 / +inf; ``k`` is capped at the number of reference windows. ``index`` (from
    ``build_index(reference.vectors)``) is reused if given, else one of ``kind`` is built.
    """
    if k < 1:
        raise SettingError(f"{{k}} must be at least 1, got {k}")
    if query.dim != reference.dim:
        raise SeqvprError(
            f"sequence descriptor dimensions differ: query has {query.dim}, reference has {reference.dim}"
        )
    if len(reference.vectors) == 0:
        raise SeqvprError("the reference has no sequence descriptors (no frame has a window)")
    if index is None:
        index = build_index(reference.vectors, kind)
    elif index.d != reference.dim or index.ntotal != len(reference.vectors):
        raise SeqvprError(
            f"the index holds {index.ntotal} vectors of {index.d}-D, the reference has {len(reference.vectors)} "
            f"of {reference.dim}-D"
        )
    k = min(k, len(reference.vectors))
    if len(query.vectors) == 0:
        return TopK(np.full((query.n_frames, k), -1, np.int64), np.full((query.n_frames, k), np.inf), query.has_window)
    squared, windows = index.search(_as_faiss(query.vectors, "query"), k)
    indices = np.full((query.n_frames, k), -1, dtype=np.int64)
    distances = np.full((query.n_frames, k), np.inf, dtype=np.float64)
    found = windows >= 0
    indices[query.rows] = np.where(found, reference.rows[np.where(found, windows, 0)], -1)
    distances[query.rows] = np.where(found, np.sqrt(np.maximum(squared.astype(np.float64), 0.0)), np.inf)
    return TopK(indices, distances, query.has_window)


def _as_faiss(vectors: np.ndarray, what: str) -> np.ndarray:
    """C-contiguous float32 [n, d] as faiss wants it, after checking shape and finiteness."""
    data = np.ascontiguousarray(vectors, dtype=np.float32)
    if data.ndim != 2 or data.shape[1] == 0:
        raise SeqvprError(f"{what} sequence descriptors must be [n, D], got shape {data.shape}")
    if not np.isfinite(data).all():
        raise SeqvprError(f"{what} sequence descriptors contain NaN or inf")
    return data
