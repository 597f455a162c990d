"""Model configurations as plain frozen dataclasses: SeqMatchNet's ``TransformConfig`` and ``JistConfig`` (with the
per-backbone default trainable stages). No torch here: the command line reads these defaults for its ``--help``
without loading a model library."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Literal

from seqvpr.errors import SeqvprError, SettingError

Init = Literal["reference", "identity"]


#: the largest descriptor a model may output: a layer to it holds input x output weights
MAX_DIM = 65_536


def check_dim(dim: int, option: str) -> None:
    """One line when a model's output dimension ``dim`` is above ``MAX_DIM`` (before any weight is allocated)."""
    if dim > MAX_DIM:
        raise SeqvprError(f"{option} {dim}: at most {MAX_DIM} dimensions")


@dataclass(frozen=True)
class TransformConfig:
    """Shape and initialisation of the transform.

    ``out_dim`` defaults to ``in_dim`` (as in the paper); ``hidden`` adds ReLU layers (the supplement's deeper
    variant). ``init="reference"`` is PyTorch's default Linear/Conv1d initialisation (what the reference code
    gets); ``"identity"`` starts from W = I (semi-orthogonal when the dimensions differ) and B = 0, i.e. from the
    untransformed descriptors.
    """

    in_dim: int
    out_dim: int | None = None
    hidden: tuple[int, ...] = ()
    init: Init = "reference"
    normalize_input: bool = True

    def __post_init__(self) -> None:
        dims = (self.in_dim, self.output_dim, *self.hidden)
        if any(int(d) != d or d < 1 for d in dims):
            raise SeqvprError(f"transform dimensions must be positive integers, got in={self.in_dim} "
                              f"out={self.out_dim} hidden={self.hidden}")
        check_dim(self.output_dim, "--out-dim")
        if self.init not in ("reference", "identity"):
            raise SettingError(f"{{init}} must be 'reference' or 'identity', got {self.init!r}")

    @property
    def output_dim(self) -> int:
        return self.in_dim if self.out_dim is None else self.out_dim

    def as_dict(self) -> dict:
        return {**asdict(self), "hidden": list(self.hidden)}

    @classmethod
    def from_dict(cls, values: dict) -> TransformConfig:
        return cls(
            in_dim=int(values["in_dim"]),
            out_dim=None if values.get("out_dim") is None else int(values["out_dim"]),
            hidden=tuple(int(h) for h in values.get("hidden", ())),
            init=values.get("init", "reference"),
            normalize_input=bool(values.get("normalize_input", True)),
        )


JIST_BACKBONES = ("resnet18", "resnet50", "efficientnet-lite0", "thumbnail-cnn")
#: the backbone stages trained when none are named: the last one (the reference's layer4); every stage of the
#: thumbnail CNN, which trains from scratch
DEFAULT_STAGES = {"resnet18": ("layer4",), "resnet50": ("layer4",), "efficientnet-lite0": ("stage7", "head"),
                  "thumbnail-cnn": ("stage1", "stage2", "stage3", "head")}
#: what JIST's loss trains: both branches (the paper's joint training), the sequence triplets alone, or the
#: CosPlace classification of single images alone (the ablation's rows)
JIST_BRANCHES = ("joint", "sequence", "images")


@dataclass(frozen=True)
class JistConfig:
    """Every choice of a JIST model and its joint loss; defaults are the reference's (digest sections 3.2, 3.3,
    3.7): ResNet-18, 512-D, only ``layer4`` trainable, L=5, loss = 1e4 * sequence triplet (margin 0.1, Euclidean)
    + 1e2 * CosFace cross-entropy (s=30, m=0.4), Adam lr 1e-5 for the model and 1e-2 for the classifiers.

    ``trainable_stages`` names backbone stages: ``stem``, ``layer1``..``layer4`` for ResNets; ``stem``,
    ``stage1``..``stage7``, ``head`` for EfficientNet-Lite0; the top-level child names for an injected backbone.
    None (or empty) is the backbone's default, ``DEFAULT_STAGES``: its last stage.
    ``weights``: None (random, for tests), a checkpoint path (torchvision or CosPlace keys; a CosPlace file also
    fills the GeM/Linear head), or 'imagenet' (EfficientNet-Lite0 only); ``thumbnail-cnn`` (a small CNN over
    patch-normalised grey thumbnails) trains from scratch. ``seqgem_normalize``: L2-normalise the SeqGeM output
    (seqvpr's default); False is upstream's forward, searched by plain L2 as the reference does. ``branches``: what
    the loss trains (``JIST_BRANCHES``): a branch left out is not computed at all.
    """

    backbone: str = "resnet18"
    weights: str | None = None
    out_dim: int = 512
    trainable_stages: tuple[str, ...] | None = None
    seq_length: int = 5
    triplet_weight: float = 1e4
    classification_weight: float = 1e2
    margin: float = 0.1
    lr: float = 1e-5
    classifier_lr: float = 1e-2
    cosface_s: float = 30.0
    cosface_m: float = 0.4
    seqgem_normalize: bool = True
    branches: str = "joint"

    def __post_init__(self) -> None:
        if self.branches not in JIST_BRANCHES:
            raise SeqvprError(f"branches {self.branches!r} is not known (choose from: {', '.join(JIST_BRANCHES)})")
        if self.backbone not in JIST_BACKBONES:
            raise SeqvprError(f"backbone {self.backbone!r} is not known (choose from: {', '.join(JIST_BACKBONES)})")
        if isinstance(self.trainable_stages, str):
            raise SettingError(f"{{trainable_stages}} must be a tuple of stage names, got {self.trainable_stages!r}")
        if not self.trainable_stages:
            object.__setattr__(self, "trainable_stages", DEFAULT_STAGES[self.backbone])
        object.__setattr__(self, "trainable_stages", tuple(self.trainable_stages))
        if not all(isinstance(s, str) for s in self.trainable_stages):
            raise SettingError(f"{{trainable_stages}} must be a tuple of stage names, got {self.trainable_stages!r}")
        for name in ("out_dim", "seq_length"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise SeqvprError(f"{name} must be a positive integer, got {value}")
        check_dim(self.out_dim, "--out-dim")
        for name in ("triplet_weight", "classification_weight", "margin"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise SeqvprError(f"{name} must be a number >= 0, got {value}")
        for name in ("lr", "classifier_lr", "cosface_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SeqvprError(f"{name} must be a positive number, got {value}")
        if not (math.isfinite(self.cosface_m) and self.cosface_m >= 0):
            raise SettingError(f"{{cosface_m}} must be a number >= 0, got {self.cosface_m}")
