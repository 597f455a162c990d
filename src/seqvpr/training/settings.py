"""Every training setting as plain frozen dataclasses, with their checks and defaults (the reference codes'):
``SeqMatchNetSettings``, ``SeqNetSettings``, JIST's ``JistTrainSettings`` and CosPlace's ``CellGrouping``.

No torch here: the command line reads these defaults for its ``--help`` without loading a model library.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from seqvpr import checks
from seqvpr.errors import SeqvprError
from seqvpr.models.configs import check_dim
from seqvpr.sequences.windows import SequenceSpec

SequenceMethod = Literal["seqmatch", "single"]
Optimizer = Literal["sgd", "adam"]
DEFAULT_MARGIN = math.sqrt(0.1)  # the reference's --margin 0.1, used as its square root
#: negatives lie outside this multiple of the positive radius: the reference codes' 10/40 frames (SeqMatchNet,
#: SeqNet) and 10/25 m (JIST); ``training.data.training_radii`` applies it
NEGATIVE_RADIUS_FACTOR = {"seqmatchnet": 4.0, "seqnet": 4.0, "jist": 2.5}


def jsonable(values: dict) -> dict:
    """``values`` as JSON would give them back (tuples become lists, other objects strings)."""
    return json.loads(json.dumps(values, default=str))


class SettingsRecord:
    """What every training-settings dataclass shares: a JSON-ready dict, and the part a resume must match."""

    def as_dict(self) -> dict[str, Any]:
        return jsonable(asdict(self))  # type: ignore[call-overload]

    def resume_key(self) -> dict[str, Any]:
        """What must not change when a run is resumed (everything but the number of epochs and the device)."""
        return {k: v for k, v in self.as_dict().items() if k not in ("epochs", "device")}


def check_optimizer_settings(settings: Any) -> None:
    """The checks of an SGD/Adam settings object (SeqMatchNet's and SeqNet's call this from ``__post_init__``):
    each field's type and range, one line naming it (``seqvpr.checks``)."""
    checks.instance(settings.sequence, "sequence", SequenceSpec, "a SequenceSpec")
    for name, least in (("negatives", 1), ("batch_size", 1), ("epochs", 0), ("lr_step", 1), ("select_k", 1),
                        ("seed", 0)):
        object.__setattr__(settings, name, checks.whole(getattr(settings, name), name, least))
    for name in ("negative_pool", "refresh_every"):
        object.__setattr__(settings, name, checks.optional_whole(getattr(settings, name), name, 1))
    for name, low, open_low in (("margin", 0.0, True), ("lr", 0.0, True), ("momentum", 0.0, False),
                                ("weight_decay", 0.0, False), ("lr_gamma", 0.0, True)):
        object.__setattr__(settings, name, checks.finite(getattr(settings, name), name, low, open_low=open_low))
    checks.text(settings.optimizer, "optimizer", ("sgd", "adam"))
    object.__setattr__(settings, "ks", checks.whole_numbers(settings.ks, "ks"))
    checks.flag(settings.select_untrained, "select_untrained")
    checks.device(settings.device)


def check_augmentation(jitter: float, hue: float, crop_scale: float) -> None:
    """CosPlace-style augmentation strengths: jitter in [0, 1], hue in [0, 0.5] of a turn, crop area in (0, 1]."""
    checks.finite(jitter, "jitter", 0.0, 1.0)
    checks.finite(hue, "hue", 0.0, 0.5)
    checks.finite(crop_scale, "crop_scale", 0.0, 1.0, open_low=True)


def window_part(method: SequenceMethod, length: int, offset: int) -> slice | None:
    """Frames of a window a distance uses: all of them (seqmatch) or the current frame only (single)."""
    if method == "seqmatch":
        return None
    if method == "single":
        return slice(offset, offset + 1)
    raise SeqvprError(f"sequence method must be 'seqmatch' or 'single', got {method!r}")


@dataclass(frozen=True)
class CellGrouping:
    """CosPlace classes: UTM cells of M metres x heading sectors of alpha degrees, split into N*N*L groups so that
    classes of one group are never adjacent. Defaults are the reference's (``--M 10 --alpha 30 --N 5 --L 2
    --min_images_per_class 10``, digest section 3.2 and 3.7)."""

    cell_m: float = 10.0
    heading_deg: float = 30.0
    groups_n: int = 5
    groups_l: int = 2
    min_images: int = 10

    def __post_init__(self) -> None:
        object.__setattr__(self, "cell_m", checks.finite(self.cell_m, "cell_m", 0.0, open_low=True))
        object.__setattr__(self, "heading_deg", checks.finite(self.heading_deg, "heading_deg", 0.0, 360.0, True))
        for name in ("groups_n", "groups_l", "min_images"):
            object.__setattr__(self, name, checks.whole(getattr(self, name), name, 1))

    @property
    def n_groups(self) -> int:
        """How many groups exist (N*N*L); some may be empty."""
        return self.groups_n * self.groups_n * self.groups_l


@dataclass(frozen=True)
class SeqMatchNetSettings(SettingsRecord):
    """Every choice of a SeqMatchNet run; defaults follow the reference code (SGD 1e-3, step x0.5 every 5)."""

    sequence: SequenceSpec = field(default_factory=lambda: SequenceSpec(5))
    loss: SequenceMethod = "seqmatch"
    mining: SequenceMethod = "seqmatch"
    margin: float = DEFAULT_MARGIN
    negatives: int = 10
    negative_pool: int | None = 1000
    refresh_every: int = 1000
    batch_size: int = 16
    epochs: int = 50
    optimizer: Optimizer = "sgd"
    lr: float = 1e-3
    momentum: float = 0.9
    weight_decay: float = 1e-3
    lr_step: int = 5
    lr_gamma: float = 0.5
    select_k: int = 1
    ks: tuple[int, ...] = (1, 5, 10, 20)
    select_untrained: bool = False
    seed: int = 123
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_optimizer_settings(self)
        window_part(self.loss, self.sequence.length, self.sequence.offset)
        window_part(self.mining, self.sequence.length, self.sequence.offset)


@dataclass(frozen=True)
class SeqNetSettings(SettingsRecord):
    """Every choice of a SeqNet run. Defaults follow the reference seqNet code (design digest, reference
    implementations §2.2 flags, §2.3 model, §2.5 training, §7 checklist):

    * ``sequence`` L = 5 (``--seqL 5``) and ``w`` = 3 (``--w 3``) (§2.2; Oxford/MSLS recipe, §2.3);
    * ``out_dim`` None = the input dimension (the reference has no default, ``--outDims`` must be given and the
      README uses 4096 = its input size, §2.2);
    * SGD ``lr`` 1e-4, ``momentum`` 0.9, ``weight_decay`` 1e-3, StepLR every ``lr_step`` 50 epochs x ``lr_gamma``
      0.5, ``epochs`` 200, ``batch_size`` 16 queries (§2.2);
    * ``margin`` sqrt(0.1) on non-squared Euclidean distances (``--margin 0.1`` used as its root, §2.2/§2.5);
    * ``negatives`` 10 hardest from ``negative_pool`` 1000 random candidates + the query's cached negatives,
      violating-margin filter (§2.2 hard-coded nNeg/nNegSample, §2.5);
    * ``refresh_every`` None: the mining features are computed once per epoch (``--cacheRefreshRate 0``, §2.2);
    * best epoch by validation Recall@5 (``select_k`` 5, §2.5) among the trained epochs (the untrained epoch 0 only
      with ``select_untrained``); ``seed`` 123 (§2.2).

    Deviations (deliberate): windows never cross a segment break (§5 item 1; the spec's boundary rule decides
    edge frames); validation runs on its own split, never the test set (§5 item 2); the negative cache lives in
    the main process, so it is actually used (§5 item 9); Euclidean distances in the loss are a clamped sqrt of
    the squared difference (``nn.TripletMarginLoss`` adds eps=1e-6 to the difference instead); the loss is the
    mean over all (q, p, n) triplets, which equals the reference's sum divided by the number of negatives.
    """

    sequence: SequenceSpec = field(default_factory=lambda: SequenceSpec(5))
    w: int = 3
    out_dim: int | None = None
    margin: float = DEFAULT_MARGIN
    negatives: int = 10
    negative_pool: int | None = 1000
    refresh_every: int | None = None
    batch_size: int = 16
    epochs: int = 200
    optimizer: Literal["sgd", "adam"] = "sgd"
    lr: float = 1e-4
    momentum: float = 0.9
    weight_decay: float = 1e-3
    lr_step: int = 50
    lr_gamma: float = 0.5
    select_k: int = 5
    ks: tuple[int, ...] = (1, 5, 10, 20)
    select_untrained: bool = False
    seed: int = 123
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_optimizer_settings(self)
        object.__setattr__(self, "w", checks.whole(self.w, "w", 1))
        object.__setattr__(self, "out_dim", checks.optional_whole(self.out_dim, "out_dim", 1))
        if self.sequence.length < self.w:
            raise SeqvprError(
                f"seqnet: sequence length {self.sequence.length} is shorter than the temporal kernel width w={self.w}"
            )
        if tuple(self.sequence.velocities) != (1.0,):
            raise SeqvprError(f"seqnet: sequence descriptors use velocity 1 only, got {self.sequence.velocities}")
        if self.out_dim is not None:
            check_dim(self.out_dim, "--out-dim")


@dataclass(frozen=True)
class JistTrainSettings(SettingsRecord):
    """Schedule, batches, mining and runtime of a JIST run. Reference values (digest 3.2, 3.6, 3.7): 5 epochs x 10
    refreshes, 1000 queries / 3000 pool windows per refresh, 4 triplets x 5 negatives, 64 classification images,
    groups rotated per epoch, AMP. ``max_iterations`` caps the steps of one refresh (None: all triplets).

    The classification images are augmented as CosPlace's are: colour jitter (brightness, contrast and saturation
    factors in [1 - ``jitter``, 1 + ``jitter``], hue turned by up to ``hue`` of a turn) and a random crop keeping
    ``crop_scale`` to 1 of the area, resized back; ``jitter`` 0, ``hue`` 0 and ``crop_scale`` 1 switch it off."""

    epochs: int = 5
    refreshes: int = 10
    queries_per_refresh: int = 1000
    negative_pool: int = 3000
    batch_size: int = 4
    negatives: int = 5
    images_per_batch: int = 64
    max_iterations: int | None = None
    width: int = 640
    height: int = 480
    grouping: CellGrouping = field(default_factory=CellGrouping)
    group_per: str = "iteration"
    jitter: float = 0.7
    hue: float = 0.5
    crop_scale: float = 0.5
    select_k: int = 5
    ks: tuple[int, ...] = (1, 5, 10)
    select_untrained: bool = False
    infer_batch: int = 32
    device: str = "cpu"
    engine: str = "torch"  # how validation describes frames (seqvpr.features.engines; an export an epoch, not kept)
    amp: bool = True
    cache_images: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("epochs", "refreshes", "queries_per_refresh", "negative_pool", "batch_size", "negatives",
                     "images_per_batch", "width", "height", "select_k", "infer_batch"):
            object.__setattr__(self, name, checks.whole(getattr(self, name), name, 1))
        object.__setattr__(self, "max_iterations", checks.optional_whole(self.max_iterations, "max_iterations", 1))
        object.__setattr__(self, "seed", checks.whole(self.seed, "seed", 0))
        object.__setattr__(self, "ks", checks.whole_numbers(self.ks, "ks"))
        checks.text(self.group_per, "group_per", ("iteration", "epoch"))
        checks.instance(self.grouping, "grouping", CellGrouping, "a CellGrouping")
        for name in ("select_untrained", "amp", "cache_images"):
            checks.flag(getattr(self, name), name)
        checks.device(self.device)
        checks.text(self.engine, "engine", checks.ENGINES)
        if self.select_k not in self.ks:
            raise SeqvprError(f"select_k={self.select_k} must be one of the recall ks {self.ks}")
        check_augmentation(self.jitter, self.hue, self.crop_scale)

    def resume_key(self) -> dict[str, Any]:
        """What must not change when a run is resumed (not the epochs, device, inference batch or image cache)."""
        return {k: v for k, v in super().resume_key().items() if k not in ("infer_batch", "cache_images", "engine")}


#: frames whose sides are both at most this many pixels are thumbnails (Nordland's 64x32)
THUMBNAIL_SIDE = 128
#: what ``seqvpr train jist`` trains thumbnails with unless told otherwise (BENCHMARKS.md, "JIST on Nordland"):
#: a small CNN over patch-normalised grey frames, from scratch (ImageNet EfficientNet-Lite0 starts near chance on
#: 64x32 grey frames, upsampled or not), at a learning rate for training from scratch, CosPlace classes of one
#: frame (two images: the pair's conditions), and a schedule of about 7 minutes an epoch on 2 CPU cores
THUMBNAIL_RECIPE: dict[str, Any] = {
    "backbone": "thumbnail-cnn", "weights": None, "out_dim": 256, "lr": 1e-3, "epochs": 2, "refreshes": 5,
    "queries_per_refresh": 400, "negative_pool": 1000, "max_iterations": 40, "batch_size": 8,
    "images_per_batch": 64, "cell_m": 1.0, "min_images": 2, "jitter": 0.3, "hue": 0.0, "crop_scale": 0.8,
}


def with_recipe(values: dict[str, Any], size: tuple[int, int]) -> dict[str, Any]:
    """The flat JIST table ``values`` (keys ``jist_setup`` takes; None: not given) over the recipe for frames of
    ``size``: ``THUMBNAIL_RECIPE`` when the backbone is (or, not given, the frames are thumbnails and so it becomes)
    the thumbnail CNN, at the frames' own size rounded up to whole 8-pixel patches (64x32 for larger frames); the
    reference's defaults otherwise. A given value always wins; ``recipe`` in the result names the one used."""
    given = {k: v for k, v in values.items() if v is not None}
    small = max(size) <= THUMBNAIL_SIDE
    if given.get("backbone", "thumbnail-cnn" if small else None) != "thumbnail-cnn":
        return {**given, "recipe": "reference"}
    width, height = (-(-side // 8) * 8 for side in size) if small else (64, 32)
    return {**THUMBNAIL_RECIPE, "width": width, "height": height, **given, "recipe": "thumbnails"}
