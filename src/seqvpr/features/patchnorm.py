"""SeqSLAM-style weight-free descriptor: a small grayscale thumbnail, normalised patch by patch.

Each ``patch x patch`` block of the resized grayscale image is shifted to mean 0 and scaled to std 1
(``(x - mean) / (std + eps)``), which removes local brightness and contrast; the blocks are concatenated and the
vector is L2-normalised.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from seqvpr.errors import SeqvprError
from seqvpr.data.images import read_image


@dataclass(frozen=True)
class PatchNormConfig:
    """Thumbnail size (width, height) in pixels, patch side in pixels, and the std guard."""

    width: int = 64
    height: int = 32
    patch: int = 8
    eps: float = 1e-6

    def __post_init__(self) -> None:
        if self.width % self.patch or self.height % self.patch:
            raise SeqvprError(
                f"thumbnail {self.width}x{self.height} is not a whole number of {self.patch}-pixel patches"
            )

    @property
    def dim(self) -> int:
        return self.width * self.height


def patch_normalize(gray: np.ndarray, patch: int, eps: float = 1e-6) -> np.ndarray:
    """Patch-normalised, L2-normalised vector of a [H, W] grayscale array (H and W multiples of ``patch``)."""
    h, w = gray.shape
    blocks = gray.astype(np.float64).reshape(h // patch, patch, w // patch, patch).swapaxes(1, 2)
    blocks = blocks.reshape(-1, patch * patch)
    mean = blocks.mean(axis=1, keepdims=True)
    std = blocks.std(axis=1, keepdims=True)
    vector = ((blocks - mean) / (std + eps)).ravel()
    norm = np.linalg.norm(vector)
    return vector / norm if norm > 0 else vector


def load_gray(path: Path, width: int, height: int) -> np.ndarray:
    """Read an image as grayscale values in [0, 255], resized to width x height when it differs."""
    gray = read_image(path, "L")
    if gray.size != (width, height):
        gray = gray.resize((width, height), Image.Resampling.BILINEAR)
    return np.asarray(gray, dtype=np.float64)


def patchnorm_descriptors(
    paths: Sequence[Path], config: PatchNormConfig = PatchNormConfig(), progress: Callable[[int], None] | None = None
) -> np.ndarray:
    """Descriptors [N, width*height] (float32) of image files, in order."""
    return patchnorm_extraction(paths, config, progress)[0]


def patchnorm_extraction(
    paths: Sequence[Path], config: PatchNormConfig = PatchNormConfig(), progress: Callable[[int], None] | None = None,
    skip_bad: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors of the readable images and their rows; with ``skip_bad`` an unreadable one is left out, else it
    is a one-line error naming it."""
    out = np.empty((len(paths), config.dim), dtype=np.float32)
    kept = []
    for row, path in enumerate(paths):
        try:
            out[len(kept)] = patch_normalize(load_gray(Path(path), config.width, config.height), config.patch, config.eps)
            kept.append(row)
        except SeqvprError:
            if not skip_bad:
                raise
        if progress is not None:
            progress(1)
    return out[: len(kept)], np.asarray(kept, dtype=np.int64)
