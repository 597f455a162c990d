"""Images -> descriptors with a backbone and a pooling head: batched, with progress, cached and resumable.

The cache key covers the extractor configuration, the weights file (path, size, mtime) and the image list (path,
size, mtime of every image), so a changed model or image set never reuses a stale cache. Rows are written to a
partial file as batches finish; an interrupted run continues from the last written batch.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import nn

from seqvpr.errors import SeqvprError
from seqvpr.features import backbones
from seqvpr.features.pooling import GeM
from seqvpr.io import atomic_write

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
BACKBONES = ("efficientnet-lite0", "resnet18", "resnet50")


@dataclass(frozen=True)
class ExtractorConfig:
    """Backbone, its weights ('imagenet' or a checkpoint path), pooling, input size (width, height), batch size."""

    backbone: str = "efficientnet-lite0"
    weights: str | None = "imagenet"
    pooling: str = "gem"
    width: int = 320
    height: int = 240
    batch_size: int = 32

    def __post_init__(self) -> None:
        if self.backbone not in BACKBONES:
            raise SeqvprError(f"backbone {self.backbone!r} is not known (choose from: {', '.join(BACKBONES)})")
        if self.pooling != "gem":
            raise SeqvprError(f"pooling {self.pooling!r} is not known (choose from: gem)")
        if min(self.width, self.height, self.batch_size) < 1:
            raise SeqvprError("image size and batch size must be positive")


class Extractor(nn.Module):
    """Backbone feature map -> pooled, L2-normalised descriptor; ``mean``/``std`` normalise [0, 1] pixels."""

    def __init__(self, backbone: nn.Module, pooling: nn.Module, mean: Sequence[float], std: Sequence[float]) -> None:
        super().__init__()
        self.backbone, self.pooling = backbone, pooling
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.pooling(self.backbone.features((images - self.mean) / self.std))


def build_extractor(config: ExtractorConfig) -> Extractor:
    """The extractor a configuration describes, in eval mode."""
    if config.backbone == "efficientnet-lite0":
        net = backbones.efficientnet_lite0(config.weights)
        return Extractor(net, GeM(), backbones.LITE_MEAN, backbones.LITE_STD).eval()
    net = backbones.resnet(int(config.backbone.removeprefix("resnet")), config.weights)
    return Extractor(net, GeM(), IMAGENET_MEAN, IMAGENET_STD).eval()


def load_image(path: Path, width: int, height: int) -> torch.Tensor:
    """An RGB image resized to width x height as a [3, H, W] float tensor in [0, 1]; one-line error if unreadable."""
    try:
        with Image.open(path) as image:
            rgb = image.convert("RGB").resize((width, height), Image.BILINEAR)
    except FileNotFoundError:
        raise SeqvprError(f"{path}: no such image") from None
    except (UnidentifiedImageError, OSError, ValueError) as error:
        raise SeqvprError(f"{path}: not a readable image ({type(error).__name__})") from None
    return torch.from_numpy(np.asarray(rgb, dtype=np.float32) / 255.0).permute(2, 0, 1)


@dataclass(frozen=True)
class Extraction:
    """Descriptors of the readable images, which input rows they are, and the images skipped as unreadable."""

    descriptors: np.ndarray
    rows: np.ndarray
    skipped: tuple[Path, ...]
    cache_file: Path | None


def cache_key(config: ExtractorConfig, paths: Sequence[Path]) -> str:
    """A digest of the configuration, the weights file and every image's path, size and mtime."""
    settings = {k: v for k, v in asdict(config).items() if k != "batch_size"}  # batching does not change rows
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode())
    for path in _weights_files(config) + list(paths):
        stat = os.stat(path) if os.path.exists(path) else None
        digest.update(f"{Path(path).resolve()}|{stat.st_size if stat else -1}|{stat.st_mtime_ns if stat else -1}\n".encode())
    return digest.hexdigest()[:24]


def _weights_files(config: ExtractorConfig) -> list[Path]:
    """The weights file a configuration reads (none for random weights or ResNet without a checkpoint)."""
    if config.weights is None or (config.weights == "imagenet" and config.backbone != "efficientnet-lite0"):
        return []
    return [backbones.lite0_weights_path() if config.weights == "imagenet" else Path(config.weights)]


def extract_descriptors(
    paths: Sequence[Path],
    config: ExtractorConfig = ExtractorConfig(),
    *,
    device: str = "cpu",
    cache_dir: str | Path | None = None,
    skip_bad: bool = False,
    progress: Callable[[int], None] | None = None,
    extractor: Extractor | None = None,
) -> Extraction:
    """Descriptors [N, D] of the images, in batches; reused from ``cache_dir`` when nothing changed.

    ``extractor`` (optional) replaces the model built from ``config``; it must be what ``config`` describes, since
    the cache key is computed from ``config``.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise SeqvprError("no images to extract descriptors from")
    key = cache_key(config, paths) if cache_dir is not None else None
    final = Path(cache_dir) / f"{key}.npz" if key else None
    if final is not None and final.is_file():
        with np.load(final, allow_pickle=False) as cached:
            if progress:
                progress(len(paths))
            skipped = tuple(paths[i] for i in cached["skipped"])
            return Extraction(cached["descriptors"], cached["rows"], skipped, final)
    model = (extractor or build_extractor(config)).to(device)
    part = _Partial(Path(cache_dir) / f"{key}.part" if key else None)
    rows_out: list[np.ndarray] = part.rows
    kept: list[int] = part.kept
    skipped: list[int] = part.skipped
    if progress and part.done:
        progress(part.done)
    with torch.no_grad():
        for begin in range(part.done, len(paths), config.batch_size):
            end = min(begin + config.batch_size, len(paths))
            batch_rows, batch_skipped, images = [], [], []
            for index in range(begin, end):
                try:
                    images.append(load_image(paths[index], config.width, config.height))
                    batch_rows.append(index)
                except SeqvprError:
                    if not skip_bad:
                        raise
                    batch_skipped.append(index)
            out = model(torch.stack(images).to(device)).cpu().numpy().astype(np.float32) if images else None
            if out is not None:
                rows_out.append(out)
            kept.extend(batch_rows)
            skipped.extend(batch_skipped)
            part.save_batch(begin, end, out, batch_rows, batch_skipped)
            if progress:
                progress(end - begin)
    if not kept:
        raise SeqvprError(f"none of the {len(paths)} images could be read (first: {paths[skipped[0]]})")
    result = Extraction(np.concatenate(rows_out), np.asarray(kept, np.int64), tuple(paths[i] for i in skipped), final)
    if final is not None:
        with atomic_write(final, "wb") as handle:
            np.savez(handle, descriptors=result.descriptors, rows=result.rows, skipped=np.asarray(skipped, np.int64))
        part.remove()
    return result


class _Partial:
    """Batches written so far by an interrupted extraction: one small .npz per finished batch in ``<key>.part/``."""

    def __init__(self, folder: Path | None) -> None:
        self.folder = folder
        self.done, self.rows, self.kept, self.skipped = 0, [], [], []
        if folder is None or not folder.is_dir():
            return
        for file in sorted(folder.glob("batch_*.npz")):
            with np.load(file, allow_pickle=False) as saved:
                if int(saved["begin"]) != self.done:
                    break  # only a contiguous run of batches from the start is reused
                if len(saved["kept"]):
                    self.rows.append(saved["descriptors"])
                self.kept.extend(int(i) for i in saved["kept"])
                self.skipped.extend(int(i) for i in saved["skipped"])
                self.done = int(saved["end"])

    def save_batch(self, begin: int, end: int, descriptors: np.ndarray | None, kept: list[int], skipped: list[int]) -> None:
        if self.folder is None:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        with atomic_write(self.folder / f"batch_{begin:09d}.npz", "wb") as handle:
            np.savez(handle, begin=begin, end=end,
                     descriptors=descriptors if descriptors is not None else np.zeros((0, 0), np.float32),
                     kept=np.asarray(kept, np.int64), skipped=np.asarray(skipped, np.int64))

    def remove(self) -> None:
        if self.folder is not None and self.folder.is_dir():
            shutil.rmtree(self.folder, ignore_errors=True)
