"""Small stand-ins for JIST tests: a tiny backbone, a learnable mean pool, random images."""

import torch
from torch import nn

from seqvpr.models.jist import JistConfig, JistModel, build_jist


class TinyBackbone(nn.Module):
    """A small two-stage convolution net with BatchNorm standing in for a real backbone."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv1 = nn.Conv2d(3, 6, 3, stride=2)
        self.bn1 = nn.BatchNorm2d(6)
        self.conv2 = nn.Conv2d(6, 8, 3, stride=2)
        self.bn2 = nn.BatchNorm2d(8)
        self.out_channels = 8

    def features(self, x):
        return torch.relu(self.bn2(self.conv2(torch.relu(self.bn1(self.conv1(x))))))


class MeanPool(nn.Module):
    """Stand-in sequence pool: a learnable softmax-weighted mean over L (uniform at init), then L2."""

    def __init__(self, length: int = 3) -> None:
        super().__init__()
        self.logits = nn.Parameter(torch.zeros(length))

    def forward(self, x):
        weights = self.logits[: x.shape[1]].softmax(0)
        return nn.functional.normalize((x * weights[None, :, None]).sum(1), dim=-1)


def tiny_model(stages=("conv2", "bn2"), out_dim=16, length=3) -> tuple[JistModel, JistConfig]:
    config = JistConfig(out_dim=out_dim, trainable_stages=stages, seq_length=length)
    return build_jist(config, MeanPool(length), backbone=TinyBackbone()), config


def random_images(*shape, seed=0):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed))
