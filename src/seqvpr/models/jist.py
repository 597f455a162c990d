"""JIST: a CosPlace frame encoder whose per-frame descriptors a sequence pooling module (SeqGeM) turns into one
descriptor per window, trained jointly on sequence triplets and CosPlace single-image classification.

Frame descriptor (CosPlace, digest section 3.3): backbone map -> channel-wise L2 -> GeM (learnable p, init 3) ->
Linear(C -> out_dim) -> L2. Only the chosen backbone stages (``layer4`` by default) and the head are trained; the
other stages are frozen for real: ``requires_grad`` off and their BatchNorm layers kept in eval mode, so their
running statistics do not drift as the reference's do (digest section 5, item 14).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from seqvpr.errors import SeqvprError
from seqvpr.features import backbones
from seqvpr.features.extraction import IMAGENET_MEAN, IMAGENET_STD
from seqvpr.features.pooling import GeM
from seqvpr.training.cosplace import CosFaceHead, cosface_loss
from seqvpr.training.losses import triplet_hinge

JIST_BACKBONES = ("resnet18", "resnet50", "efficientnet-lite0")


@dataclass(frozen=True)
class JistConfig:
    """Every choice of a JIST model and its joint loss; defaults are the reference's (digest sections 3.2, 3.3,
    3.7): ResNet-18, 512-D, only ``layer4`` trainable, L=5, loss = 1e4 * sequence triplet (margin 0.1, Euclidean)
    + 1e2 * CosFace cross-entropy (s=30, m=0.4), Adam lr 1e-5 for the model and 1e-2 for the classifiers.

    ``trainable_stages`` names backbone stages: ``stem``, ``layer1``..``layer4`` for ResNets; ``stem``,
    ``stage1``..``stage7``, ``head`` for EfficientNet-Lite0; the top-level child names for an injected backbone.
    ``weights``: None (random, for tests), a checkpoint path (torchvision or CosPlace keys; a CosPlace file also
    fills the GeM/Linear head), or 'imagenet' (EfficientNet-Lite0 only).
    """

    backbone: str = "resnet18"
    weights: str | None = None
    out_dim: int = 512
    trainable_stages: tuple[str, ...] = ("layer4",)
    seq_length: int = 5
    triplet_weight: float = 1e4
    classification_weight: float = 1e2
    margin: float = 0.1
    lr: float = 1e-5
    classifier_lr: float = 1e-2
    cosface_s: float = 30.0
    cosface_m: float = 0.4

    def __post_init__(self) -> None:
        if self.backbone not in JIST_BACKBONES:
            raise SeqvprError(f"backbone {self.backbone!r} is not known (choose from: {', '.join(JIST_BACKBONES)})")
        if isinstance(self.trainable_stages, str) or not all(isinstance(s, str) for s in self.trainable_stages):
            raise SeqvprError(f"trainable_stages must be a tuple of stage names, got {self.trainable_stages!r}")
        for name in ("out_dim", "seq_length"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise SeqvprError(f"{name} must be a positive integer, got {value}")
        for name in ("triplet_weight", "classification_weight", "margin"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise SeqvprError(f"{name} must be a number >= 0, got {value}")
        for name in ("lr", "classifier_lr", "cosface_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SeqvprError(f"{name} must be a positive number, got {value}")
        if not (math.isfinite(self.cosface_m) and self.cosface_m >= 0):
            raise SeqvprError(f"cosface_m must be a number >= 0, got {self.cosface_m}")


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
        normalised = (images - self.mean.to(images.dtype)) / self.std.to(images.dtype)
        local = nn.functional.normalize(self.backbone.features(normalised), dim=1)
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

    ``sequence_pool`` defaults to ``seqvpr.sequences.descriptors.SeqGeM()``; ``backbone`` injects another image
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

        sequence_pool = SeqGeM()
    return JistModel(encoder, sequence_pool).eval()


def trainable_parameters(model: JistModel, config: JistConfig) -> list[nn.Parameter]:
    """What the model optimiser updates: the configured backbone stages, the encoder head and the sequence pool's
    parameters (those that require grad)."""
    params: dict[int, nn.Parameter] = {}
    for p in model.encoder.stage_parameters(config.trainable_stages):
        params[id(p)] = p
    for p in model.encoder.head_parameters():
        params[id(p)] = p
    for p in model.sequence_pool.parameters():
        if p.requires_grad:
            params[id(p)] = p
    return list(params.values())


def optimizer_groups(
    model: JistModel, classifiers: nn.Module | Iterable[nn.Module], config: JistConfig
) -> list[dict]:
    """Two Adam parameter groups: the model's trainable parameters at ``config.lr`` and the CosFace classifiers'
    at ``config.classifier_lr`` (the reference uses two Adam optimisers; Adam state is per parameter, so one
    optimiser with two groups takes the same steps)."""
    if isinstance(classifiers, nn.Module):
        classifiers = [classifiers]
    heads: dict[int, nn.Parameter] = {}
    for head in classifiers:
        heads.update((id(p), p) for p in head.parameters())
    return [
        {"params": trainable_parameters(model, config), "lr": config.lr},
        {"params": list(heads.values()), "lr": config.classifier_lr},
    ]


def make_classifier(config: JistConfig, n_classes: int) -> CosFaceHead:
    """One group's CosFace classifier over the model's frame descriptors, with the configured s and m."""
    return CosFaceHead(config.out_dim, n_classes, s=config.cosface_s, m=config.cosface_m)


def euclidean(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise Euclidean distance with a finite gradient at zero distance."""
    return (a - b).pow(2).sum(-1).clamp_min(1e-12).sqrt()


def jist_losses(
    model: JistModel,
    head: CosFaceHead,
    windows_q: torch.Tensor,
    windows_p: torch.Tensor,
    windows_n: torch.Tensor,
    images: torch.Tensor,
    labels: torch.Tensor,
    config: JistConfig,
) -> dict[str, torch.Tensor]:
    """The joint objective of one step (digest section 3.7).

    ``windows_q``/``windows_p``: [B, L, 3, H, W]; ``windows_n``: [B, K, L, 3, H, W] (K negatives per query; a
    5-D tensor means K = 1). All B*(2+K) windows go through the model in one pass. "sequence" is the mean over
    the B*K triplets of ``[|q-p| - |q-n| + margin]_+`` on sequence descriptors; "images" the CosFace
    cross-entropy of the single ``images`` [M, 3, H', W'] with ``labels`` [M]; "total" is
    ``triplet_weight * sequence + classification_weight * images``.
    """
    _check_windows(windows_q, "query windows")
    if windows_p.shape != windows_q.shape:
        raise SeqvprError(
            f"positive windows must have the query windows' shape {tuple(windows_q.shape)}, got {tuple(windows_p.shape)}"
        )
    if windows_n.ndim == 5:
        windows_n = windows_n.unsqueeze(1)
    b = windows_q.shape[0]
    if windows_n.ndim != 6 or windows_n.shape[0] != b or windows_n.shape[1] < 1 or windows_n.shape[2:] != windows_q.shape[1:]:
        raise SeqvprError(
            f"negative windows must be [{b}, K, {', '.join(map(str, windows_q.shape[1:]))}], "
            f"got shape {tuple(windows_n.shape)}"
        )
    _check_images(images)
    k = windows_n.shape[1]
    descriptors = model(torch.cat([windows_q, windows_p, windows_n.flatten(0, 1)]))
    q, p, n = descriptors[:b], descriptors[b : 2 * b], descriptors[2 * b :].view(b, k, -1)
    d_ap = euclidean(q, p)[:, None].expand(b, k)
    d_an = euclidean(q[:, None], n)
    sequence = triplet_hinge(d_ap, d_an, config.margin)
    image_loss = cosface_loss(head, model.frames(images), labels)
    total = config.triplet_weight * sequence + config.classification_weight * image_loss
    return {"sequence": sequence, "images": image_loss, "total": total}
