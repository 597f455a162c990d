"""Camera frames to map frames: one image (a path, a PIL image or an H x W x 3 uint8 array) described exactly as
the map's frames were (its descriptor or image model), with the model built once. The localiser applies the map's
SeqMatchNet transform after, to described and given descriptors alike."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from seqvpr.errors import SeqvprError
from seqvpr.data.images import read_image, to_8bit
from seqvpr.maps.build import FrameDescription
from seqvpr.methods import image_model
from seqvpr.models.registry import TrainedModel

Frame = str | Path | Image.Image | np.ndarray


def rgb_image(frame: Frame) -> Image.Image:
    """An RGB PIL image from a path, a PIL image or an H x W x 3 (or H x W) uint8 array; one line if it is none."""
    if isinstance(frame, (str, Path)):
        return read_image(frame, "RGB")
    if isinstance(frame, Image.Image):
        if 0 in frame.size:
            raise SeqvprError(f"a camera frame has no pixels (size {frame.size})")
        return to_8bit(frame, "RGB")
    array = np.asarray(frame)
    if array.dtype != np.uint8 or array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3):
        raise SeqvprError(f"a camera frame must be an H x W x 3 uint8 array, got {array.dtype} {array.shape}")
    if 0 in array.shape[:2]:
        raise SeqvprError(f"a camera frame has no pixels (shape {array.shape})")
    return Image.fromarray(array).convert("RGB")


class ImageDescriber:
    """Describes single images as the map's frames: ``encode(frame) -> [D]`` float32 on the CPU (before any
    transform or normalisation); the network run by ``engine`` (``features.engines``)."""

    def __init__(self, description: FrameDescription, models: Mapping[str, TrainedModel], device: str = "cpu",
                 engine: str = "auto"):
        self.description, self.device = description, device
        self.model = image_model(models)
        if self.model is not None:
            self.size = description.image_size or self.model.image_size
            module = self.model.module
            self.network = getattr(module, "encoder", module)
        elif description.descriptor == "patchnorm":
            self.size, self.network = None, None
        else:
            from seqvpr.features.extraction import build_encoder
            from seqvpr.features.describe import descriptor_config

            config = descriptor_config(description.descriptor, description.extractor)
            self.size, self.network = (config.width, config.height), build_encoder(config).to(device)
        if self.network is not None:
            from seqvpr.features.engines import with_engine

            self.network = with_engine(self.network.eval(), *self.size, engine, device)

    @torch.no_grad()
    def encode(self, frame: Frame) -> torch.Tensor:
        image = rgb_image(frame)
        if self.network is None:
            from seqvpr.features.patchnorm import patch_normalize

            config = self.description.patchnorm
            gray = np.asarray(image.convert("L").resize((config.width, config.height), Image.Resampling.BILINEAR),
                              dtype=np.float64)
            vector = torch.from_numpy(patch_normalize(gray, config.patch, config.eps).astype(np.float32))
        else:
            pixels = np.asarray(image.resize(self.size, Image.BILINEAR), dtype=np.float32) / 255.0
            batch = torch.from_numpy(pixels).permute(2, 0, 1)[None].to(self.device)
            vector = self.network(batch)[0].float().cpu()
        return vector

