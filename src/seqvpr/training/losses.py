"""Triplet loss whose distance is the matching kernel's sequence distance (SeqMatchNet), or the centre frame's."""

from __future__ import annotations

import torch

from seqvpr.sequences.matching import aligned_sequence_distances
from seqvpr.training.settings import DEFAULT_MARGIN, SequenceMethod, window_part  # noqa: F401 (re-exported)


def euclidean(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Row-wise Euclidean distance with a clamped sqrt (finite gradient at distance 0)."""
    return (a - b).pow(2).sum(-1).clamp_min(eps).sqrt()


def triplet_hinge(d_ap: torch.Tensor, d_an: torch.Tensor, margin: float = DEFAULT_MARGIN) -> torch.Tensor:
    """mean over triplets of max(d_ap - d_an + margin, 0), on non-squared distances as in the reference."""
    return torch.relu(d_ap - d_an + margin).mean()


def sequence_triplet_loss(
    query_windows: torch.Tensor,
    positive_windows: torch.Tensor,
    negative_windows: torch.Tensor,
    owner: torch.Tensor,
    margin: float = DEFAULT_MARGIN,
    frames: slice | None = None,
) -> torch.Tensor:
    """Triplet loss over windows [*, L, D]: query b with its positive b and each negative t whose owner is b."""
    d_ap = aligned_sequence_distances(query_windows, positive_windows, frames)
    d_an = aligned_sequence_distances(query_windows[owner], negative_windows, frames)
    return triplet_hinge(d_ap[owner], d_an, margin)
