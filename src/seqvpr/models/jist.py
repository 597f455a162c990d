"""JIST: a CosPlace frame encoder whose per-frame descriptors a sequence pooling module (SeqGeM) turns into one
descriptor per window, trained jointly on sequence triplets and CosPlace single-image classification.

Frame descriptor (CosPlace, digest section 3.3): backbone map -> channel-wise L2 -> GeM (learnable p, init 3) ->
Linear(C -> out_dim) -> L2. Only the chosen backbone stages (``layer4`` by default) and the head are trained; the
other stages are frozen for real: ``requires_grad`` off and their BatchNorm layers kept in eval mode, so their
running statistics do not drift as the reference's do (digest section 5, item 14).

Same name as ``seqvpr.training.jist``: JIST's model; its learner there.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from torch import nn

from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.models.configs import DEFAULT_STAGES, JIST_BACKBONES, JistConfig  # noqa: F401 (re-exported)
from seqvpr.features import backbones
from seqvpr.features.extraction import IMAGENET_MEAN, IMAGENET_STD, load_image
from seqvpr.features.pooling import GeM
from seqvpr.models.files import CONFIG_FILE, load_weights_into, read_model_config, save_model_folder

FORMAT = "seqvpr-jist"


def backbone_stages(backbone: nn.Module) -> dict[str, list[nn.Module]]:
    """The named stages of a backbone, in forward order, each as the modules it owns."""
    if isinstance(backbone, backbones.ResNet):
        stages = {"stem": [backbone.conv1, backbone.bn1]}
        stages.update({f"layer{i}": [getattr(backbone, f"layer{i}")] for i in range(1, 5)})
        return stages
    if isinstance(backbone, backbones.EfficientNetLite):
        stages = {"stem": [backbone._conv_stem, backbone._bn0]}
        begin = 0
        for number, spec in enumerate(backbones.LITE0_STAGES, start=1):
            stages[f"stage{number}"] = list(backbone._blocks[begin : begin + spec.repeats])
            begin += spec.repeats
        stages["head"] = [backbone._conv_head, backbone._bn1]
        return stages
    return {name: [child] for name, child in backbone.named_children()}


class FrameEncoder(nn.Module):
    """Backbone -> GeM -> linear to out_dim -> L2: the CosPlace frame descriptor JIST starts from.

    Takes images in [0, 1] ([B, 3, H, W]) and normalises them with ``mean``/``std`` as the Extractor does. The
    backbone needs ``features(images)`` (its last map) and ``out_channels``.
    """

    def __init__(
        self,
        backbone: nn.Module,
        out_dim: int = 512,
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
    ) -> None:
        super().__init__()
        channels = getattr(backbone, "out_channels", None)
        if not callable(getattr(backbone, "features", None)) or not isinstance(channels, int):
            raise SeqvprError("a JIST backbone needs a features(images) method and an integer out_channels")
        self.backbone = backbone
        self.gem = GeM(normalize=False)
        self.fc = nn.Linear(channels, int(out_dim))
        self.out_dim = int(out_dim)
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))
        self.trainable_stages: tuple[str, ...] = tuple(backbone_stages(backbone))
        self._frozen_norms: tuple[str, ...] = ()

    def stage_parameters(self, stages: Iterable[str]) -> list[nn.Parameter]:
        """The backbone parameters of the named stages, in stage order; unknown names are a one-line error."""
        known = backbone_stages(self.backbone)
        stages = tuple(stages)
        unknown = [s for s in stages if s not in known]
        if unknown:
            raise SeqvprError(f"unknown backbone stage {unknown[0]!r} (choose from: {', '.join(known)})")
        params: dict[int, nn.Parameter] = {}
        for name in known:
            if name in stages:
                for module in known[name]:
                    params.update((id(p), p) for p in module.parameters())
        return list(params.values())

    def head_parameters(self) -> list[nn.Parameter]:
        """GeM p and the Linear layer: always trained."""
        return [*self.gem.parameters(), *self.fc.parameters()]

    def freeze(self, trainable_stages: Iterable[str]) -> None:
        """Train only the named backbone stages (and the head): every other backbone parameter gets
        ``requires_grad=False`` and every BatchNorm without a trainable parameter stays in eval mode."""
        trainable = {id(p) for p in self.stage_parameters(trainable_stages)}
        for p in self.backbone.parameters():
            p.requires_grad_(id(p) in trainable)
        for p in self.head_parameters():
            p.requires_grad_(True)
        self.trainable_stages = tuple(trainable_stages)
        self._frozen_norms = tuple(
            f"backbone.{name}" if name else "backbone"
            for name, module in self.backbone.named_modules()
            if isinstance(module, nn.modules.batchnorm._BatchNorm)
            and not any(p.requires_grad for p in module.parameters(recurse=False))
        )
        self.train(self.training)

    def train(self, mode: bool = True) -> FrameEncoder:
        super().train(mode)
        if mode and self._frozen_norms:
            modules = dict(self.named_modules())
            for name in self._frozen_norms:
                modules[name].eval()
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Unit-norm frame descriptors [B, out_dim] of images [B, 3, H, W] in [0, 1]."""
        _check_images(images)
        normalized = (images - self.mean.to(images.dtype)) / self.std.to(images.dtype)
        local = nn.functional.normalize(self.backbone.features(normalized), dim=1)
        return nn.functional.normalize(self.fc(self.gem(local)), dim=-1)


def _check_images(images: torch.Tensor) -> None:
    if images.ndim != 4 or images.shape[1] != 3 or images.shape[0] < 1:
        raise SeqvprError(f"images must be [B, 3, H, W] with B >= 1, got shape {tuple(images.shape)}")


def _check_windows(windows: torch.Tensor, name: str = "windows") -> None:
    if windows.ndim != 5 or windows.shape[2] != 3 or windows.shape[0] < 1 or windows.shape[1] < 1:
        raise SeqvprError(f"{name} must be [B, L, 3, H, W] with B, L >= 1, got shape {tuple(windows.shape)}")


class JistModel(nn.Module):
    """Frame encoder + a sequence pooling module (SeqGeM by default, injected) -> one sequence descriptor per
    window. The pool maps frame descriptors [B, L, D] to [B, D]."""

    def __init__(self, encoder: FrameEncoder, sequence_pool: nn.Module) -> None:
        super().__init__()
        self.encoder = encoder
        self.sequence_pool = sequence_pool

    @property
    def dim(self) -> int:
        return self.encoder.out_dim

    def frames(self, images: torch.Tensor) -> torch.Tensor:
        """Frame descriptors [B, D] of images [B, 3, H, W]."""
        return self.encoder(images)

    def pool(self, frame_descriptors: torch.Tensor) -> torch.Tensor:
        """Sequence descriptors [B, D] of frame descriptors [B, L, D] (frames computed once can be pooled into
        many overlapping windows)."""
        if frame_descriptors.ndim != 3 or frame_descriptors.shape[-1] != self.dim:
            raise SeqvprError(
                f"frame descriptors must be [B, L, {self.dim}], got shape {tuple(frame_descriptors.shape)}"
            )
        return self.sequence_pool(frame_descriptors)

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        """Sequence descriptors [B, D] of windows [B, L, 3, H, W]: all B*L frames in one pass, then pooled over L."""
        _check_windows(windows)
        b, length = windows.shape[:2]
        frames = self.encoder(windows.flatten(0, 1))
        return self.pool(frames.view(b, length, -1))


def _make_backbone(config: JistConfig) -> tuple[nn.Module, tuple[float, ...], tuple[float, ...]]:
    if config.backbone == "efficientnet-lite0":
        return backbones.efficientnet_lite0(config.weights), backbones.LITE_MEAN, backbones.LITE_STD
    if config.backbone == "thumbnail-cnn":  # its patch normalisation removes any input scaling
        return backbones.thumbnail_cnn(config.weights), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    depth = int(config.backbone.removeprefix("resnet"))
    return backbones.resnet(depth, config.weights), IMAGENET_MEAN, IMAGENET_STD


def load_cosplace_head(encoder: FrameEncoder, path: str | Path) -> bool:
    """Fill GeM p and the Linear layer from a CosPlace checkpoint (``aggregation.1.p``, ``aggregation.3.*``) when
    the file has them; returns whether it did. A head of another shape is a one-line error."""
    state = backbones.load_state_dict_file(path)
    if "aggregation.3.weight" not in state:
        return False
    weight, bias = state["aggregation.3.weight"], state.get("aggregation.3.bias")
    if weight.shape != encoder.fc.weight.shape or (bias is not None and bias.shape != encoder.fc.bias.shape):
        raise SeqvprError(
            f"{path}: CosPlace head is {tuple(weight.shape)} (out, in), the model needs "
            f"{tuple(encoder.fc.weight.shape)}: set out_dim to match"
        )
    with torch.no_grad():
        encoder.fc.weight.copy_(weight)
        if bias is not None:
            encoder.fc.bias.copy_(bias)
        if "aggregation.1.p" in state:
            encoder.gem.p.copy_(state["aggregation.1.p"].reshape(()))
    return True


def build_jist(
    config: JistConfig, sequence_pool: nn.Module | None = None, *, backbone: nn.Module | None = None
) -> JistModel:
    """The JIST model a configuration describes, in eval mode, frozen but for ``config.trainable_stages``.

    ``sequence_pool`` defaults to SeqGeM (normalised as ``config.seqgem_normalize`` says); ``backbone`` injects another image
    backbone (ImageNet normalisation; ``config.backbone``/``weights`` are then not used).
    """
    if backbone is None:
        backbone, mean, std = _make_backbone(config)
        encoder = FrameEncoder(backbone, config.out_dim, mean, std)
        if config.weights is not None and config.backbone.startswith("resnet"):
            load_cosplace_head(encoder, config.weights)
    else:
        encoder = FrameEncoder(backbone, config.out_dim)
    encoder.freeze(config.trainable_stages)
    if sequence_pool is None:
        from seqvpr.sequences.descriptors import SeqGeM

        sequence_pool = SeqGeM(normalize=config.seqgem_normalize)
    return JistModel(encoder, sequence_pool).eval()


def trainable_parameters(model: JistModel, config: JistConfig) -> list[nn.Parameter]:
    """What the model's optimiser group updates: the configured backbone stages, the encoder head and the sequence
    pool's parameters (those that require grad)."""
    params: dict[int, nn.Parameter] = {}
    for p in model.encoder.stage_parameters(config.trainable_stages):
        params[id(p)] = p
    for p in model.encoder.head_parameters():
        params[id(p)] = p
    for p in model.sequence_pool.parameters():
        if p.requires_grad:
            params[id(p)] = p
    return list(params.values())


# --- inference: images to frame descriptors ---------------------------------------------------------------------


class ImageStore:
    """Decoded images of one run at one size, as uint8 [3, H, W] CPU tensors, cached in memory when asked."""

    def __init__(self, width: int, height: int, cache: bool = True) -> None:
        self.width, self.height, self.cache = width, height, cache
        self._images: dict[Path, torch.Tensor] = {}

    def get(self, path: Path) -> torch.Tensor:
        """One image as uint8 [3, H, W]."""
        image = self._images.get(path)
        if image is None:
            image = (load_image(Path(path), self.width, self.height) * 255.0).round().to(torch.uint8)
            if self.cache:
                self._images[path] = image
        return image

    def batch(self, paths: Sequence[Path], device: str) -> torch.Tensor:
        """Images [N, 3, H, W] in [0, 1] on ``device``."""
        stacked = torch.stack([self.get(p) for p in paths])
        return stacked.to(device).float().div_(255.0)


@torch.no_grad()
def encode_frames(
    model: nn.Module, store: ImageStore, paths: Sequence[Path], device: str, batch: int = 32
) -> torch.Tensor:
    """Frame descriptors [N, D] of the images (eval mode, no grad), each image encoded once, by a frame encoder
    (images [B, 3, H, W] in [0, 1] -> [B, D]: CosPlace's) or a JIST model's encoder."""
    encoder = model.encoder if isinstance(model, JistModel) else model
    was_training = encoder.training
    encoder.eval()
    try:
        parts = [encoder(store.batch(paths[i : i + batch], device)) for i in range(0, len(paths), batch)]
    finally:
        encoder.train(was_training)
    return torch.cat(parts).float()


def check_images_exist(traversal: Traversal, what: str) -> None:
    """Fail with one line when the traversal has no images or one of them is missing."""
    if traversal.image_paths is None:
        raise SeqvprError(f"{what}: the model describes images, this traversal has descriptors only")
    for path in traversal.image_paths:
        if not Path(path).is_file():
            raise SeqvprError(f"{what}: image {path} does not exist")


def describe_images(
    model: nn.Module, traversal: Traversal, width: int, height: int, device: str = "cpu",
    store: ImageStore | None = None, batch: int = 32, engine: str = "torch", keep: bool = True,
) -> Traversal:
    """The traversal with the frame descriptors of a frame encoder (CosPlace) or a JIST model's encoder, images at
    ``width`` x ``height``. Pooling JIST's frames with ``model.sequence_pool`` (the retrieval matcher with
    pooling ``seqgem`` and that module) gives JIST's sequence descriptors. ``engine`` runs the frame encoder
    (``features.engines``; ``keep`` False: its export is not kept in the cache, as training's changing weights
    would only fill it)."""
    check_images_exist(traversal, traversal.source or traversal.name)
    store = store or ImageStore(width, height)
    encoder = model.encoder if isinstance(model, JistModel) else model
    if engine != "torch":  # training's validation keeps torch: its weights change between epochs
        from seqvpr.features.engines import with_engine

        encoder = with_engine(encoder.eval(), width, height, engine, device, keep)
    rows = encode_frames(encoder, store, list(traversal.image_paths), device, batch)
    return traversal.with_descriptors(rows.cpu().numpy())


#: JIST's frames are its encoder's (the name the training and its tests use)
describe_with_jist = describe_images


# --- model folder ------------------------------------------------------------------------------------------------


def save_jist(folder: str | Path, model: JistModel, config: JistConfig, metadata: dict[str, Any]) -> Path:
    """``model.safetensors`` and ``config.json`` (format, the JistConfig, the sequence pool, then ``metadata``:
    image size, sequence length, training settings...), each written atomically."""
    pool = model.sequence_pool
    pool_meta = {"type": type(pool).__name__, "mode": getattr(pool, "mode", None), "eps": getattr(pool, "eps", None),
                 "normalize": getattr(pool, "normalize", True)}
    return save_model_folder(folder, model, {
        "format": FORMAT, "config": asdict(config), "sequence_pool": pool_meta, **metadata,
    })


def load_jist(folder: str | Path, *, backbone: nn.Module | None = None) -> JistModel:
    """The JIST model saved by ``save_jist`` (eval mode); ``backbone`` re-injects a custom backbone."""
    meta = read_model_config(folder, FORMAT, "JIST")
    from seqvpr.sequences.descriptors import SeqGeM

    try:
        values = dict(meta["config"], weights=None)
        config = JistConfig(**{**values, "trainable_stages": tuple(values.get("trainable_stages") or ())})
    except (KeyError, TypeError) as error:
        raise SeqvprError(f"{Path(folder) / CONFIG_FILE}: JIST config lacks a valid {error}") from None
    pool_meta = meta.get("sequence_pool") or {}
    pool = SeqGeM(mode=pool_meta.get("mode") or "clamp", eps=pool_meta.get("eps") or 1e-6,
                  normalize=bool(pool_meta.get("normalize", True)))
    return load_weights_into(build_jist(config, pool, backbone=backbone), folder)


def jist_image_size(meta: dict[str, Any]) -> tuple[int, int]:
    """The (width, height) a saved JIST model reads its images at (640 x 480 when the folder does not say)."""
    width, height = meta.get("image_size") or (640, 480)
    return int(width), int(height)
