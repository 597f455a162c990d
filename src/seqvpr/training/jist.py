"""JIST training: a frame encoder + SeqGeM trained jointly on sequence triplets and CosPlace classification,
as a learner of the one training loop (``trainer.train_sequence_model``).

Per step (digest section 3.7): one batch of mined sequence triplets (query window, nearest positive reference
window, K hardest negatives outside the negative radius) and one class-balanced batch of single images from ONE
CosPlace group, each group with its own CosFace head (``JistLoss``, the loss's trainable parameters). The classes
hold every training traversal's images of a place (reference and query: all conditions), augmented as CosPlace's
(``training.augment``), so the classifier too learns what survives a change of condition; CosPlace cells may not
be wider than the negative radius (frames of one class would be negatives of each other in the triplet loss). The loss is
``jist_losses(...)["total"]``; one Adam optimiser with a model group (``config.lr``) and a group for the heads
(``config.classifier_lr``). An epoch has ``refreshes`` mining rounds (the reference's sub-epochs), each over
``queries_per_refresh`` random trainable queries and a pool of ``negative_pool`` reference windows: the frames
they use are encoded once (no grad) and pooled into windows with ``model.pool``; the shared ``SequenceMiner`` picks
the triplets with a kernel over those window descriptors. Validation is the pipeline's:
``describe_with_jist`` then SeqGeM retrieval (``RetrievalMatcher``) and Recall@K.

Same name as ``seqvpr.models.jist``: JIST's learner; its model there.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from seqvpr.data.ground_truth import GroundTruth, Radius
from seqvpr import checks
from seqvpr.data.traversal import Traversal, frame_positions
from seqvpr.errors import SeqvprError, SettingError
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.models.files import MODEL_FILE, read_tensors
from seqvpr.models.jist import (
    ImageStore, JistConfig, JistModel, build_jist, check_images_exist, describe_with_jist, encode_frames, save_jist,
    trainable_parameters,
)
from seqvpr.matchers.retrieval import RetrievalMatcher
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec, window_frames
from seqvpr.training.augment import augment_images
from seqvpr.training.cosplace import CosFaceHead, assign_classes, cosface_loss, group_members
from seqvpr.training.settings import CellGrouping, JistTrainSettings
from seqvpr.training.losses import euclidean, triplet_hinge
from seqvpr.training.mining import MiningConfig, SequenceMiner, Triplet
from seqvpr.training.trainer import (
    SequenceLearner, Step, check_training_inputs, TrainingContext, TrainingData, TrainingMonitor, TrainResult,
    train_sequence_model,
)


def train_jist(
    data: TrainingData,
    config: JistConfig,
    settings: JistTrainSettings,
    out_dir: str | Path,
    *,
    resume: bool = False,
    monitor: TrainingMonitor | None = None,
    backbone_factory: Callable[[], nn.Module] | None = None,
    classification: Sequence[Traversal] | None = None,
) -> TrainResult:
    """Train JIST jointly (see the module docstring); the best epoch by validation R@select_k goes to ``out_dir``
    (``models.jist.load_jist`` reads it), with ``history.csv`` and the resumable state. ``classification``: the
    traversals whose single images feed the CosPlace branch (default: the training reference and query);
    ``backbone_factory`` builds an injected backbone (tests). Runs with the same seed are identical on CPU."""
    check_training_inputs(data, settings, JistTrainSettings)
    checks.instance(config, "config", JistConfig, "a JistConfig")
    checks.function(backbone_factory, "backbone_factory")
    if classification is not None and (isinstance(classification, (str, bytes)) or not all(
            isinstance(t, Traversal) for t in checks.instance(classification, "classification", Sequence,
                                                              "a list of traversals (or None)"))):
        raise SettingError("{classification} must be a list of traversals (or None)")
    learner = JistLearner(config, settings, backbone_factory, classification)
    return train_sequence_model(data, learner, settings, out_dir, resume=resume, monitor=monitor)


def training_spec(length: int) -> SequenceSpec:
    """JIST's windows (digest 3.4): centred, stride 1, windows that would leave the segment are dropped."""
    return SequenceSpec(length, "centered", "drop")


def jist_positions(traversal: Traversal, radius: Radius) -> Traversal:
    """A traversal JIST can train on at this radius unit: images with positions in metres, or, with a frame
    radius, frame-aligned images placed along the route one unit per frame (``frame_positions``)."""
    label = traversal.source or traversal.name
    if traversal.image_paths is None:
        raise SeqvprError(f"{label}: JIST trains from images, this traversal holds descriptors only")
    if radius.unit == "m":
        if traversal.positions is None:
            raise SettingError(f"{label}: no positions for a radius in metres; frame-aligned data takes a frame "
                              f"radius, e.g. {{radius}} 1f")
        return traversal
    if traversal.positions is not None:
        raise SettingError(f"{{radius}} {radius}: {label} has positions; give the radius in metres, e.g. 25m "
                          f"(a frame radius is for frame-aligned traversals without positions)")
    return frame_positions(traversal)


# --- the classification images ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class ClassificationImages:
    """The single images the CosPlace branch classifies, with their positions [N, 2] and headings [N] (None
    unless every traversal has them)."""

    paths: list[Path]
    positions: np.ndarray
    headings: np.ndarray | None


def classification_images(traversals: Sequence[Traversal]) -> ClassificationImages:
    """Every image of the traversals (all conditions of each place), in traversal order."""
    for traversal in traversals:
        if traversal.positions is None or traversal.image_paths is None:
            raise SeqvprError(f"{traversal.source or traversal.name}: JIST's classification needs images with "
                              f"positions (metres, or frames placed along the route by jist_positions)")
    headings = [t.headings for t in traversals]
    return ClassificationImages(
        [Path(p) for t in traversals for p in t.image_paths],
        np.concatenate([np.asarray(t.positions, dtype=np.float64) for t in traversals]),
        None if any(h is None for h in headings) else np.concatenate([np.asarray(h, np.float64) for h in headings]),
    )


def check_cells(grouping: CellGrouping, negative: Radius) -> None:
    """CosPlace cells must fit inside the negative radius: two images of one class (up to a cell's diagonal
    apart in metres, a cell's length in frames) may not be negatives of each other for the triplet loss."""
    widest = grouping.cell_m * (math.sqrt(2.0) if negative.unit == "m" else 1.0)
    if widest > negative.value:
        what = f"diagonal {widest:g}{negative.unit}" if negative.unit == "m" else f"{widest:g} frames"
        raise SettingError(
            f"CosPlace cells of {grouping.cell_m:g}{negative.unit} ({what}) are wider than the negative radius "
            f"{negative}: images of one class would be negatives of each other; use a cell size of at most "
            f"{negative.value / (widest / grouping.cell_m):g}{negative.unit} ({{cell_size}}) or a larger {{neg_radius}}"
        )


# --- the loss: sequence triplets + CosFace classification per group ----------------------------------------------


class JistLoss(nn.Module):
    """The loss's trainable part: one CosFace classifier per CosPlace group (created in group order, right after
    the model, from the seeded generator)."""

    def __init__(self, config: JistConfig, classes_per_group: dict[int, int]) -> None:
        super().__init__()
        self.heads = nn.ModuleDict({
            str(group): CosFaceHead(config.out_dim, n, s=config.cosface_s, m=config.cosface_m)
            for group, n in sorted(classes_per_group.items())
        })

    def head(self, group: int) -> CosFaceHead:
        return self.heads[str(group)]


def jist_losses(
    model: JistModel,
    head: CosFaceHead | None,
    windows_q: torch.Tensor | None,
    windows_p: torch.Tensor | None,
    windows_n: torch.Tensor | None,
    images: torch.Tensor | None,
    labels: torch.Tensor | None,
    config: JistConfig,
) -> dict[str, torch.Tensor]:
    """The joint objective of one step (digest section 3.7).

    ``windows_q``/``windows_p``: [B, L, 3, H, W]; ``windows_n``: [B, K, L, 3, H, W] (K negatives per query; a
    5-D tensor means K = 1). All B*(2+K) windows go through the model in one pass. "sequence" is the mean over
    the B*K triplets of ``[|q-p| - |q-n| + margin]_+`` on sequence descriptors; "images" the CosFace
    cross-entropy of the single ``images`` [M, 3, H', W'] with ``labels`` [M]; "total" is
    ``triplet_weight * sequence + classification_weight * images``. A branch ``config.branches`` leaves out is
    not computed (its inputs may be None) and reads 0.
    """
    zero = torch.zeros((), device=next(model.parameters()).device)
    sequence = image_loss = zero
    if config.branches != "images":
        windows_n = _check_triplet_windows(windows_q, windows_p, windows_n)
        b, k = windows_q.shape[0], windows_n.shape[1]
        descriptors = model(torch.cat([windows_q, windows_p, windows_n.flatten(0, 1)]))
        q, p, n = descriptors[:b], descriptors[b : 2 * b], descriptors[2 * b :].view(b, k, -1)
        sequence = triplet_hinge(euclidean(q, p)[:, None].expand(b, k), euclidean(q[:, None], n), config.margin)
    if config.branches != "sequence":
        if images is None or images.ndim != 4 or images.shape[1] != 3 or images.shape[0] < 1:
            shape = None if images is None else tuple(images.shape)
            raise SeqvprError(f"images must be [B, 3, H, W] with B >= 1, got shape {shape}")
        image_loss = cosface_loss(head, model.frames(images), labels)
    total = config.triplet_weight * sequence + config.classification_weight * image_loss  # a left-out part is 0
    return {"sequence": sequence, "images": image_loss, "total": total}


def _check_triplet_windows(windows_q: torch.Tensor, windows_p: torch.Tensor, windows_n: torch.Tensor) -> torch.Tensor:
    """The negative windows as [B, K, L, 3, H, W], after checking all three shapes agree."""
    if windows_q.ndim != 5 or windows_q.shape[2] != 3 or windows_q.shape[0] < 1 or windows_q.shape[1] < 1:
        raise SeqvprError(f"query windows must be [B, L, 3, H, W] with B, L >= 1, got shape {tuple(windows_q.shape)}")
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
    return windows_n


# --- mining ----------------------------------------------------------------------------------------------------


def pool_windows(model: JistModel, frame_descriptors: torch.Tensor, frames: np.ndarray) -> torch.Tensor:
    """Sequence descriptors [n_windows, D] pooled from frame descriptors [N, D] (rows ``frames`` [n, L])."""
    index = torch.as_tensor(frames, device=frame_descriptors.device)
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            return model.pool(frame_descriptors[index.reshape(-1)].view(*frames.shape, -1)).float()
    finally:
        model.train(was_training)


def jist_window_descriptors(
    model: JistModel, store: ImageStore, traversal: Traversal, frames: np.ndarray, device: str, batch: int = 32
) -> torch.Tensor:
    """Descriptors of the given windows (rows [n, L] of the traversal): only the frames they use are encoded."""
    used, inverse = np.unique(frames.reshape(-1), return_inverse=True)
    descriptors = encode_frames(model, store, [traversal.image_paths[i] for i in used], device, batch)
    return pool_windows(model, descriptors, inverse.reshape(frames.shape))


def classification_batch(
    class_ids: np.ndarray, group_ids: np.ndarray, group: int, size: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, int]:
    """Class-balanced batch of one group (digest 3.7): ``size`` classes drawn in shuffled rounds, one random image
    each. Returns image rows, labels in [0, C_g) and C_g."""
    images, labels, n_classes = group_members(class_ids, group_ids, group)
    if n_classes == 0:
        raise SeqvprError(f"CosPlace group {group} has no class")
    rounds = -(-size // n_classes)
    classes = np.concatenate([rng.permutation(n_classes) for _ in range(rounds)])[:size]
    rows = np.array([rng.choice(images[labels == c]) for c in classes], dtype=np.int64)
    return rows, classes.astype(np.int64), n_classes


def used_groups(group_ids: np.ndarray) -> list[int]:
    """The non-empty CosPlace groups, sorted."""
    groups = np.unique(group_ids[group_ids >= 0])
    if len(groups) == 0:
        raise SeqvprError("no CosPlace class has enough images (lower min_images or use a larger cell size)")
    return [int(g) for g in groups]


def window_batch(store: ImageStore, traversal: Traversal, frames: np.ndarray, device: str) -> torch.Tensor:
    """Images of windows [n, L] as [n, L, 3, H, W]."""
    images = store.batch([traversal.image_paths[i] for i in frames.reshape(-1)], device)
    return images.view(*frames.shape, *images.shape[1:])


# --- the learner ---------------------------------------------------------------------------------------------------


class JistLearner(SequenceLearner):
    """JIST as a learner of the one training loop: image windows, mined in its own sequence-descriptor space."""

    config_key = "jist"
    unused_parameters = True  # a step trains one group's CosFace head

    def __init__(
        self, config: JistConfig, settings: JistTrainSettings,
        backbone_factory: Callable[[], nn.Module] | None = None, classification: Sequence[Traversal] | None = None,
    ) -> None:
        self.jist, self.spec = config, training_spec(config.seq_length)
        self.backbone_factory, self.classification = backbone_factory, classification
        self.store = ImageStore(settings.width, settings.height, settings.cache_images)

    def config(self) -> dict[str, Any]:
        return asdict(self.jist)

    def check_data(self, data: TrainingData) -> None:
        for name, traversal in data.traversals().items():
            check_images_exist(traversal, name)
        for traversal in self.classification or ():
            check_images_exist(traversal, "classification")
        classification_images(self.classification or (data.reference, data.query))

    def prepare(self, context: TrainingContext, settings: JistTrainSettings) -> None:
        self.context, self._settings = context, settings
        check_cells(settings.grouping, context.data.negative_radius)
        self.images = classification_images(self.classification or (context.data.reference, context.data.query))
        self.class_ids, self.group_ids = assign_classes(self.images.positions, self.images.headings, settings.grouping)
        self.groups = used_groups(self.group_ids)
        self.reference_rows = np.flatnonzero(context.reference_starts >= 0)
        self.encoded = np.zeros(len(context.reference_starts), dtype=bool)
        mining = MiningConfig(settings.negatives, pool=None, margin=self.jist.margin, only_violating=False)
        self.miner = SequenceMiner(self._distances, context.query_starts, context.positives, context.near, mining)

    def build_model(self, settings: JistTrainSettings) -> JistModel:
        return build_jist(self.jist, backbone=self.backbone_factory() if self.backbone_factory else None)

    def build_loss(self, settings: JistTrainSettings) -> JistLoss:
        classes = {g: group_members(self.class_ids, self.group_ids, g)[2] for g in self.groups}
        return JistLoss(self.jist, classes)

    def build_optimizer(self, model: JistModel, loss: JistLoss, settings: JistTrainSettings):
        """One Adam with two groups (the reference's two Adam optimisers take the same steps)."""
        return torch.optim.Adam([
            {"params": trainable_parameters(model, self.jist), "lr": self.jist.lr},
            {"params": list(loss.parameters()), "lr": self.jist.classifier_lr},
        ]), None

    def rounds(self, trainable: np.ndarray, rng: np.random.Generator, settings: JistTrainSettings) -> list[np.ndarray]:
        """``refreshes`` uniform samples of the trainable queries, in the drawn (random) order, as the reference's:
        batches of consecutive triplets then mix places along the route, and a ``max_iterations`` cap keeps a
        random subset rather than the start of the route."""
        size = min(settings.queries_per_refresh, len(trainable))
        return [rng.choice(trainable, size=size, replace=False) for _ in range(settings.refreshes)]

    def mine(self, model: JistModel, queries: np.ndarray, rng: np.random.Generator) -> list[Triplet]:
        """One refresh (digest 3.6): a pool of reference windows; the frames it and the queries' positives use
        encoded once and pooled into windows; then the shared miner (nearest positive, the K nearest pool windows
        outside the negative radius). Queries with fewer than K such negatives are skipped."""
        context, settings = self.context, self._settings
        pool = np.sort(rng.choice(self.reference_rows, size=min(settings.negative_pool, len(self.reference_rows)),
                                  replace=False))
        positives = [context.positives.positives_of(int(q)) for q in queries]
        needed = np.intersect1d(np.concatenate([pool, *positives]), self.reference_rows)
        self.encoded[:] = False
        self.encoded[needed] = True
        reference = torch.zeros(len(self.encoded), self.jist.out_dim, device=context.device)
        reference[torch.as_tensor(needed, device=context.device)] = self._windows(model, "reference", needed)
        query = torch.zeros(len(context.query_starts), self.jist.out_dim, device=context.device)
        query[torch.as_tensor(queries, device=context.device)] = self._windows(model, "query", queries)
        triplets = self.miner.mine(query, reference, queries, rng)
        return [t for t in triplets if len(t.negatives) == settings.negatives]

    def _distances(self, query: torch.Tensor, reference: torch.Tensor, starts: np.ndarray) -> torch.Tensor:
        """JIST's mining kernel: Euclidean distances from the windows starting at ``starts`` (query rows
        ``starts + offset``) to every reference window encoded this refresh (+inf for the others)."""
        rows = torch.as_tensor(np.asarray(starts) + self.spec.offset, device=query.device)
        distances = torch.cdist(query[rows], reference)
        return distances.masked_fill(~torch.as_tensor(self.encoded, device=distances.device)[None, :], float("inf"))

    def _windows(self, model: JistModel, side: str, rows: np.ndarray) -> torch.Tensor:
        starts = getattr(self.context, f"{side}_starts")[rows]
        traversal = getattr(self.context.data, side)
        return jist_window_descriptors(model, self.store, traversal, window_frames(starts, self.spec.length),
                                  str(self.context.device), self._settings.infer_batch)

    def batches(self, triplets: list[Triplet], settings: JistTrainSettings) -> list[list[Triplet]]:
        """Full batches only, at most ``max_iterations`` of them; a round with none is an error."""
        count = len(triplets) // settings.batch_size
        if settings.max_iterations is not None:
            count = min(count, settings.max_iterations)
        if count == 0:
            raise SeqvprError(f"only {len(triplets)} triplets were mined, fewer than one batch of {settings.batch_size}")
        return [triplets[b * settings.batch_size : (b + 1) * settings.batch_size] for b in range(count)]

    def batch_loss(
        self, model: JistModel, loss: JistLoss, batch: Sequence[Triplet], step: Step, rng: np.random.Generator,
        settings: JistTrainSettings,
    ) -> dict[str, torch.Tensor]:
        """The joint loss of one step: the batch's windows and an augmented classification batch of this step's
        group."""
        group = self.groups[(step.index if settings.group_per == "iteration" else step.epoch - 1) % len(self.groups)]
        rows, labels, _ = classification_batch(self.class_ids, self.group_ids, group, settings.images_per_batch, rng)
        device = str(self.context.device)
        images = labels_on = None
        if self.jist.branches != "sequence":
            images = self.store.batch([self.images.paths[i] for i in rows], device)
            images = augment_images(images, rng, settings.jitter, settings.hue, settings.crop_scale)
            labels_on = torch.as_tensor(labels, device=device)
        windows = self._triplet_images(batch) if self.jist.branches != "images" else (None, None, None)
        return jist_losses(model, loss.head(group), *windows, images, labels_on, self.jist)

    def _triplet_images(self, batch: Sequence[Triplet]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Query [B, L, ...], positive [B, L, ...] and negative [B, K, L, ...] window images of a triplet batch."""
        context, length, device = self.context, self.spec.length, str(self.context.device)
        query_starts = context.query_starts[[t.query for t in batch]]
        positive_starts = context.reference_starts[[t.positive for t in batch]]
        negative_starts = context.reference_starts[np.array([t.negatives for t in batch])]
        negatives = window_frames(negative_starts.reshape(-1), length).reshape(*negative_starts.shape, length)
        return (window_batch(self.store, context.data.query, window_frames(query_starts, length), device),
                window_batch(self.store, context.data.reference, window_frames(positive_starts, length), device),
                window_batch(self.store, context.data.reference, negatives, device))

    def mixed_precision(self, settings: JistTrainSettings) -> bool:
        return settings.amp and str(settings.device).startswith("cuda")

    def validate(self, model: JistModel, data: TrainingData, gt: GroundTruth, settings: JistTrainSettings) -> Evaluation:
        """The pipeline's JIST evaluation: frame descriptors once, SeqGeM windows, faiss top-K, Recall@K."""
        describe = lambda t: describe_with_jist(model, t, settings.width, settings.height, settings.device,  # noqa: E731
                                                self.store, settings.infer_batch, settings.engine, keep=False)
        match = MatchSettings(self.spec, k=max(settings.ks), device=settings.device)
        result = RetrievalMatcher(match, "seqgem", model.sequence_pool).topk(describe(data.val_reference),
                                                                             describe(data.val_query))
        return evaluate_match(result, gt, settings.ks)

    def save_model(self, folder: Path, model: JistModel, metadata: dict[str, Any]) -> None:
        save_jist(folder, model, self.jist, {"image_size": [self.store.width, self.store.height], **metadata})

    def load_weights(self, folder: Path) -> dict[str, torch.Tensor]:
        return read_tensors(Path(folder) / MODEL_FILE)


def frame_size(traversal: Traversal) -> tuple[int, int]:
    """(width, height) of a traversal's first image."""
    from seqvpr.data.images import read_image

    if not traversal.image_paths:
        raise SeqvprError(f"{traversal.source or traversal.name}: JIST trains from images, this traversal holds "
                          f"descriptors only")
    return read_image(traversal.image_paths[0]).size


def jist_setup(values: dict[str, Any], seq_length: int | None = None) -> tuple[JistConfig, JistTrainSettings]:
    """The JistConfig and JistTrainSettings of a flat table of their field values (plus the CosPlace cell's
    ``cell_m`` and ``min_images``); what is not given takes the dataclasses' defaults (the reference's, and the
    backbone's default trainable stages). ``seq-length`` overrides the table's."""
    table = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items() if k != "recipe"}
    grouping = CellGrouping(**{k: table.pop(k) for k in ("cell_m", "min_images") if k in table})
    model_keys = {f.name for f in fields(JistConfig)}
    model = {k: v for k, v in table.items() if k in model_keys}
    if seq_length is not None:
        model["seq_length"] = seq_length
    settings = JistTrainSettings(**{k: v for k, v in table.items() if k not in model_keys}, grouping=grouping)
    return JistConfig(**model), settings


#: the keys ``jist_setup`` takes
JIST_KEYS = frozenset(
    {f.name for f in fields(JistConfig)} | {f.name for f in fields(JistTrainSettings)} | {"cell_m", "min_images"}
) - {"grouping"}
