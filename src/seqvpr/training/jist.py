"""JIST training: a frame encoder + SeqGeM trained jointly on sequence triplets and CosPlace classification.

Per iteration (digest section 3.7): one batch of mined sequence triplets (query window, nearest positive
reference window, K hardest negatives outside the negative radius) and one class-balanced batch of single images
from ONE CosPlace group, each group with its own CosFace head (created on first use). The loss is
``jist_losses(...)["total"]``; one Adam optimiser with a model group (``config.lr``) and one group per head
(``config.classifier_lr``). Mining is refreshed ``refreshes`` times per epoch (the reference's sub-epochs): the
needed frames are encoded once (no grad), windows are pooled from those frame descriptors with ``model.pool``.
After each epoch the model is validated on its own pair (frame descriptors once, pooled, faiss retrieval,
Recall@K); the best epoch's weights are written to ``out_dir`` (``model.safetensors``, ``config.json``,
``history.csv``), each file atomically.
"""

from __future__ import annotations

import copy
import csv
import io
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from seqvpr.data.groundtruth import Radius, ground_truth_within_radius
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation, evaluate
from seqvpr.features.extraction import load_image
from seqvpr.io import atomic_write
from seqvpr.models.jist import JistConfig, JistModel, build_jist, jist_losses, make_classifier, optimizer_groups
from seqvpr.sequences.descriptors import SequenceDescriptors
from seqvpr.sequences.retrieval import retrieve
from seqvpr.sequences.windows import SequenceSpec, require_windows, window_starts
from seqvpr.training import checkpoint as ckpt
from seqvpr.training.cosplace import CellGrouping, CosFaceHead, assign_classes, group_members

FORMAT = "seqvpr-jist"
HISTORY_FILE = "history.csv"


@dataclass(frozen=True)
class JistTrainSettings:
    """Schedule, batches, mining and runtime of a JIST run. Reference values (digest 3.2, 3.6, 3.7): 5 epochs x 10
    refreshes, 1000 queries / 3000 pool windows per refresh, 4 triplets x 5 negatives, 64 classification images,
    groups rotated per epoch, AMP. ``max_iterations`` caps the iterations of one refresh (None: all triplets)."""

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
    select_k: int = 5
    ks: tuple[int, ...] = (1, 5, 10)
    infer_batch: int = 32
    device: str = "cpu"
    amp: bool = True
    cache_images: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("epochs", "refreshes", "queries_per_refresh", "negative_pool", "batch_size", "negatives",
                     "images_per_batch", "width", "height", "select_k", "infer_batch"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise SeqvprError(f"{name} must be a positive integer, got {value}")
        if self.max_iterations is not None and (int(self.max_iterations) != self.max_iterations or self.max_iterations < 1):
            raise SeqvprError(f"max_iterations must be a positive integer or None, got {self.max_iterations}")
        if self.group_per not in ("iteration", "epoch"):
            raise SeqvprError(f"group_per must be 'iteration' or 'epoch', got {self.group_per!r}")
        if self.select_k not in self.ks:
            raise SeqvprError(f"select_k={self.select_k} must be one of the recall ks {self.ks}")


@dataclass(frozen=True)
class JistData:
    """Train and validation traversals (image paths + positions) and the radii of digest 3.5: positives within
    ``positive_radius`` m, negatives outside ``negative_radius`` m, validation positives within ``val_radius`` m.
    ``classification`` defaults to the train reference (positions and headings give the CosPlace classes)."""

    train_reference: Traversal
    train_query: Traversal
    val_reference: Traversal
    val_query: Traversal
    positive_radius: float = 10.0
    negative_radius: float = 25.0
    val_radius: float = 25.0
    classification: Traversal | None = None

    def __post_init__(self) -> None:
        for name in ("train_reference", "train_query", "val_reference", "val_query", "classification"):
            traversal = getattr(self, name)
            if traversal is None:
                continue
            label = traversal.source or traversal.name
            if traversal.image_paths is None:
                raise SeqvprError(f"{name} ({label}): JIST training needs image paths")
            if traversal.positions is None:
                raise SeqvprError(f"{name} ({label}): JIST training needs positions (metres)")
        if not (0 < self.positive_radius <= self.negative_radius) or self.val_radius <= 0:
            raise SeqvprError(
                f"radii must satisfy 0 < positive ({self.positive_radius}) <= negative ({self.negative_radius}) "
                f"and val ({self.val_radius}) > 0"
            )

    @property
    def images(self) -> Traversal:
        """The traversal whose single images feed the classification branch."""
        return self.classification if self.classification is not None else self.train_reference


@dataclass(frozen=True)
class ImageWindows:
    """Windows of one traversal: frame rows [n_windows, L] and the frame each window belongs to (its row)."""

    frames: np.ndarray
    rows: np.ndarray

    def paths(self, traversal: Traversal) -> list[tuple[Path, ...]]:
        """The image paths of every window."""
        return [tuple(traversal.image_paths[i] for i in window) for window in self.frames]


@dataclass(frozen=True)
class Triplet:
    """Window indices (into ImageWindows) of one query, its positive and its K negatives."""

    query: int
    positive: int
    negatives: tuple[int, ...]


@dataclass
class JistResult:
    """The best model, its epoch and validation recall, the per-epoch history and every iteration's losses."""

    model: JistModel
    best_epoch: int
    best_recall: dict[int, float]
    history: list[dict[str, Any]]
    iteration_losses: list[dict[str, float]]
    out_dir: Path


class JistMonitor(Protocol):
    """Progress callbacks (None: silent)."""

    def iteration(self, epoch: int, losses: dict[str, float]) -> None: ...

    def epoch(self, record: dict[str, Any]) -> None: ...


def image_windows(traversal: Traversal, spec: SequenceSpec) -> ImageWindows:
    """Windows of the traversal's frames under the core window rules (never across a segment break)."""
    starts = window_starts(np.asarray(traversal.segment_ids), spec.length, spec.offset, spec.boundary)
    require_windows(starts, spec.length, traversal.source or traversal.name, traversal.segment_ids)
    rows = np.flatnonzero(starts >= 0)
    frames = starts[rows][:, None] + np.arange(spec.length, dtype=np.int64)[None, :]
    return ImageWindows(frames, rows)


def training_spec(length: int) -> SequenceSpec:
    """JIST's windows (digest 3.4): centred, stride 1, windows that would leave the segment are dropped."""
    return SequenceSpec(length, "centered", "drop")


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


def check_images_exist(traversal: Traversal, what: str) -> None:
    """Fail with one line before training when an image of the traversal is missing."""
    for path in traversal.image_paths:
        if not Path(path).is_file():
            raise SeqvprError(f"{what}: image {path} does not exist")


@torch.no_grad()
def encode_frames(
    model: JistModel, store: ImageStore, paths: Sequence[Path], device: str, batch: int = 32
) -> torch.Tensor:
    """Frame descriptors [N, D] of the images (eval mode, no grad), each image encoded once."""
    was_training = model.training
    model.eval()
    try:
        parts = [model.frames(store.batch(paths[i : i + batch], device)) for i in range(0, len(paths), batch)]
    finally:
        model.train(was_training)
    return torch.cat(parts).float()


@torch.no_grad()
def pool_windows(model: JistModel, frame_descriptors: torch.Tensor, frames: np.ndarray) -> torch.Tensor:
    """Sequence descriptors [n_windows, D] pooled from frame descriptors [N, D] (rows ``frames`` [n, L])."""
    index = torch.as_tensor(frames, device=frame_descriptors.device)
    was_training = model.training
    model.eval()
    try:
        return model.pool(frame_descriptors[index.reshape(-1)].view(*frames.shape, -1)).float()
    finally:
        model.train(was_training)


def window_descriptors(
    model: JistModel, store: ImageStore, traversal: Traversal, frames: np.ndarray, device: str, batch: int = 32
) -> torch.Tensor:
    """Descriptors of the given windows (rows [n, L] of the traversal): only the frames they use are encoded."""
    used, inverse = np.unique(frames.reshape(-1), return_inverse=True)
    descriptors = encode_frames(model, store, [traversal.image_paths[i] for i in used], device, batch)
    return pool_windows(model, descriptors, inverse.reshape(frames.shape))


def select_triplets(
    query_desc: torch.Tensor,
    reference_desc: torch.Tensor,
    positives: Sequence[np.ndarray],
    non_negatives: Sequence[np.ndarray],
    pool: np.ndarray,
    negatives: int,
) -> list[tuple[int, int, tuple[int, ...]]]:
    """Per query: the positive (among ``positives[q]``) nearest in descriptor space and the ``negatives`` nearest
    pool windows that are not in ``non_negatives[q]`` (digest 3.6); queries lacking either are skipped.
    Returns (query position, reference window, negative windows) with window indices into ``reference_desc``."""
    out = []
    pool = np.asarray(pool, dtype=np.int64)
    pool_desc = reference_desc[torch.as_tensor(pool, device=reference_desc.device)]
    for q, (pos, near) in enumerate(zip(positives, non_negatives)):
        if len(pos) == 0:
            continue
        candidates = ~np.isin(pool, near)
        if candidates.sum() < negatives:
            continue
        d_pos = torch.cdist(query_desc[q : q + 1], reference_desc[torch.as_tensor(pos, device=reference_desc.device)])[0]
        best = int(pos[int(torch.argmin(d_pos))])
        d_neg = torch.cdist(query_desc[q : q + 1], pool_desc)[0].double().cpu().numpy()
        d_neg[~candidates] = np.inf
        order = np.argsort(d_neg, kind="stable")[:negatives]
        out.append((q, best, tuple(int(pool[i]) for i in order)))
    return out


def mine_triplets(
    model: JistModel,
    data: JistData,
    query_windows: ImageWindows,
    reference_windows: ImageWindows,
    settings: JistTrainSettings,
    rng: np.random.Generator,
    store: ImageStore,
) -> list[Triplet]:
    """One refresh of digest 3.6: sample query windows that have positives and a pool of reference windows, encode
    the frames they (and all the queries' positives) use once, pool windows, then ``select_triplets``. Window
    positions are their own (anchor) frame's positions. Seeded by ``rng``."""
    anchors_ref = data.train_reference.select(reference_windows.rows)
    anchors_qry = data.train_query.select(query_windows.rows)
    near = ground_truth_within_radius(anchors_qry, anchors_ref, Radius(float(data.positive_radius), "m"))
    not_negative = ground_truth_within_radius(anchors_qry, anchors_ref, Radius(float(data.negative_radius), "m"))
    eligible = np.flatnonzero(near.has_positive())
    if len(eligible) == 0:
        raise SeqvprError(f"no training query window has a reference window within {data.positive_radius:g} m")
    queries = np.sort(rng.choice(eligible, size=min(settings.queries_per_refresh, len(eligible)), replace=False))
    n_ref = len(reference_windows.rows)
    pool = np.sort(rng.choice(n_ref, size=min(settings.negative_pool, n_ref), replace=False))
    positives = [near.positives_of(int(q)) for q in queries]
    non_negatives = [not_negative.positives_of(int(q)) for q in queries]
    needed = np.unique(np.concatenate([pool, *positives]))
    ref_desc = torch.zeros(n_ref, model.dim, device=settings.device)
    ref_desc[torch.as_tensor(needed, device=settings.device)] = window_descriptors(
        model, store, data.train_reference, reference_windows.frames[needed], settings.device, settings.infer_batch
    )
    q_desc = window_descriptors(
        model, store, data.train_query, query_windows.frames[queries], settings.device, settings.infer_batch
    )
    chosen = select_triplets(q_desc, ref_desc, positives, non_negatives, pool, settings.negatives)
    return [Triplet(int(queries[q]), p, n) for q, p, n in chosen]


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


def triplet_tensors(
    store: ImageStore, data: JistData, qw: ImageWindows, rw: ImageWindows, batch: Sequence[Triplet], device: str
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Query [B, L, ...], positive [B, L, ...] and negative [B, K, L, ...] window images of a triplet batch."""
    q = window_batch(store, data.train_query, qw.frames[[t.query for t in batch]], device)
    p = window_batch(store, data.train_reference, rw.frames[[t.positive for t in batch]], device)
    n = window_batch(store, data.train_reference, rw.frames[np.array([t.negatives for t in batch])], device)
    return q, p, n


def evaluate_jist(
    model: JistModel,
    reference: Traversal,
    query: Traversal,
    *,
    seq_length: int,
    radius: float = 25.0,
    ks: Sequence[int] = (1, 5, 10),
    shuffle_frames: bool = False,
    store: ImageStore | None = None,
    width: int = 640,
    height: int = 480,
    device: str = "cpu",
    seed: int = 0,
) -> Evaluation:
    """Recall@K of sequence retrieval: frame descriptors of each traversal computed once, pooled into windows of
    ``seq_length`` (any length, not only the trained one), optionally with the frame order shuffled inside every
    window (seeded), faiss L2 top-K, positives within ``radius`` m of the query window's frame."""
    store = store or ImageStore(width, height)
    spec = training_spec(seq_length)
    generator = torch.Generator().manual_seed(seed)
    described = []
    for traversal in (reference, query):
        windows = image_windows(traversal, spec)
        frames = windows.frames
        if shuffle_frames:
            order = torch.argsort(torch.rand(frames.shape, generator=generator), dim=1).numpy()
            frames = np.take_along_axis(frames, order, axis=1)
        descriptors = encode_frames(model, store, list(traversal.image_paths), device)
        vectors = pool_windows(model, descriptors, frames).cpu().numpy().astype(np.float32)
        described.append(SequenceDescriptors(vectors, windows.rows, len(traversal)))
    top = retrieve(described[1], described[0], max(ks))
    gt = ground_truth_within_radius(query, reference, Radius(float(radius), "m"))
    return evaluate(top.indices, top.distances, top.has_window, gt, tuple(ks))


def frame_positions(traversal: Traversal, spacing: float = 1.0) -> Traversal:
    """The traversal with along-route positions (``frame_index * spacing``, 0) and heading 0, for frame-aligned
    datasets (Nordland): JIST's radii and CosPlace cells are then counted in frames (times ``spacing``)."""
    from dataclasses import replace

    if traversal.positions is not None:
        return traversal
    east = traversal.frame_index.astype(np.float64) * float(spacing)
    return replace(traversal, positions=np.stack([east, np.zeros_like(east)], axis=1),
                   headings=np.zeros(len(traversal)))


def jist_positions(traversal: Traversal, radius: Radius) -> Traversal:
    """A traversal JIST can train on at this radius unit: images with positions in metres, or, with a frame
    radius, frame-aligned images placed along the route one unit per frame (``frame_positions``)."""
    label = traversal.source or traversal.name
    if traversal.image_paths is None:
        raise SeqvprError(f"{label}: JIST trains from images, this traversal holds descriptors only")
    if radius.unit == "m":
        if traversal.positions is None:
            raise SeqvprError(f"{label}: no positions for a radius in metres; frame-aligned data takes a frame "
                              f"radius, e.g. --radius 1f")
        return traversal
    if traversal.positions is not None:
        raise SeqvprError(f"--radius {radius}: {label} has positions; give the radius in metres, e.g. 25m "
                          f"(a frame radius is for frame-aligned traversals without positions)")
    return frame_positions(traversal)


def describe_with_jist(
    model: JistModel, traversal: Traversal, width: int, height: int, device: str = "cpu",
    store: ImageStore | None = None, batch: int = 32,
) -> Traversal:
    """The traversal with JIST frame descriptors (its encoder, images at ``width`` x ``height``); pooling them with
    ``model.sequence_pool`` (e.g. ``retrieve_traversals(..., "seqgem", model=model.sequence_pool)``) gives JIST's
    sequence descriptors."""
    if traversal.image_paths is None:
        raise SeqvprError(f"{traversal.source or traversal.name}: JIST needs images, this traversal has descriptors only")
    check_images_exist(traversal, traversal.source or traversal.name)
    store = store or ImageStore(width, height)
    return traversal.with_descriptors(encode_frames(model, store, list(traversal.image_paths), device, batch).cpu().numpy())


def _autocast(settings: JistTrainSettings):
    """Mixed precision on CUDA only when asked; a no-op context elsewhere."""
    enabled = settings.amp and str(settings.device).startswith("cuda")
    return torch.autocast("cuda", dtype=torch.float16, enabled=enabled) if enabled else torch.autocast("cpu", enabled=False)


def _group_of(groups: list[int], epoch: int, iteration: int, settings: JistTrainSettings) -> int:
    """The group of this iteration: rotated per iteration, or per epoch as the reference (digest 3.7)."""
    step = iteration if settings.group_per == "iteration" else epoch
    return groups[step % len(groups)]


def _head_for(
    heads: dict[int, CosFaceHead], group: int, n_classes: int, config: JistConfig,
    optimizer: torch.optim.Optimizer, device: str,
) -> CosFaceHead:
    """The group's CosFace head, created (and added to the optimiser at the classifier lr) on first use."""
    if group not in heads:
        heads[group] = make_classifier(config, n_classes).to(device)
        optimizer.add_param_group({"params": list(heads[group].parameters()), "lr": config.classifier_lr})
    return heads[group]


def train_step(
    model: JistModel, head: CosFaceHead, tensors: tuple[torch.Tensor, ...], labels: torch.Tensor,
    config: JistConfig, optimizer: torch.optim.Optimizer, scaler: torch.amp.GradScaler | None,
    settings: JistTrainSettings,
) -> dict[str, float]:
    """One joint step: ``jist_losses`` total, backward, one optimiser step for the model and the head."""
    optimizer.zero_grad(set_to_none=True)
    with _autocast(settings):
        losses = jist_losses(model, head, *tensors, labels, config)
    if scaler is not None:
        scaler.scale(losses["total"]).backward()
        scaler.step(optimizer)
        scaler.update()
    else:
        losses["total"].backward()
        optimizer.step()
    return {name: float(value.detach()) for name, value in losses.items()}


def _history_csv(history: list[dict[str, Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(history[0]))
    writer.writeheader()
    writer.writerows(history)
    return buffer.getvalue()


def save_jist(
    out_dir: Path, model: JistModel, config: JistConfig, settings: JistTrainSettings, extra: dict[str, Any]
) -> None:
    """Write ``model.safetensors`` and ``config.json`` (config, settings, pool, ``extra``), each atomically."""
    pool = model.sequence_pool
    meta = {
        "format": FORMAT,
        "config": asdict(config),
        "settings": asdict(settings),
        "sequence_pool": {"type": type(pool).__name__, "mode": getattr(pool, "mode", None), "eps": getattr(pool, "eps", None)},
        **extra,
    }
    ckpt.save_tensors(out_dir / ckpt.MODEL_FILE, model.state_dict())
    ckpt.save_json(out_dir / ckpt.CONFIG_FILE, meta)


def load_jist(folder: str | Path, *, backbone: torch.nn.Module | None = None) -> JistModel:
    """The JIST model saved by ``train_jist`` (eval mode); ``backbone`` re-injects a custom backbone."""
    folder = Path(folder)
    meta = ckpt.read_json(folder / ckpt.CONFIG_FILE)
    if meta.get("format") != FORMAT:
        raise SeqvprError(f"{folder}: not a JIST model folder (format {meta.get('format')!r})")
    values = dict(meta["config"], weights=None)
    values["trainable_stages"] = tuple(values["trainable_stages"])
    config = JistConfig(**values)
    from seqvpr.sequences.descriptors import SeqGeM

    pool_meta = meta.get("sequence_pool") or {}
    pool = SeqGeM(mode=pool_meta.get("mode") or "clamp", eps=pool_meta.get("eps") or 1e-6)
    model = build_jist(config, pool, backbone=backbone)
    state = ckpt.read_tensors(folder / ckpt.MODEL_FILE)
    try:
        model.load_state_dict(state)
    except RuntimeError as error:
        raise SeqvprError(f"{folder}: weights do not fit the saved config ({str(error).splitlines()[0]})") from None
    return model.eval()


def load_finished_jist(out_dir: str | Path, config: JistConfig, settings: JistTrainSettings) -> JistModel | None:
    """The best model of a run in ``out_dir`` that finished every epoch with this config and these settings, or
    None (no run, another run, or an unfinished one): lets a re-run skip training."""
    import json

    out_dir = Path(out_dir)
    try:
        meta = ckpt.read_json(out_dir / ckpt.CONFIG_FILE)
        epochs = (out_dir / HISTORY_FILE).read_text(encoding="utf-8").count("\n") - 1
    except (OSError, SeqvprError):
        return None
    same = json.loads(json.dumps({"config": asdict(config), "settings": asdict(settings)}))
    if meta.get("format") != FORMAT or epochs != settings.epochs or {k: meta.get(k) for k in same} != same:
        return None
    return load_jist(out_dir)


def _check_data(data: JistData) -> None:
    for name in ("train_reference", "train_query", "val_reference", "val_query"):
        check_images_exist(getattr(data, name), name)
    if data.classification is not None:
        check_images_exist(data.classification, "classification")


def train_jist(
    data: JistData,
    config: JistConfig,
    settings: JistTrainSettings,
    out_dir: str | Path,
    *,
    monitor: JistMonitor | None = None,
    backbone_factory: Callable[[], torch.nn.Module] | None = None,
) -> JistResult:
    """Train JIST jointly (see the module docstring); keeps and writes the best epoch by validation R@select_k.
    ``backbone_factory`` builds an injected backbone (tests); the model is built after seeding, so runs with
    the same seed are identical on CPU."""
    _check_data(data)
    out_dir = Path(out_dir)
    device = settings.device
    torch.manual_seed(settings.seed)
    model = build_jist(config, backbone=backbone_factory() if backbone_factory else None).to(device)
    store = ImageStore(settings.width, settings.height, settings.cache_images)
    spec = training_spec(config.seq_length)
    qw, rw = image_windows(data.train_query, spec), image_windows(data.train_reference, spec)
    images = data.images
    class_ids, group_ids = assign_classes(images.positions, images.headings, settings.grouping)
    groups = used_groups(group_ids)
    optimizer = torch.optim.Adam(optimizer_groups(model, [], config)[:1])
    use_amp = settings.amp and str(device).startswith("cuda")
    scaler = torch.amp.GradScaler("cuda") if use_amp else None
    heads: dict[int, CosFaceHead] = {}
    history: list[dict[str, Any]] = []
    losses_log: list[dict[str, float]] = []
    best_state, best_epoch, best_recall = None, -1, {}
    iteration = 0
    for epoch in range(settings.epochs):
        started = time.perf_counter()
        rng = np.random.default_rng([settings.seed, epoch])
        epoch_losses: list[dict[str, float]] = []
        for _ in range(settings.refreshes):
            triplets = mine_triplets(model, data, qw, rw, settings, rng, store)
            n_batches = len(triplets) // settings.batch_size
            if settings.max_iterations is not None:
                n_batches = min(n_batches, settings.max_iterations)
            if n_batches == 0:
                raise SeqvprError(
                    f"only {len(triplets)} triplets were mined, fewer than one batch of {settings.batch_size}"
                )
            model.train()
            for b in range(n_batches):
                batch = triplets[b * settings.batch_size : (b + 1) * settings.batch_size]
                group = _group_of(groups, epoch, iteration, settings)
                rows, labels, n_classes = classification_batch(
                    class_ids, group_ids, group, settings.images_per_batch, rng
                )
                head = _head_for(heads, group, n_classes, config, optimizer, device)
                head.train()
                tensors = (
                    *triplet_tensors(store, data, qw, rw, batch, device),
                    store.batch([images.image_paths[i] for i in rows], device),
                )
                label_tensor = torch.as_tensor(labels, device=device)
                losses = train_step(model, head, tensors, label_tensor, config, optimizer, scaler, settings)
                losses_log.append(losses)
                epoch_losses.append(losses)
                iteration += 1
                if monitor is not None:
                    monitor.iteration(epoch, losses)
        model.eval()
        evaluation = evaluate_jist(
            model, data.val_reference, data.val_query, seq_length=config.seq_length, radius=data.val_radius,
            ks=settings.ks, store=store, device=device,
        )
        record = {
            "epoch": epoch,
            "iterations": len(epoch_losses),
            "loss": float(np.mean([l["total"] for l in epoch_losses])),
            "sequence_loss": float(np.mean([l["sequence"] for l in epoch_losses])),
            "image_loss": float(np.mean([l["images"] for l in epoch_losses])),
            **{f"recall@{k}": float(v) for k, v in evaluation.recall.items()},
            "seconds": round(time.perf_counter() - started, 3),
        }
        history.append(record)
        if monitor is not None:
            monitor.epoch(record)
        if best_state is None or evaluation.recall[settings.select_k] > best_recall[settings.select_k]:
            best_state = copy.deepcopy(model.state_dict())
            best_epoch, best_recall = epoch, dict(evaluation.recall)
            save_jist(out_dir, model, config, settings, {
                "best_epoch": best_epoch,
                "validation_recall": {str(k): v for k, v in best_recall.items()},
                "image_size": [settings.width, settings.height],
            })
        with atomic_write(out_dir / HISTORY_FILE) as handle:
            handle.write(_history_csv(history))
    model.load_state_dict(best_state)
    return JistResult(model.eval(), best_epoch, best_recall, history, losses_log, out_dir)
