"""A topological filter over reference frames (an HMM forward pass): the alternative to fixed-slope windows.

The state is the reference frame the query is at. Each query frame moves the belief by a window of steps (standing
still, going back a little, going faster than one frame per frame), never across a reference segment break (mass
that would leave a segment stops at its end), then mixes in a floor so that a kidnapped robot can be found again,
and weighs each frame by the likelihood ``exp(-(d - min d) / scale)`` of its frame distance. ``scale`` comes from
the map's own distance quantiles (``distance_scale``). The score is the belief mass near the most likely frame.

Same name as ``seqvpr.matchers.filter``: the filter's algorithm; its matcher there.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from seqvpr import checks
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.sequences.matching import ReferenceRows, distances_to_reference
from seqvpr.sequences.topk import best_k
from seqvpr.results import TopK
from seqvpr.sequences.windows import segment_bounds


#: the most map frames the filter lets one query frame move (each step is a pass over the belief)
MAX_STEP = 1000


@dataclass(frozen=True)
class FilterSettings:
    """Steps a query frame may move the state (``min_step``..``max_step`` reference frames, equally likely), the
    probability per frame of a jump anywhere (``floor``), how sharply distances above the best are discounted
    (``sharpness``: the scale is the map's median spread divided by it) and the score's half-width in frames."""

    min_step: int = 0
    max_step: int = 2
    floor: float = 1e-3
    sharpness: float = 1.5
    radius: int = 2

    def __post_init__(self) -> None:
        for name, least in (("min_step", None), ("max_step", None), ("radius", 0)):
            object.__setattr__(self, name, checks.whole(getattr(self, name), name, least))
        object.__setattr__(self, "floor", checks.finite(self.floor, "floor", 0.0, 1.0))
        object.__setattr__(self, "sharpness", checks.finite(self.sharpness, "sharpness", 0.0, open_low=True))
        if self.min_step > self.max_step:
            raise SeqvprError(f"filter steps: min_step {self.min_step} is above max_step {self.max_step}")
        if self.max_step > MAX_STEP:  # each step a frame is a pass over the belief
            raise SettingError(f"filter steps: {{max_step}} {self.max_step} is above {MAX_STEP} map frames per frame")
        if self.floor >= 1.0:
            raise SettingError(f"filter {{floor}} must be in [0, 1), got {self.floor}")

    def as_dict(self) -> dict:
        return asdict(self)


class TopologicalFilter:
    """Belief [N] over reference frames, advanced by one query frame's distances [N] per ``step``."""

    def __init__(self, reference_segments: np.ndarray, scale: float, settings: FilterSettings = FilterSettings()):
        if not np.isfinite(scale) or scale <= 0:
            raise SeqvprError(f"filter scale must be a positive number, got {scale}")
        segments = np.asarray(reference_segments)
        self.settings, self.scale, self.n = settings, float(scale), len(segments)
        start, end = segment_bounds(segments)
        rows = np.arange(self.n)
        self.targets = [np.clip(rows + step, start, end - 1) for step in range(settings.min_step, settings.max_step + 1)]
        self.belief = np.full(self.n, 1.0 / self.n)
        self.count = 0

    def reset(self) -> None:
        """Anywhere, equally likely: a new drive or a kidnapping."""
        self.belief[:] = 1.0 / self.n
        self.count = 0

    def step(self, distances: np.ndarray) -> np.ndarray:
        """The belief after one more query frame with these frame distances to every reference frame."""
        if distances.shape != (self.n,):
            raise SeqvprError(f"expected distances to the {self.n} reference frames, got shape {distances.shape}")
        weight = 1.0 / len(self.targets)
        moved = np.zeros(self.n)
        for target in self.targets:
            moved += np.bincount(target, weights=self.belief, minlength=self.n)
        moved *= weight * (1.0 - self.settings.floor)
        moved += self.settings.floor / self.n
        finite = np.isfinite(distances)
        lowest = distances[finite].min() if finite.any() else 0.0
        likelihood = np.exp(-(np.where(finite, distances, np.inf) - lowest) / self.scale)
        posterior = moved * likelihood
        total = posterior.sum()
        self.belief = posterior / total if total > 0 else np.full(self.n, 1.0 / self.n)
        self.count += 1
        return self.belief

    def mass(self) -> np.ndarray:
        """Belief mass within ``radius`` frames of each reference frame [N]: the estimate is its largest, and its
        value the score (near 1 when the filter is sure, small when not)."""
        r = self.settings.radius
        return np.convolve(self.belief, np.ones(2 * r + 1), mode="same") if r else self.belief.copy()

    def state(self) -> dict[str, np.ndarray]:
        return {"belief": self.belief.copy(), "count": np.array(self.count)}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        if state["belief"].shape != self.belief.shape:
            raise SeqvprError(f"saved belief has {state['belief'].shape[0]} states, this map has {self.n}")
        self.belief = state["belief"].astype(np.float64)
        self.count = int(state["count"])


def distance_scale(sample_distances: np.ndarray, sharpness: float, exclusion: int, rows: np.ndarray) -> float:
    """The likelihood scale from map-to-map distances [s, N] of sample map frames ``rows``: the median over the
    samples of (median distance - 1st percentile), their own neighbourhood (``exclusion`` frames) left out, divided
    by ``sharpness``."""
    spreads = []
    for values, row in zip(np.asarray(sample_distances, dtype=np.float64), rows):
        keep = np.ones(len(values), bool)
        keep[max(row - exclusion, 0) : row + exclusion + 1] = False
        kept = values[keep & np.isfinite(values)]
        if len(kept) > 1:
            spreads.append(np.median(kept) - np.percentile(kept, 1))
    spread = float(np.median(spreads)) if spreads else 0.0
    if not spread > 0:
        raise SeqvprError("cannot calibrate the filter: the map's frames are all equally far apart")
    return spread / sharpness


def map_distance_scale(
    reference: ReferenceRows, norms: np.ndarray, settings: FilterSettings, samples: int = 64, seed: int = 0,
    exclusion: int = 10,
) -> float:
    """``distance_scale`` from ``samples`` map frames drawn with ``seed``, measured against the whole map."""
    rng = np.random.default_rng(seed)
    rows = np.sort(rng.choice(len(reference), size=min(samples, len(reference)), replace=False))
    picked = torch.as_tensor(np.asarray(reference[rows] if not isinstance(reference, torch.Tensor)
                                        else reference[torch.as_tensor(rows)].cpu(), dtype=np.float32))
    return distance_scale(distances_to_reference(picked, reference, norms), settings.sharpness, exclusion, rows)


def filter_topk(
    query: torch.Tensor, reference: ReferenceRows, norms: np.ndarray, filter_: TopologicalFilter, k: int,
    query_segments: np.ndarray, block: int = 256,
) -> TopK:
    """The filter run over a whole query traversal in order (reset at each query segment break): per query frame
    the K reference frames of most belief mass, with distances ``1 - mass`` (the first one's is 1 - score)."""
    n = len(query)
    k = min(k, filter_.n)
    indices, distances = np.full((n, k), -1, np.int64), np.full((n, k), np.inf)
    segments = np.asarray(query_segments)
    filter_.reset()
    for lo in range(0, n, block):
        rows = distances_to_reference(query[lo : lo + block], reference, norms)
        for i, row in enumerate(rows, start=lo):
            if i and segments[i] != segments[i - 1]:
                filter_.reset()
            filter_.step(row.astype(np.float64))
            indices[i], distances[i] = best_k(1.0 - filter_.mass(), k)
    return TopK(indices, distances, np.ones(n, bool))
