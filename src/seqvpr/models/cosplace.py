"""CosPlace: a single-image frame encoder (ResNet -> channel L2 -> GeM -> Linear -> L2), the ``FrameEncoder`` JIST
starts from. A CosPlace model folder describes the frames of image traversals; any frame-level or pooling method
then runs on those descriptors (single-image retrieval by default).

Upstream's layout (gmberton/CosPlace): ``backbone = Sequential(*resnet.children()[:-2])``, so ``backbone.0`` is
conv1, ``backbone.1`` bn1 and ``backbone.4..7`` layer1..layer4; ``aggregation = Sequential(L2Norm, GeM, Flatten,
Linear, L2Norm)``, so ``aggregation.1.p`` is GeM's p and ``aggregation.3.*`` the Linear layer. ``seqvpr_name`` and
``upstream_key`` translate between those keys and the ``FrameEncoder``'s names (JIST's files hold the same keys
under ``model.``).

Same name as ``seqvpr.training.cosplace``: CosPlace at the model layer, its training classes there.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from seqvpr.errors import SeqvprError
from seqvpr.features import backbones
from seqvpr.models import files
from seqvpr.models.jist import FrameEncoder

FORMAT = "seqvpr-cosplace"
#: upstream tests at full resolution; seqvpr reads CosPlace's images at 512 x 384 (W x H) unless told otherwise
DEFAULT_IMAGE_SIZE = (512, 384)
#: the ResNet a CosPlace head's input size implies
BACKBONE_OF_CHANNELS = {512: "resnet18", 2048: "resnet50"}
HEAD_NAMES = {"aggregation.1.p": "gem.p", "aggregation.3.weight": "fc.weight", "aggregation.3.bias": "fc.bias"}
#: seqvpr's input normalisation (ImageNet mean/std), buffers a CosPlace file does not hold
INPUT_BUFFERS = ("mean", "std")


def seqvpr_name(key: str) -> str | None:
    """The ``FrameEncoder`` name of an upstream CosPlace key (no prefix), or None when the key is not CosPlace's."""
    if key in HEAD_NAMES:
        return HEAD_NAMES[key]
    child, _, rest = key.removeprefix("backbone.").partition(".")
    if key.startswith("backbone.") and child in backbones.COSPLACE_CHILDREN and rest:
        return f"backbone.{backbones.COSPLACE_CHILDREN[child]}.{rest}"
    return None


def upstream_key(name: str) -> str:
    """The upstream CosPlace key of a ``FrameEncoder`` name (to name a missing key as the file would)."""
    inverse = {v: k for k, v in HEAD_NAMES.items()}
    if name in inverse:
        return inverse[name]
    child, _, rest = name.removeprefix("backbone.").partition(".")
    index = {v: k for k, v in backbones.COSPLACE_CHILDREN.items()}.get(child, child)
    return f"backbone.{index}.{rest}"


def build_cosplace(backbone: str = "resnet18", out_dim: int = 512) -> FrameEncoder:
    """A CosPlace frame encoder (random weights, eval mode) on ResNet-18 or ResNet-50, ImageNet normalisation."""
    if backbone not in BACKBONE_OF_CHANNELS.values():
        known = ", ".join(BACKBONE_OF_CHANNELS.values())
        raise SeqvprError(f"CosPlace backbone must be one of {known}, got {backbone!r}")
    return FrameEncoder(backbones.resnet(int(backbone.removeprefix("resnet")), None), out_dim).eval()


def save_cosplace(folder: str | Path, encoder: FrameEncoder, backbone: str, metadata: dict[str, Any]) -> Path:
    """``model.safetensors`` and ``config.json`` (format, backbone and out_dim, then ``metadata``: image size,
    source file...), each written atomically."""
    config = {"backbone": backbone, "out_dim": encoder.out_dim}
    return files.save_model_folder(folder, encoder, {"format": FORMAT, "config": config, **metadata})


def load_cosplace(folder: str | Path) -> tuple[FrameEncoder, dict[str, Any]]:
    """The CosPlace encoder saved by ``save_cosplace`` (eval mode) and its ``config.json``."""
    meta = files.read_model_config(folder, FORMAT, "CosPlace")
    try:
        encoder = build_cosplace(str(meta["config"]["backbone"]), int(meta["config"]["out_dim"]))
    except (KeyError, TypeError, ValueError) as error:
        raise SeqvprError(f"{Path(folder) / files.CONFIG_FILE}: CosPlace config lacks a valid {error}") from None
    return files.load_weights_into(encoder, folder), meta


def cosplace_image_size(meta: dict[str, Any]) -> tuple[int, int]:
    """The (width, height) a saved CosPlace model reads its images at (``DEFAULT_IMAGE_SIZE`` when not recorded)."""
    width, height = meta.get("image_size") or DEFAULT_IMAGE_SIZE
    return int(width), int(height)
