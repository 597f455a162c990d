"""Options and value parsers the command families share. Nothing here imports torch: ``--help`` and option errors
stay fast."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from seqvpr.errors import SeqvprError

#: how images become descriptors: patch-normalised thumbnails or one of the backbones
BACKBONES = ("efficientnet-lite0", "resnet18", "resnet50")
DESCRIPTORS = ("patchnorm", *BACKBONES)
POOLINGS = ("gem", "netvlad")


def with_options(options: list[Callable]) -> Callable[[Callable], Callable]:
    """A decorator adding click ``options`` to a command, in the order ``--help`` shows them."""

    def decorate(function: Callable) -> Callable:
        for option in reversed(options):
            function = option(function)
        return function

    return decorate


def parse_ks(text: str) -> tuple[int, ...]:
    """``1,5,10,20`` -> (1, 5, 10, 20)."""
    message = f"--k {text!r}: expected comma-separated positive integers, e.g. 1,5,10,20"
    try:
        ks = tuple(sorted({int(x) for x in text.split(",") if x.strip()}))
    except ValueError:
        raise SeqvprError(message) from None
    if not ks or ks[0] < 1:
        raise SeqvprError(message)
    return ks


def parse_velocities(text: str) -> tuple[float, ...]:
    """``1`` or ``0.8,1,1.2`` or ``0.8:1.2:0.1`` (min:max:step) -> velocities."""
    try:
        if ":" in text:
            lo, hi, step = (float(x) for x in text.split(":"))
            if step <= 0 or hi < lo:
                raise ValueError
            import numpy as np

            return tuple(float(v) for v in np.round(np.arange(lo, hi + step / 2, step), 6))
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise SeqvprError(f"--velocities {text!r}: expected V, V1,V2,... or MIN:MAX:STEP") from None


def parse_size(text: str | None) -> int | None:
    """``512M``, ``2G`` or plain bytes -> bytes; ``none`` -> no budget."""
    if text is None or text.lower() == "none":
        return None
    units = {"k": 1024, "m": 1024**2, "g": 1024**3}
    try:
        scale = units.get(text[-1].lower(), 1)
        return int(float(text[:-1] if text[-1].lower() in units else text) * scale)
    except (ValueError, IndexError):
        raise SeqvprError(f"--memory-budget {text!r}: expected bytes such as 512M or 2G") from None


def parse_thumbnail(text: str, option: str = "--thumbnail") -> tuple[int, int]:
    """``WIDTHxHEIGHT`` -> (width, height), both positive."""
    try:
        width, height = (int(x) for x in text.lower().split("x"))
        if width < 1 or height < 1:
            raise ValueError
        return width, height
    except ValueError:
        raise SeqvprError(f"{option} {text!r}: expected WIDTHxHEIGHT, e.g. 64x32") from None


def parse_stages(text: str | None) -> tuple[str, ...] | None:
    """``stage7,head`` -> ('stage7', 'head'); nothing -> None (the backbone's default)."""
    stages = tuple(s.strip() for s in (text or "").split(",") if s.strip())
    return stages or None


extraction_options = with_options([
    click.option("--descriptor", type=click.Choice(list(DESCRIPTORS)), default="patchnorm", show_default=True,
                 help="How images become descriptors (descriptor files are used as they are)."),
    click.option("--thumbnail", default="64x32", show_default=True, help="patchnorm: grayscale thumbnail WIDTHxHEIGHT."),
    click.option("--patch", default=8, show_default=True, type=int, help="patchnorm: patch side in pixels."),
    click.option("--weights", default="imagenet", show_default=True,
                 help="Backbone weights: 'imagenet' (EfficientNet-Lite0's packaged weights) or a checkpoint path."),
    click.option("--pooling", type=click.Choice(list(POOLINGS)), default="gem", show_default=True,
                 help="Backbone pooling: GeM, or NetVLAD with clusters from k-means of local features."),
    click.option("--clusters", default=64, show_default=True, type=int, help="netvlad: number of clusters."),
    click.option("--image-size", default="320x240", show_default=True, help="Backbone input WIDTHxHEIGHT."),
    click.option("--batch-size", "extract_batch", default=32, show_default=True, type=int,
                 help="Images per backbone batch."),
    click.option("--cache-dir", type=click.Path(), help="Cache extracted descriptors here (keyed by model and images)."),
    click.option("--skip-bad", is_flag=True, help="Skip unreadable images (listed on stderr) instead of failing."),
])


def extraction_settings(o: dict[str, Any], device: str = "cpu") -> tuple[str, Any, dict[str, Any]]:
    """The parsed extraction options: descriptor name, patchnorm config, keyword arguments of ``describe``."""
    width, height = parse_thumbnail(o["thumbnail"])
    image_width, image_height = parse_thumbnail(o["image_size"], "--image-size")
    from seqvpr.features.extraction import ExtractorConfig
    from seqvpr.features.patchnorm import PatchNormConfig

    descriptor = o["descriptor"]
    backbone = descriptor if descriptor != "patchnorm" else "efficientnet-lite0"
    config = ExtractorConfig(backbone, o["weights"], o["pooling"], image_width, image_height, o["extract_batch"],
                             o["clusters"])
    return descriptor, PatchNormConfig(width, height, o["patch"]), {
        "extractor": config, "device": device, "cache_dir": o["cache_dir"], "skip_bad": o["skip_bad"],
    }


EXTRACTION_KEYS = ("descriptor", "thumbnail", "patch", "weights", "pooling", "clusters", "image_size", "extract_batch",
                   "cache_dir", "skip_bad")
