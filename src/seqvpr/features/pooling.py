"""Pooling heads that turn a feature map [B, C, H, W] into one descriptor per image."""

from __future__ import annotations

import torch
from torch import nn


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
