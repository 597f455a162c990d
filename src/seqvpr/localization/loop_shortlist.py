"""Loop closures over long drives in O(N S) (``seqvpr.localization.loops`` with ``shortlist`` S): each frame's S
nearest eligible earlier frames come from a faiss index that grows with the drive (HNSW by default: no training,
rows added as they become eligible), every frame of a window places candidate windows (``frame_shortlist``, as a
map's shortlist does), and the candidates are re-ranked by the exact sequence distance (``rerank_candidates`` with
the sequence family's ``candidate_distances``). With an exact index (``flat``) and S at least the drive's length
it equals the exhaustive pass.

Query frames are searched a block at a time against the rows eligible for the block's first frame, and compared
exactly with the few rows that become eligible within the block; each frame keeps its S nearest among the rows
eligible for it (with an exact index, whatever block it falls in).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from seqvpr.errors import SettingError
from seqvpr.results import TopK

#: query frames searched against the index at a time, at most
BLOCK = 1024
#: rows that may become eligible within one block (a block ends sooner where more would): compared exactly
EXTRA = 256


def check_shortlist_index(text: str):
    """The index a loop shortlist grows (``flat`` or ``hnsw:M``): IVF lists would be trained on rows the drive has
    not reached yet."""
    from seqvpr.maps.index import parse_index_spec

    spec = parse_index_spec(text)
    if spec.kind not in ("flat", "hnsw"):
        raise SettingError(f"a loop shortlist grows its index a frame at a time: {{shortlist_index}} flat or hnsw:M, "
                           f"not {text}")
    return spec


def shortlisted_topk(rows: torch.Tensor, segments: np.ndarray, spec, k: int, limits: np.ndarray, width: int,
                     index: str = "hnsw:32", progress: Callable[[int], None] | None = None) -> TopK:
    """Each frame's best ``k`` earlier windows (anchors below ``limits``) among the candidates its window's frames'
    ``width`` nearest eligible frames place, by exact sequence distance; [N, k], -1 / +inf where none."""
    from seqvpr.sequences.rerank import frame_shortlist
    from seqvpr.sequences.windows import window_starts

    array = rows.numpy() if rows.dtype == torch.float32 else rows.float().numpy()
    starts = window_starts(segments, spec.length, spec.offset, spec.boundary)
    neighbours = np.full((len(array), width), -1, np.int64)
    grown = GrowingIndex(check_shortlist_index(index), array)
    indices = np.full((len(array), k), -1, np.int64)
    distances = np.full((len(array), k), np.inf)
    for a, b in blocks(limits):
        neighbours[a:b] = grown.nearest_eligible(a, b, limits, width)
        candidates = frame_shortlist(neighbours, starts[a:b], spec, len(array))
        candidates.indices[candidates.indices >= limits[a:b, None]] = -1
        top = rerank_block(rows, array, starts, a, spec.length, candidates, k)
        kept = top.indices.shape[1]  # fewer than k where the block has fewer candidates
        indices[a:b, :kept], distances[a:b, :kept] = top.indices, top.distances
        if progress:
            progress(b - a)
    return TopK(indices, distances, starts >= 0)


def blocks(limits: np.ndarray) -> list[tuple[int, int]]:
    """Consecutive query blocks [a, b): at most ``BLOCK`` frames, and at most ``EXTRA`` rows becoming eligible
    between a block's first and last frame (a single frame where more do)."""
    found, a, n = [], 0, len(limits)
    while a < n:
        b = min(int(np.searchsorted(limits, limits[a] + EXTRA, "right")), a + BLOCK, n)
        b = max(b, a + 1)
        found.append((a, b))
        a = b
    return found


class GrowingIndex:
    """A faiss index over a drive's first rows, grown to the rows a block may reach before it is searched."""

    def __init__(self, spec, rows: np.ndarray) -> None:
        from seqvpr.maps.index import empty_index

        self.index, self.rows, self.added = empty_index(spec, rows.shape[1]), rows, 0

    def grow_to(self, count: int, rows: np.ndarray | None = None) -> None:
        """Rows up to ``count`` in the index (``rows``: the drive's rows now, where they grow in place)."""
        self.rows = self.rows if rows is None else rows
        if count > self.added:
            self.index.add(np.ascontiguousarray(self.rows[self.added : count], dtype=np.float32))
            self.added = count

    def nearest_eligible(self, a: int, b: int, limits: np.ndarray, width: int) -> np.ndarray:
        """Frames a..b-1's ``width`` nearest rows among those eligible for each ([b - a, width], -1 pads): the
        index (grown to the rows eligible for frame a) searched, merged with the exact distances to the few rows
        that become eligible within the block."""
        from seqvpr.maps.index import search_frames
        from seqvpr.sequences.topk import best_of

        queries = np.asarray(self.rows[a:b], dtype=np.float32)
        self.grow_to(int(limits[a]))
        if self.added:
            found, distances = search_frames(self.index, queries, min(width, self.added))
        else:
            found, distances = np.full((b - a, 0), -1, np.int64), np.zeros((b - a, 0))
        newest = np.arange(int(limits[a]), int(limits[b - 1]))
        if len(newest):
            near = euclidean(queries, np.asarray(self.rows[newest], np.float32))
            eligible = newest[None, :] < limits[a:b, None]
            found = np.concatenate([found, np.where(eligible, newest[None, :], -1)], axis=1)
            distances = np.concatenate([distances, np.where(eligible, near.astype(np.float64), np.inf)], axis=1)
        distances = np.where(found >= 0, distances, np.inf)
        kept, _ = best_of(found, distances, width) if found.shape[1] else (found, distances)
        return np.pad(kept, ((0, 0), (0, width - kept.shape[1])), constant_values=-1)

    def to_bytes(self) -> np.ndarray:
        """The index as bytes (a saved detector state keeps it: an HNSW graph is not rebuilt the same)."""
        import faiss

        return faiss.serialize_index(self.index)

    def load_bytes(self, data: np.ndarray, added: int) -> None:
        import faiss

        index = faiss.deserialize_index(np.ascontiguousarray(data, dtype=np.uint8))
        if index.ntotal != added or index.d != self.index.d:
            raise ValueError("the saved index does not hold the rows it names")
        self.index, self.added = index, added


def euclidean(queries: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Euclidean distances [n, m] of two sets of rows, by one product (as a flat index computes them)."""
    squared = (queries**2).sum(1)[:, None] + (rows**2).sum(1)[None, :] - 2.0 * queries @ rows.T
    return np.sqrt(np.maximum(squared, 0.0))


def rerank_block(rows: torch.Tensor, array: np.ndarray, starts: np.ndarray, a: int, length: int,
                 candidates: TopK, k: int) -> TopK:
    """The block's candidate windows (queries from row ``a``) scored by the exact sequence distance, the best ``k``
    kept."""
    from seqvpr.sequences.rerank import candidate_distances, rerank_candidates

    def distances_of(chosen: np.ndarray, anchors: np.ndarray) -> np.ndarray:
        r_starts = np.where(anchors >= 0, starts[np.maximum(anchors, 0)], -1)
        found = candidate_distances(rows, array, starts[a + chosen], r_starts, length)
        found[r_starts < 0] = np.inf
        return found

    return rerank_candidates(candidates, starts[a : a + len(candidates.indices)] >= 0, k, distances_of, batch=256)
