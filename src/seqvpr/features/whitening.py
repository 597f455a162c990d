"""PCA-whitening fitted on a reference traversal (the papers' NetVLAD + PCA-W setting)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seqvpr.errors import SeqvprError


@dataclass(frozen=True)
class PCAWhitening:
    """x -> normalize(diag(1/sqrt(lambda + eps)) U^T (x - mean)), keeping the top ``dim`` components."""

    mean: np.ndarray
    components: np.ndarray  # [dim, D]
    scale: np.ndarray  # [dim]

    def apply(self, descriptors: np.ndarray) -> np.ndarray:
        if descriptors.shape[1] != self.components.shape[1]:
            raise SeqvprError(
                f"PCA-whitening was fitted on {self.components.shape[1]}-D descriptors, got {descriptors.shape[1]}-D"
            )
        out = ((descriptors - self.mean) @ self.components.T) * self.scale
        return (out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def fit_pca_whitening(descriptors: np.ndarray, dim: int, eps: float = 1e-9) -> PCAWhitening:
    """Principal directions of the (reference) descriptors via SVD; ``dim`` may not exceed min(N - 1, D)."""
    x = np.asarray(descriptors, dtype=np.float64)
    limit = min(len(x) - 1, x.shape[1])
    if not 1 <= dim <= limit:
        raise SeqvprError(f"PCA-whitening to {dim} dimensions needs 1 <= dim <= {limit} (frames - 1 and descriptor size)")
    mean = x.mean(0)
    _, singular, vt = np.linalg.svd(x - mean, full_matrices=False)
    variance = singular[:dim] ** 2 / (len(x) - 1)
    return PCAWhitening(mean, vt[:dim], 1.0 / np.sqrt(variance + eps))
