"""SeqMatchNet training: per-frame transform, sequence triplet loss, sequence-based online hard-negative mining.

One epoch visits the training queries in a seeded random order, in chunks of ``refresh_every`` queries. Before
each chunk the current model transforms every training frame and the miner ranks all reference windows by the
kernel's sequence distance. After each epoch the model is validated on its own split (neither train nor test);
the best one by Recall@K is kept. Every epoch leaves a complete resumable state, so ``resume=True`` continues a
killed run to the same weights as an uninterrupted one (deterministic on CPU for a seed).
"""

from __future__ import annotations

import csv
import io
import json
import math
import shutil
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
import torch

from seqvpr.data.groundtruth import GroundTruth, Radius, ground_truth_within_radius
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.io import atomic_write
from seqvpr.models.seqmatchnet import FrameTransform, TransformConfig
from seqvpr.pipeline import MatchSettings, evaluate_match, match_traversals, transform_traversal
from seqvpr.sequences.windows import SequenceSpec, require_windows, window_starts
from seqvpr.training import checkpoint as ckpt
from seqvpr.training.losses import DEFAULT_MARGIN, SequenceMethod, sequence_triplet_loss, window_part
from seqvpr.training.mining import MiningConfig, SequenceMiner, Triplet, mining_kernel

Optimizer = Literal["sgd", "adam"]


@dataclass(frozen=True)
class TrainSettings:
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
    seed: int = 123
    device: str = "cpu"

    def __post_init__(self) -> None:
        for name in ("refresh_every", "batch_size", "lr_step", "select_k"):
            if getattr(self, name) < 1:
                raise SeqvprError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.epochs < 0:
            raise SeqvprError(f"epochs must be >= 0, got {self.epochs}")
        if self.optimizer not in ("sgd", "adam"):
            raise SeqvprError(f"optimizer must be 'sgd' or 'adam', got {self.optimizer!r}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise SeqvprError(f"learning rate must be a positive number, got {self.lr}")
        window_part(self.loss, self.sequence.length, self.sequence.offset)
        window_part(self.mining, self.sequence.length, self.sequence.offset)

    def as_dict(self) -> dict[str, Any]:
        values = asdict(self)
        values["ks"] = list(self.ks)
        values["sequence"]["velocities"] = list(self.sequence.velocities)
        return values

    def resume_key(self) -> dict[str, Any]:
        """What must not change when a run is resumed (everything but the number of epochs and the device)."""
        return {k: v for k, v in self.as_dict().items() if k not in ("epochs", "device")}


@dataclass(frozen=True)
class TrainingData:
    """Training and validation traversals with their radii (positives, negatives, validation ground truth)."""

    reference: Traversal
    query: Traversal
    val_reference: Traversal
    val_query: Traversal
    positive_radius: Radius
    negative_radius: Radius
    val_radius: Radius

    def __post_init__(self) -> None:
        for name in ("reference", "query", "val_reference", "val_query"):
            traversal = getattr(self, name)
            if traversal.descriptors is None:
                raise SeqvprError(f"{traversal.source or name}: training needs descriptors (describe the images first)")
        dim = self.reference.descriptors.shape[1]
        for name in ("query", "val_reference", "val_query"):
            other = getattr(self, name)
            if other.descriptors.shape[1] != dim:
                raise SeqvprError(
                    f"descriptor dimensions differ: {self.reference.source or 'reference'} has {dim}, "
                    f"{other.source or name} ({name.replace('_', ' ')}) has {other.descriptors.shape[1]}"
                )
        if self.negative_radius.unit != self.positive_radius.unit:
            raise SeqvprError("positive and negative radii must have the same unit (both m or both f)")
        if self.negative_radius.value < self.positive_radius.value:
            raise SeqvprError(
                f"negative radius {self.negative_radius} is smaller than the positive radius {self.positive_radius}"
            )

    @property
    def dim(self) -> int:
        return int(self.reference.descriptors.shape[1])


@dataclass
class EpochRecord:
    """What one epoch did: loss, triplets, skipped queries, time split, validation recall."""

    epoch: int
    loss: float
    triplets: int
    queries_used: int
    queries_skipped: int
    lr: float
    epoch_seconds: float
    mining_seconds: float
    features_seconds: float
    recall: dict[int, float]


@dataclass(frozen=True)
class TrainResult:
    folder: Path
    best_epoch: int
    best_recall: dict[int, float]
    history: list[EpochRecord]


class TrainingMonitor(Protocol):
    """Progress callbacks of a training run (the CLI shows a bar; library callers may pass nothing)."""

    def start_run(self, data: TrainingData, trainable_queries: int) -> None: ...

    def start_epoch(self, epoch: int, epochs: int, queries: int) -> None: ...

    def advance(self, queries: int, loss: float | None) -> None: ...

    def end_epoch(self, record: EpochRecord) -> None: ...


class SilentMonitor:
    def start_run(self, data: TrainingData, trainable_queries: int) -> None:
        pass

    def start_epoch(self, epoch: int, epochs: int, queries: int) -> None:
        pass

    def advance(self, queries: int, loss: float | None) -> None:
        pass

    def end_epoch(self, record: EpochRecord) -> None:
        pass


def train_seqmatchnet(
    data: TrainingData,
    transform: TransformConfig | None = None,
    settings: TrainSettings = TrainSettings(),
    out_dir: str | Path = "seqmatchnet-run",
    *,
    resume: bool = False,
    monitor: TrainingMonitor | None = None,
) -> TrainResult:
    """Train the transform; the best model by validation R@``select_k`` is written to ``out_dir``.

    ``out_dir`` then holds ``model.safetensors`` + ``config.json`` (usable by ``seqvpr match --model``),
    ``history.csv``, and the resumable state of the last finished epoch. ``resume`` continues from that state
    (a run killed before its first state starts over, so ``resume=True`` is always safe to pass).
    """
    out = Path(out_dir)
    monitor = monitor or SilentMonitor()
    transform = transform or TransformConfig(data.dim)
    if transform.in_dim != data.dim:
        raise SeqvprError(f"transform expects {transform.in_dim}-D input but the descriptors are {data.dim}-D")
    run = _Run(data, transform, settings)
    monitor.start_run(data, len(run.trainable))
    history: list[EpochRecord] = []
    best_epoch, best_recall = 0, {}
    if resume and (out / ckpt.STATE_JSON).is_file():
        history, best_epoch, best_recall = run.restore(out)
    elif (out / ckpt.STATE_JSON).exists():
        raise SeqvprError(f"{out}: already holds a training run (use --resume to continue it, or another --out)")
    if not history:
        record = run.validate_record(0)
        history, best_epoch, best_recall = [record], 0, record.recall
        run.save_best(out, 0, best_recall)
        run.save_state(out, history, best_epoch, best_recall)
        monitor.end_epoch(record)
    for epoch in range(len(history), settings.epochs + 1):
        record = run.train_epoch(epoch, monitor)
        history.append(record)
        if record.recall[settings.select_k] > best_recall[settings.select_k]:
            best_epoch, best_recall = epoch, record.recall
            run.save_best(out, epoch, best_recall)
        run.save_state(out, history, best_epoch, best_recall)
        monitor.end_epoch(record)
    return TrainResult(out, best_epoch, best_recall, history)


class _Run:
    """The state of one training run: data on the device, model, optimizer, scheduler, miner."""

    def __init__(self, data: TrainingData, transform: TransformConfig, settings: TrainSettings) -> None:
        if settings.select_k not in settings.ks:
            settings = replace(settings, ks=tuple(sorted({*settings.ks, settings.select_k})))
        self.data, self.transform, self.settings = data, transform, settings
        spec = settings.sequence
        device = torch.device(settings.device)
        self.device = device
        self.query = torch.as_tensor(np.ascontiguousarray(data.query.descriptors), dtype=torch.float32, device=device)
        self.reference = torch.as_tensor(
            np.ascontiguousarray(data.reference.descriptors), dtype=torch.float32, device=device
        )
        self.query_starts = window_starts(data.query.segment_ids, spec.length, spec.offset, spec.boundary)
        self.reference_starts = window_starts(data.reference.segment_ids, spec.length, spec.offset, spec.boundary)
        for name in ("query", "reference", "val_query", "val_reference"):
            traversal = getattr(data, name)
            starts = window_starts(traversal.segment_ids, spec.length, spec.offset, spec.boundary)
            require_windows(starts, spec.length, f"{traversal.source or name} ({name.replace('_', ' ')})",
                            traversal.segment_ids)
        positives = ground_truth_within_radius(data.query, data.reference, data.positive_radius)
        near = ground_truth_within_radius(data.query, data.reference, data.negative_radius)
        self.trainable = np.flatnonzero((self.query_starts >= 0) & positives.has_positive())
        if len(self.trainable) == 0:
            raise SeqvprError(
                f"no training query has both a window of {spec.length} frames and a positive within "
                f"{data.positive_radius}"
            )
        kernel = mining_kernel(settings.mining, spec, data.reference.segment_ids)
        mining = MiningConfig(settings.negatives, settings.negative_pool, settings.margin)
        self.miner = SequenceMiner(kernel, self.query_starts, positives, near, mining)
        self.val_gt = ground_truth_within_radius(data.val_query, data.val_reference, data.val_radius)
        torch.manual_seed(settings.seed)
        self.model = FrameTransform(transform, seed=settings.seed).to(device)
        self.optimizer = _optimizer(self.model, settings)
        self.scheduler = torch.optim.lr_scheduler.StepLR(self.optimizer, settings.lr_step, settings.lr_gamma)
        self.frames = window_part(settings.loss, spec.length, spec.offset)
        self.window = torch.arange(spec.length, device=device)

    # --- one epoch -----------------------------------------------------------------------------------------
    def train_epoch(self, epoch: int, monitor: TrainingMonitor) -> EpochRecord:
        settings = self.settings
        started = time.perf_counter()
        rng = np.random.default_rng([settings.seed, epoch])
        order = rng.permutation(self.trainable)
        monitor.start_epoch(epoch, settings.epochs, len(order))
        losses: list[float] = []
        triplet_count = used = 0
        mining_s = features_s = 0.0
        lr = self.optimizer.param_groups[0]["lr"]
        for begin in range(0, len(order), settings.refresh_every):
            chunk = order[begin : begin + settings.refresh_every]
            tick = time.perf_counter()
            query_feat, reference_feat = self._features()
            features_s += time.perf_counter() - tick
            tick = time.perf_counter()
            triplets = self.miner.mine(query_feat, reference_feat, chunk, rng)
            mining_s += time.perf_counter() - tick
            used += len(triplets)
            for batch_begin in range(0, len(triplets), settings.batch_size):
                batch = triplets[batch_begin : batch_begin + settings.batch_size]
                loss = self._step(batch)
                losses.append(loss)
                triplet_count += sum(len(t.negatives) for t in batch)
                monitor.advance(len(batch), loss)
            monitor.advance(len(chunk) - len(triplets), None)
        self.scheduler.step()
        record = self.validate_record(epoch)
        record.loss = float(np.mean(losses)) if losses else 0.0
        record.triplets, record.queries_used = triplet_count, used
        record.queries_skipped = len(order) - used
        record.lr, record.mining_seconds, record.features_seconds = lr, mining_s, features_s
        record.epoch_seconds = time.perf_counter() - started
        return record

    def _features(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Every training frame through the current model (no gradients), for mining."""
        self.model.eval()
        with torch.no_grad():
            return self.model(self.query), self.model(self.reference)

    def _step(self, batch: Sequence[Triplet]) -> float:
        """One optimiser step on a batch of mined triplet groups; returns the loss."""
        self.model.train()
        device = self.device
        q_rows = torch.as_tensor(self.query_starts[[t.query for t in batch]], device=device)
        p_rows = torch.as_tensor(self.reference_starts[[t.positive for t in batch]], device=device)
        negatives = np.concatenate([t.negatives for t in batch])
        n_rows = torch.as_tensor(self.reference_starts[negatives], device=device)
        owner = torch.as_tensor(np.repeat(np.arange(len(batch)), [len(t.negatives) for t in batch]), device=device)
        q_frames = q_rows[:, None] + self.window
        r_frames = torch.cat([p_rows, n_rows])[:, None] + self.window
        unique, inverse = torch.unique(r_frames, return_inverse=True)
        q_windows = self.model(self.query[q_frames.reshape(-1)]).view(*q_frames.shape, -1)
        r_windows = self.model(self.reference[unique])[inverse]
        loss = sequence_triplet_loss(
            q_windows, r_windows[: len(batch)], r_windows[len(batch) :], owner, self.settings.margin, self.frames
        )
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return float(loss.detach())

    # --- validation ----------------------------------------------------------------------------------------
    def validate_record(self, epoch: int) -> EpochRecord:
        evaluation = self.validate()
        return EpochRecord(epoch, 0.0, 0, 0, 0, self.optimizer.param_groups[0]["lr"], 0.0, 0.0, 0.0, evaluation.recall)

    def validate(self) -> Evaluation:
        return evaluate_transform(
            self.model, self.data.val_reference, self.data.val_query, self.val_gt,
            self.settings.sequence, self.settings.ks, self.settings.device,
        )

    # --- checkpoints ---------------------------------------------------------------------------------------
    def metadata(self, epoch: int, recall: dict[int, float]) -> dict[str, Any]:
        spec = self.settings.sequence
        return {
            "sequence": {"length": spec.length, "align": spec.align, "boundary": spec.boundary},
            "epoch": epoch,
            "validation_recall": {str(k): v for k, v in recall.items()},
            "training": self.settings.as_dict(),
            "data": {
                "reference": self.data.reference.source, "query": self.data.query.source,
                "val_reference": self.data.val_reference.source, "val_query": self.data.val_query.source,
                "positive_radius": str(self.data.positive_radius), "negative_radius": str(self.data.negative_radius),
                "val_radius": str(self.data.val_radius),
            },
        }

    def save_best(self, out: Path, epoch: int, recall: dict[int, float]) -> None:
        ckpt.save_model(out, self.model, self.metadata(epoch, recall))

    def save_state(self, out: Path, history: list[EpochRecord], best_epoch: int, best_recall: dict[int, float]) -> None:
        """A complete state folder for this epoch, then the pointer to it (the commit), then old folders go."""
        epoch = history[-1].epoch
        folder = out / "state" / f"epoch_{epoch:04d}"
        ckpt.save_model(folder, self.model, self.metadata(epoch, history[-1].recall))
        tensors, rest = ckpt.flatten_optimizer(self.optimizer.state_dict())
        tensors["miner.cache"] = torch.as_tensor(self.miner.cache_array(len(self.data.query)))
        ckpt.save_tensors(folder / ckpt.STATE_FILE, tensors)
        _write_history(out / "history.csv", history)
        ckpt.save_json(out / ckpt.STATE_JSON, {
            "state_dir": str(folder.relative_to(out)),
            "settings": self.settings.resume_key(),
            "transform": self.transform.as_dict(),
            "optimizer": rest,
            "scheduler": self.scheduler.state_dict(),
            "best_epoch": best_epoch,
            "best_recall": {str(k): v for k, v in best_recall.items()},
            "history": [asdict(r) for r in history],
        })
        for old in (out / "state").iterdir():
            if old != folder:
                shutil.rmtree(old, ignore_errors=True)

    def restore(self, out: Path) -> tuple[list[EpochRecord], int, dict[int, float]]:
        """Load the last finished epoch's state; the run's settings must match the saved ones."""
        state = ckpt.read_json(out / ckpt.STATE_JSON)
        _check_same(state["settings"], self.settings.resume_key(), out / ckpt.STATE_JSON)
        _check_same(state["transform"], self.transform.as_dict(), out / ckpt.STATE_JSON)
        folder = out / state["state_dir"]
        model, _ = ckpt.load_model(folder)
        self.model.load_state_dict(model.state_dict())
        tensors = ckpt.read_tensors(folder / ckpt.STATE_FILE)
        self.optimizer.load_state_dict(ckpt.unflatten_optimizer(tensors, state["optimizer"]))
        self.scheduler.load_state_dict(state["scheduler"])
        self.miner.load_cache(tensors["miner.cache"].numpy())
        history = [_record_from_dict(r) for r in state["history"]]
        best = {int(k): float(v) for k, v in state["best_recall"].items()}
        return history, int(state["best_epoch"]), best


def evaluate_transform(
    model: FrameTransform,
    reference: Traversal,
    query: Traversal,
    gt: GroundTruth,
    spec: SequenceSpec,
    ks: Sequence[int],
    device: str = "cpu",
) -> Evaluation:
    """Recall@K of sequence matching over transformed descriptors (the core kernel, top-K)."""
    ref, qry = transform_traversal(reference, model, device), transform_traversal(query, model, device)
    settings = MatchSettings(spec, k=max(ks), device=device)
    return evaluate_match(match_traversals(ref, qry, settings), gt, ks)


def _optimizer(model: FrameTransform, settings: TrainSettings) -> torch.optim.Optimizer:
    if settings.optimizer == "sgd":
        return torch.optim.SGD(
            model.parameters(), lr=settings.lr, momentum=settings.momentum, weight_decay=settings.weight_decay
        )
    return torch.optim.Adam(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)


def _check_same(saved: dict, current: dict, path: Path) -> None:
    """Resuming with other settings would not continue the same run: name the first differing field."""
    current = _jsonable(current)
    for key in sorted(set(saved) | set(current)):
        if saved.get(key) != current.get(key):
            raise SeqvprError(
                f"{path}: cannot resume with {key}={current.get(key)!r}; the run was started with {saved.get(key)!r}"
            )


def _jsonable(values: dict) -> dict:
    return json.loads(json.dumps(values, default=str))


def _record_from_dict(values: dict) -> EpochRecord:
    values = dict(values)
    values["recall"] = {int(k): float(v) for k, v in values["recall"].items()}
    return EpochRecord(**values)


def _write_history(path: Path, history: list[EpochRecord]) -> None:
    """One CSV row per epoch (epoch 0 is the untrained model)."""
    ks = sorted(history[0].recall)
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["epoch", "loss", "triplets", "queries_used", "queries_skipped", "lr", "epoch_s", "mining_s",
                     "features_s", *[f"val_R@{k}" for k in ks]])
    for r in history:
        writer.writerow([r.epoch, f"{r.loss:.6f}", r.triplets, r.queries_used, r.queries_skipped, f"{r.lr:.3g}",
                         f"{r.epoch_seconds:.3f}", f"{r.mining_seconds:.3f}", f"{r.features_seconds:.3f}",
                         *[f"{r.recall[k]:.4f}" for k in ks]])
    with atomic_write(path) as handle:
        handle.write(buffer.getvalue())
