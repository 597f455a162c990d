"""Pooling heads that turn a feature map [B, C, H, W] into one descriptor per image."""

from __future__ import annotations

import torch
from torch import nn

from seqvpr.errors import SeqvprError


class GeM(nn.Module):
    """Generalised mean pooling, (mean_hw clamp(x, eps)^p)^(1/p), with a learnable p (init 3), then L2 norm."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6, normalize: bool = True) -> None:
        super().__init__()
        self.p = nn.Parameter(torch.tensor(float(p)))
        self.eps = eps
        self.normalize = normalize

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        pooled = features.clamp(min=self.eps).pow(self.p).mean((-2, -1)).pow(1.0 / self.p)
        return nn.functional.normalize(pooled, dim=-1) if self.normalize else pooled


class NetVLAD(nn.Module):
    """NetVLAD: soft-assignment of local features to K clusters, summed residuals, intra- and L2-normalised.

    ``a_k(x) = softmax_k(w_k . x + b_k)`` and ``V_k = sum_hw a_k(x) (x - c_k)``; local features are L2-normalised
    first. ``init_from_features`` sets the centroids by k-means and ``w_k = 2 alpha c_k``, ``b_k = -alpha |c_k|^2``
    as the NetVLAD paper does.
    """

    def __init__(self, clusters: int, dim: int, alpha: float = 100.0) -> None:
        super().__init__()
        self.clusters, self.dim, self.alpha = clusters, dim, alpha
        self.assign = nn.Conv2d(dim, clusters, 1, bias=True)
        self.centroids = nn.Parameter(torch.rand(clusters, dim))

    @property
    def out_dim(self) -> int:
        return self.clusters * self.dim

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = nn.functional.normalize(features, dim=1)
        soft = self.assign(x).flatten(2).softmax(1)  # [B, K, HW]
        flat = x.flatten(2)  # [B, C, HW]
        vlad = torch.einsum("bkn,bcn->bkc", soft, flat) - soft.sum(2).unsqueeze(2) * self.centroids[None]
        vlad = nn.functional.normalize(vlad, dim=2)
        return nn.functional.normalize(vlad.flatten(1), dim=1)

    def init_from_features(self, local: torch.Tensor, seed: int = 0) -> None:
        """Centroids = k-means (k-means++ seeded) of L2-normalised local features [N, C]; alpha from their spread."""
        from scipy.cluster.vq import kmeans2

        data = nn.functional.normalize(local.double(), dim=1).numpy()
        if len(data) < self.clusters:
            raise SeqvprError(f"NetVLAD needs at least {self.clusters} local features to initialise, got {len(data)}")
        centroids, _ = kmeans2(data, self.clusters, iter=20, minit="++", seed=seed)
        centroids = nn.functional.normalize(torch.from_numpy(centroids), dim=1)
        dots = torch.sort(torch.from_numpy(data) @ centroids.T, dim=1, descending=True).values
        gap = (dots[:, 0] - dots[:, 1]).mean().clamp(min=1e-6)
        self.alpha = float(-torch.log(torch.tensor(0.01)) / gap)
        with torch.no_grad():
            self.centroids.copy_(centroids.float())
            self.assign.weight.copy_((2.0 * self.alpha * centroids).float()[:, :, None, None])
            self.assign.bias.copy_((-self.alpha * centroids.norm(dim=1) ** 2).float())
