"""CosPlace's augmentation of classification images, on batches in [0, 1] and drawn from a seeded generator:
a random resized crop (area share in [``crop_scale``, 1], aspect ratio in [3/4, 4/3], resized back) and colour
jitter (brightness, contrast and saturation factors in [1 - ``jitter``, 1 + ``jitter``], hue turned by up to
``hue`` of a turn), applied in that order. Images of another condition (night, snow) are still the same place, so
the classifier learns what survives a change of light and framing.

The hue turn rotates the chroma plane of YIQ, a linear stand-in for the HSV hue shift torchvision uses (equal at
grey, close elsewhere); everything here is plain tensor algebra, so no image library is needed.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.nn import functional as F

#: RGB -> luma weights (ITU-R BT.601), as grey conversion in torchvision and PIL
LUMA = (0.299, 0.587, 0.114)
_RGB_TO_YIQ = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])


def jitter_factors(rng: np.random.Generator, count: int, strength: float) -> torch.Tensor:
    """Per-image factors [count, 1, 1, 1] uniform in [max(0, 1 - strength), 1 + strength]."""
    factors = rng.uniform(max(0.0, 1.0 - strength), 1.0 + strength, size=count)
    return torch.as_tensor(factors, dtype=torch.float32).view(count, 1, 1, 1)


def gray(images: torch.Tensor) -> torch.Tensor:
    """Luma [B, 1, H, W] of RGB images [B, 3, H, W]."""
    weights = torch.tensor(LUMA, dtype=images.dtype, device=images.device).view(1, 3, 1, 1)
    return (images * weights).sum(1, keepdim=True)


def blend(images: torch.Tensor, other: torch.Tensor, factors: torch.Tensor) -> torch.Tensor:
    """``factors * images + (1 - factors) * other``, clamped to [0, 1] (torchvision's adjust_* formula)."""
    factors = factors.to(images.device, images.dtype)
    return (factors * images + (1.0 - factors) * other).clamp(0.0, 1.0)


def turn_hue(images: torch.Tensor, turns: torch.Tensor) -> torch.Tensor:
    """Images with their chroma rotated by ``turns`` [B] of a full turn (YIQ rotation), clamped to [0, 1]."""
    matrix = _RGB_TO_YIQ.to(images.device, images.dtype)
    yiq = torch.einsum("ij,bjhw->bihw", matrix, images)
    angle = 2.0 * math.pi * turns.to(images.device, images.dtype)
    cos, sin = torch.cos(angle).view(-1, 1, 1), torch.sin(angle).view(-1, 1, 1)
    i, q = yiq[:, 1], yiq[:, 2]
    turned = torch.stack([yiq[:, 0], cos * i - sin * q, sin * i + cos * q], dim=1)
    return torch.einsum("ij,bjhw->bihw", torch.linalg.inv(matrix), turned).clamp(0.0, 1.0)


def color_jitter(images: torch.Tensor, rng: np.random.Generator, jitter: float, hue: float) -> torch.Tensor:
    """Brightness, contrast, saturation and hue changed per image, in that order (no change at 0 and 0)."""
    count = len(images)
    if jitter > 0:
        images = (images * jitter_factors(rng, count, jitter).to(images.device, images.dtype)).clamp(0.0, 1.0)
        mean_gray = gray(images).mean(dim=(1, 2, 3), keepdim=True)
        images = blend(images, mean_gray, jitter_factors(rng, count, jitter))
        images = blend(images, gray(images), jitter_factors(rng, count, jitter))
    if hue > 0:
        images = turn_hue(images, torch.as_tensor(rng.uniform(-hue, hue, size=count), dtype=torch.float32))
    return images


def crop_boxes(rng: np.random.Generator, count: int, height: int, width: int, scale: float) -> np.ndarray:
    """Per image a crop (top, left, height, width) [count, 4] keeping an area share in [scale, 1] at an aspect
    ratio in [3/4, 4/3] of the image's (clipped to the image)."""
    area = rng.uniform(scale, 1.0, size=count)
    ratio = np.exp(rng.uniform(math.log(3 / 4), math.log(4 / 3), size=count))
    crop_h = np.clip(np.round(height * np.sqrt(area / ratio)), 1, height).astype(np.int64)
    crop_w = np.clip(np.round(width * np.sqrt(area * ratio)), 1, width).astype(np.int64)
    top = np.floor(rng.uniform(0.0, 1.0, size=count) * (height - crop_h + 1)).astype(np.int64)
    left = np.floor(rng.uniform(0.0, 1.0, size=count) * (width - crop_w + 1)).astype(np.int64)
    return np.stack([top, left, crop_h, crop_w], axis=1)


def random_resized_crop(images: torch.Tensor, rng: np.random.Generator, scale: float) -> torch.Tensor:
    """Each image cropped (``crop_boxes``) and resized back to [H, W] bilinearly; unchanged when ``scale`` is 1."""
    if scale >= 1.0:
        return images
    height, width = images.shape[-2:]
    boxes = crop_boxes(rng, len(images), height, width, scale)
    return torch.cat([
        F.interpolate(image[None, :, top : top + h, left : left + w], size=(height, width), mode="bilinear",
                      align_corners=False)
        for image, (top, left, h, w) in zip(images, boxes.tolist())
    ])


def augment_images(
    images: torch.Tensor, rng: np.random.Generator, jitter: float, hue: float, crop_scale: float
) -> torch.Tensor:
    """A random resized crop, then colour jitter, of a batch [B, 3, H, W] in [0, 1] (CosPlace's training views)."""
    return color_jitter(random_resized_crop(images, rng, crop_scale), rng, jitter, hue)
