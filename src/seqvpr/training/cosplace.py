"""CosPlace-style single-image classification, the image branch of JIST's joint training.

Places are split into classes: UTM cells of ``cell_m`` metres crossed with heading sectors of ``heading_deg``
degrees. Classes are spread over ``groups_n * groups_n * groups_l`` groups by taking the cell and sector indices
modulo (N, N, L), so two classes of one group are never neighbouring cells with the same sector, nor neighbouring
sectors of one cell: no visually overlapping classes compete inside one classifier. Each group gets its own
large-margin cosine (CosFace) classifier over the shared image descriptor.

Same name as ``seqvpr.models.cosplace``: CosPlace at the training layer (its classes of images), the model there.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from seqvpr.errors import SeqvprError
from seqvpr.training.settings import CellGrouping


def cell_keys(positions: np.ndarray, headings: np.ndarray | None, grouping: CellGrouping) -> np.ndarray:
    """Per image the integer class key (east cell, north cell, heading sector) as an [N, 3] int64 array.

    Cells are ``floor(x / M)``; headings are wrapped into [0, 360) before ``floor(h / alpha)``; without headings
    every image is in sector 0.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 2:
        raise SeqvprError(f"positions must be [N, 2] (east, north) in metres, got shape {positions.shape}")
    if not np.isfinite(positions).all():
        raise SeqvprError("positions must be finite (found NaN or inf)")
    keys = np.zeros((len(positions), 3), dtype=np.int64)
    keys[:, :2] = np.floor_divide(positions, grouping.cell_m)
    if headings is not None:
        headings = np.asarray(headings, dtype=np.float64)
        if headings.shape != (len(positions),):
            raise SeqvprError(f"headings must be [N] with N = {len(positions)} positions, got shape {headings.shape}")
        if not np.isfinite(headings).all():
            raise SeqvprError("headings must be finite (found NaN or inf)")
        wrapped = np.mod(headings, 360.0)
        wrapped = np.where(wrapped >= 360.0, 0.0, wrapped)  # tiny negatives wrap to exactly 360.0
        keys[:, 2] = np.floor_divide(wrapped, grouping.heading_deg)
    return keys


def group_of_keys(keys: np.ndarray, grouping: CellGrouping) -> np.ndarray:
    """The group id in [0, N*N*L) of class keys [K, 3]: ``((e mod N) * N + (n mod N)) * L + (sector mod L)``."""
    n, l = grouping.groups_n, grouping.groups_l
    return (np.mod(keys[:, 0], n) * n + np.mod(keys[:, 1], n)) * l + np.mod(keys[:, 2], l)


def assign_classes(
    positions: np.ndarray, headings: np.ndarray | None, grouping: CellGrouping
) -> tuple[np.ndarray, np.ndarray]:
    """Per image: class id and group id (both int64 [N]); deterministic.

    Class ids are dense 0..C-1 over the classes with at least ``min_images`` images, numbered in the sorted order
    of their (east cell, north cell, sector) keys; images of dropped classes get class -1 and group -1. Unlike
    the reference (dict insertion order) the group id is a fixed function of the key, so it does not depend on
    the order of the images.
    """
    keys = cell_keys(positions, headings, grouping)
    if len(keys) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy()
    unique, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    kept = counts >= grouping.min_images
    dense = np.where(kept, np.cumsum(kept) - 1, -1)
    groups = np.where(kept, group_of_keys(unique, grouping), -1)
    return dense[inverse].astype(np.int64), groups[inverse].astype(np.int64)


def group_members(class_ids: np.ndarray, group_ids: np.ndarray, group: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The images of one group, their labels renumbered 0..C_g-1 (in class id order), and C_g: what one group's
    classifier is trained on."""
    class_ids, group_ids = np.asarray(class_ids), np.asarray(group_ids)
    if class_ids.shape != group_ids.shape or class_ids.ndim != 1:
        raise SeqvprError(f"class and group ids must be two [N] arrays, got {class_ids.shape} and {group_ids.shape}")
    images = np.flatnonzero((group_ids == group) & (class_ids >= 0))
    classes, labels = np.unique(class_ids[images], return_inverse=True)
    return images, labels.reshape(-1).astype(np.int64), len(classes)


class CosFaceHead(nn.Module):
    """Large-margin cosine classifier (CosFace): logits = s * (cos(theta) - m * onehot); weights and features
    L2-normalised. Defaults s=30, m=0.4 (digest section 3.7); weights Xavier-uniform as in CosPlace."""

    def __init__(self, dim: int, n_classes: int, s: float = 30.0, m: float = 0.4) -> None:
        super().__init__()
        if int(dim) != dim or dim < 1 or int(n_classes) != n_classes or n_classes < 1:
            raise SeqvprError(f"CosFace needs a positive dimension and class count, got dim={dim} classes={n_classes}")
        if not (math.isfinite(s) and s > 0 and math.isfinite(m) and m >= 0):
            raise SeqvprError(f"CosFace scale must be > 0 and margin >= 0, got s={s} m={m}")
        self.dim, self.n_classes, self.s, self.m = int(dim), int(n_classes), float(s), float(m)
        self.weight = nn.Parameter(torch.empty(self.n_classes, self.dim))
        nn.init.xavier_uniform_(self.weight)

    def cosine(self, features: torch.Tensor) -> torch.Tensor:
        """cos(theta) [B, C] between the features [B, dim] and every class weight."""
        if features.ndim != 2 or features.shape[1] != self.dim:
            raise SeqvprError(f"CosFace features must be [B, {self.dim}], got shape {tuple(features.shape)}")
        weight = nn.functional.normalize(self.weight, dim=1)
        return nn.functional.normalize(features, dim=1) @ weight.to(features.dtype).T

    def forward(self, features: torch.Tensor, labels: torch.Tensor | None = None) -> torch.Tensor:
        """Logits [B, C]; the margin is subtracted from the true class only, and only when labels are given."""
        cosine = self.cosine(features)
        if labels is None:
            return self.s * cosine
        labels = _check_labels(labels, len(features), self.n_classes)
        onehot = nn.functional.one_hot(labels, self.n_classes).to(cosine.dtype)
        return self.s * (cosine - self.m * onehot)


def _check_labels(labels: torch.Tensor, batch: int, n_classes: int) -> torch.Tensor:
    if labels.shape != (batch,) or labels.dtype not in (torch.int64, torch.int32):
        raise SeqvprError(
            f"labels must be an integer tensor of shape [{batch}], got {tuple(labels.shape)} {labels.dtype}"
        )
    if batch and (int(labels.min()) < 0 or int(labels.max()) >= n_classes):
        raise SeqvprError(f"labels must be in [0, {n_classes}), got values in [{int(labels.min())}, {int(labels.max())}]")
    return labels.long()


def cosface_loss(head: CosFaceHead, features: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Mean cross-entropy of the margin logits."""
    return nn.functional.cross_entropy(head(features, labels), labels.long())
