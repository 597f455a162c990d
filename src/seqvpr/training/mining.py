"""Sequence-based online hard-negative mining: positives and negatives ranked by the matching kernel.

The miner is given a kernel (``DistanceRows``): a function from transformed query/reference frames and query
window starts to sequence distances against every reference window. ``seqmatch_rows`` is the core kernel;
``centre_frame_rows`` is the "single" ablation over the same windows. Tests and benchmarks inject other kernels
(brute force, the reference code's per-query L x L matrices) into the same miner.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from seqvpr.data.ground_truth import GroundTruth
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.sequences.matching import sequence_distance_rows
from seqvpr.sequences.topk import rank_order
from seqvpr.sequences.windows import SequenceSpec, window_starts
from seqvpr.training.losses import DEFAULT_MARGIN, SequenceMethod

#: (query frames [n_q, D], reference frames [n_r, D], query window starts [R]) -> distances [R, n_r] (+inf: no window)
DistanceRows = Callable[[torch.Tensor, torch.Tensor, np.ndarray], torch.Tensor]


def seqmatch_rows(spec: SequenceSpec, reference_segments: np.ndarray) -> DistanceRows:
    """The core kernel: mean order-aligned frame distance between query windows and every reference window."""

    def rows(query: torch.Tensor, reference: torch.Tensor, starts: np.ndarray) -> torch.Tensor:
        return sequence_distance_rows(query, reference, spec, starts, reference_segments)

    return rows


def centre_frame_rows(spec: SequenceSpec, reference_segments: np.ndarray) -> DistanceRows:
    """'single' mining: the distance between the windows' centre frames (same windows, one frame each)."""
    ref_starts = window_starts(np.asarray(reference_segments), spec.length, spec.offset, spec.boundary)
    valid = torch.as_tensor(ref_starts >= 0)
    centres = torch.as_tensor(np.where(ref_starts >= 0, ref_starts + spec.offset, 0))

    def rows(query: torch.Tensor, reference: torch.Tensor, starts: np.ndarray) -> torch.Tensor:
        single = sequence_distance_rows(query, reference, SequenceSpec(1), np.asarray(starts) + spec.offset)
        out = single[:, centres.to(single.device)]
        return out.masked_fill_(~valid.to(single.device), float("inf"))

    return rows


def mining_kernel(method: SequenceMethod, spec: SequenceSpec, reference_segments: np.ndarray) -> DistanceRows:
    if method == "seqmatch":
        return seqmatch_rows(spec, reference_segments)
    if method == "single":
        return centre_frame_rows(spec, reference_segments)
    raise SettingError(f"{{mining}} must be 'seqmatch' or 'single', got {method!r}")


MAX_NEGATIVES = 1000  # hard negatives mined a query


@dataclass(frozen=True)
class MiningConfig:
    """n hardest negatives from a pool (``pool`` random candidates plus the query's previous negatives; None =
    every negative), kept only if they violate the margin (the reference's rule)."""

    negatives: int = 10
    pool: int | None = 1000
    margin: float = DEFAULT_MARGIN
    only_violating: bool = True

    def __post_init__(self) -> None:
        if not 1 <= self.negatives <= MAX_NEGATIVES:  # the negative cache holds this many a query
            raise SettingError(f"{{negatives}} must be from 1 to {MAX_NEGATIVES}, got {self.negatives}")
        if self.pool is not None and self.pool < 1:
            raise SeqvprError(f"negative pool must be >= 1 (or all), got {self.pool}")


@dataclass(frozen=True)
class Triplet:
    """A query frame, its best positive reference frame and its hard negative reference frames (rows)."""

    query: int
    positive: int
    negatives: np.ndarray
    positive_distance: float
    negative_distances: np.ndarray


class SequenceMiner:
    """Mines (query, best positive, hard negatives) over the whole training reference with an injected kernel."""

    def __init__(
        self,
        kernel: DistanceRows,
        query_starts: np.ndarray,
        positives: GroundTruth,
        near: GroundTruth,
        config: MiningConfig = MiningConfig(),
    ) -> None:
        """``positives``: within the positive radius; ``near``: within the negative radius (never negatives)."""
        self.kernel = kernel
        self.query_starts = np.asarray(query_starts)
        self.positives = positives
        self.near = near
        self.config = config
        self.cache: dict[int, np.ndarray] = {}

    def mine(
        self, query: torch.Tensor, reference: torch.Tensor, queries: np.ndarray, rng: np.random.Generator
    ) -> list[Triplet]:
        """Triplets for the given query rows (those with a window); queries with nothing to learn are skipped."""
        queries = np.asarray([q for q in queries if self.query_starts[q] >= 0], dtype=np.int64)
        if len(queries) == 0:
            return []
        with torch.no_grad():
            rows = self.kernel(query, reference, self.query_starts[queries]).double().cpu().numpy()
        triplets = []
        for query_row, distances in zip(queries, rows):
            triplet = self._select(int(query_row), distances, rng)
            if triplet is not None:
                triplets.append(triplet)
        return triplets

    def _select(self, query: int, distances: np.ndarray, rng: np.random.Generator) -> Triplet | None:
        finite = np.isfinite(distances)
        positives = self.positives.positives_of(query)
        positives = positives[finite[positives]]
        if len(positives) == 0:
            return None
        best = int(positives[np.argmin(distances[positives])])
        candidates = finite.copy()
        candidates[self.near.positives_of(query)] = False
        negatives = np.flatnonzero(candidates)
        if len(negatives) == 0:
            return None
        pool = self._pool(query, negatives, rng)
        order = rank_order(pool, distances[pool], self.config.negatives)
        chosen = pool[order]
        self.cache[query] = chosen
        d_p = float(distances[best])
        if self.config.only_violating:
            chosen = chosen[distances[chosen] < d_p + self.config.margin]
        if len(chosen) == 0:
            return None
        return Triplet(query, best, chosen, d_p, distances[chosen])

    def _pool(self, query: int, negatives: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Random candidates plus the query's cached negatives, unique and sorted (None pool = all negatives)."""
        if self.config.pool is None or self.config.pool >= len(negatives):
            return negatives
        drawn = rng.choice(negatives, size=self.config.pool, replace=False)
        return np.union1d(drawn, self.cache.get(query, np.empty(0, dtype=np.int64)))

    def cache_array(self, n_queries: int) -> np.ndarray:
        """The negative cache as [n_queries, negatives] rows padded with -1 (for checkpoints)."""
        out = np.full((n_queries, self.config.negatives), -1, dtype=np.int64)
        for query, values in self.cache.items():
            out[query, : len(values)] = values
        return out

    def load_cache(self, array: np.ndarray) -> None:
        self.cache = {int(q): row[row >= 0] for q, row in enumerate(np.asarray(array)) if (row >= 0).any()}
