"""The model-agnostic sequence training loop, shared by SeqMatchNet and SeqNet (one adapter each).

One epoch visits the trainable queries (a window and a positive) in a seeded random order, in chunks of
``refresh_every`` queries. Before each chunk the adapter computes mining features of every training frame with the
current model (no gradients) and the injected ``SequenceMiner`` ranks all reference windows with the adapter's
``DistanceRows`` kernel. Batches of mined triplets go through the adapter's loss, one optimiser step each
(SGD or Adam, StepLR per epoch). After each epoch the adapter validates the model on its own split; the best
epoch by validation Recall@``select_k`` is saved to ``out_dir``. Every epoch leaves a complete resumable state
(model, optimizer, scheduler, miner cache, history), committed by an atomically written pointer
(``train_state.json``), so a killed run resumed with the same settings reaches the same weights.

What differs between models lives behind ``SequenceLearner``: building the model, its input frames, the mining
features and kernel, the loss of a batch of triplets, validation, and the model folder + its config.
"""

from __future__ import annotations

import csv
import io
import json
import math
import shutil
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn

from seqvpr.data.groundtruth import GroundTruth, Radius, ground_truth_within_radius
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.io import atomic_write
from seqvpr.sequences.windows import SequenceSpec, require_windows, window_starts
from seqvpr.training import checkpoint as ckpt
from seqvpr.training.mining import DistanceRows, MiningConfig, SequenceMiner, Triplet


class SettingsRecord:
    """What every training-settings dataclass shares: a JSON-ready dict, and the part a resume must match."""

    def as_dict(self) -> dict[str, Any]:
        values = asdict(self)  # type: ignore[call-overload]
        values["ks"] = list(self.ks)  # type: ignore[attr-defined]
        values["sequence"]["velocities"] = list(self.sequence.velocities)  # type: ignore[attr-defined]
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


class LoopSettings(Protocol):
    """The fields of a (frozen dataclass) settings object the loop reads; each model's settings class has them."""

    sequence: SequenceSpec
    margin: float
    negatives: int
    negative_pool: int | None
    refresh_every: int | None  # None: mine once per epoch
    batch_size: int
    epochs: int
    optimizer: str
    lr: float
    momentum: float
    weight_decay: float
    lr_step: int
    lr_gamma: float
    select_k: int
    ks: tuple[int, ...]
    seed: int
    device: str

    def as_dict(self) -> dict[str, Any]: ...

    def resume_key(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class TrainingFrames:
    """The training frames on the device as the adapter prepared them, with every frame's window start (-1: none)."""

    query: torch.Tensor
    reference: torch.Tensor
    query_starts: np.ndarray
    reference_starts: np.ndarray
    window: torch.Tensor  # arange(L) on the device
    device: torch.device

    def query_windows(self, rows: np.ndarray) -> torch.Tensor:
        """Frame rows [n, L] of the windows of query rows ``rows``."""
        return torch.as_tensor(self.query_starts[rows], device=self.device)[:, None] + self.window

    def reference_windows(self, rows: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(self.reference_starts[rows], device=self.device)[:, None] + self.window


class SequenceLearner(Protocol):
    """The model-specific parts of a sequence training run (SeqMatchNet, SeqNet)."""

    #: key of the model config in ``train_state.json`` (checked on resume)
    config_key: str

    def config(self) -> dict[str, Any]:
        """The model config that must match when a run is resumed (JSON-able)."""
        ...

    def build_model(self, settings: LoopSettings) -> nn.Module:
        """A fresh model (called right after ``torch.manual_seed(settings.seed)``; the loop moves it to the device)."""
        ...

    def input_frames(self, descriptors: np.ndarray, device: torch.device) -> torch.Tensor:
        """A traversal's frame descriptors as the model's training input on ``device``."""
        ...

    def mining_kernel(self, data: TrainingData, frames: TrainingFrames, settings: LoopSettings) -> DistanceRows:
        """The miner's kernel over ``mining_features`` outputs."""
        ...

    def mining_features(self, model: nn.Module, frames: TrainingFrames) -> tuple[torch.Tensor, torch.Tensor]:
        """Query and reference features for the kernel (called in eval mode under ``torch.no_grad``)."""
        ...

    def batch_loss(
        self, model: nn.Module, frames: TrainingFrames, batch: Sequence[Triplet], settings: LoopSettings
    ) -> torch.Tensor:
        """The differentiable loss of a batch of mined triplet groups (model in train mode)."""
        ...

    def validate(self, model: nn.Module, data: TrainingData, gt: GroundTruth, settings: LoopSettings) -> Evaluation:
        """Recall@``settings.ks`` on the validation traversals."""
        ...

    def save_model(self, folder: Path, model: nn.Module, metadata: dict[str, Any]) -> None:
        """Write the model folder (weights + config with ``metadata``)."""
        ...

    def load_weights(self, folder: Path) -> dict[str, torch.Tensor]:
        """The state dict saved by ``save_model`` in ``folder``."""
        ...


def train_sequence_model(
    data: TrainingData,
    learner: SequenceLearner,
    settings: LoopSettings,
    out_dir: str | Path,
    *,
    resume: bool = False,
    monitor: TrainingMonitor | None = None,
) -> TrainResult:
    """Train ``learner``'s model; the best one by validation R@``select_k`` is written to ``out_dir``.

    ``out_dir`` then holds the model folder files, ``history.csv``, and the resumable state of the last finished
    epoch. ``resume`` continues from that state (a run killed before its first state starts over, so
    ``resume=True`` is always safe to pass).
    """
    out = Path(out_dir)
    monitor = monitor or SilentMonitor()
    run = _Run(data, learner, settings)
    settings = run.settings
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


def check_optimizer_settings(settings: LoopSettings) -> None:
    """The loop's own checks of a settings object (each settings class calls this from ``__post_init__``)."""
    for name in ("refresh_every", "batch_size", "lr_step", "select_k"):
        if getattr(settings, name) is not None and getattr(settings, name) < 1:
            raise SeqvprError(f"{name} must be >= 1, got {getattr(settings, name)}")
    if settings.epochs < 0:
        raise SeqvprError(f"epochs must be >= 0, got {settings.epochs}")
    if settings.optimizer not in ("sgd", "adam"):
        raise SeqvprError(f"optimizer must be 'sgd' or 'adam', got {settings.optimizer!r}")
    if not (settings.lr > 0 and math.isfinite(settings.lr)):
        raise SeqvprError(f"learning rate must be a positive number, got {settings.lr}")


class _Run:
    """The state of one training run: data on the device, model, optimizer, scheduler, miner."""

    def __init__(self, data: TrainingData, learner: SequenceLearner, settings: LoopSettings) -> None:
        if settings.select_k not in settings.ks:
            settings = replace(settings, ks=tuple(sorted({*settings.ks, settings.select_k})))  # type: ignore[type-var]
        self.data, self.learner, self.settings = data, learner, settings
        spec = settings.sequence
        device = torch.device(settings.device)
        self.device = device
        for name in ("query", "reference", "val_query", "val_reference"):
            traversal = getattr(data, name)
            starts = window_starts(traversal.segment_ids, spec.length, spec.offset, spec.boundary)
            require_windows(starts, spec.length, f"{traversal.source or name} ({name.replace('_', ' ')})",
                            traversal.segment_ids)
        self.frames = TrainingFrames(
            learner.input_frames(data.query.descriptors, device),
            learner.input_frames(data.reference.descriptors, device),
            window_starts(data.query.segment_ids, spec.length, spec.offset, spec.boundary),
            window_starts(data.reference.segment_ids, spec.length, spec.offset, spec.boundary),
            torch.arange(spec.length, device=device),
            device,
        )
        positives = ground_truth_within_radius(data.query, data.reference, data.positive_radius)
        near = ground_truth_within_radius(data.query, data.reference, data.negative_radius)
        self.trainable = np.flatnonzero((self.frames.query_starts >= 0) & positives.has_positive())
        if len(self.trainable) == 0:
            raise SeqvprError(
                f"no training query has both a window of {spec.length} frames and a positive within "
                f"{data.positive_radius}"
            )
        kernel = learner.mining_kernel(data, self.frames, settings)
        mining = MiningConfig(settings.negatives, settings.negative_pool, settings.margin)
        self.miner = SequenceMiner(kernel, self.frames.query_starts, positives, near, mining)
        self.val_gt = ground_truth_within_radius(data.val_query, data.val_reference, data.val_radius)
        torch.manual_seed(settings.seed)
        self.model = learner.build_model(settings).to(device)
        self.optimizer = _optimizer(self.model, settings)
        self.scheduler = torch.optim.lr_scheduler.StepLR(self.optimizer, settings.lr_step, settings.lr_gamma)

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
        refresh = settings.refresh_every or max(len(order), 1)
        for begin in range(0, len(order), refresh):
            chunk = order[begin : begin + refresh]
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
        """Mining features of every training frame with the current model (no gradients)."""
        self.model.eval()
        with torch.no_grad():
            return self.learner.mining_features(self.model, self.frames)

    def _step(self, batch: Sequence[Triplet]) -> float:
        """One optimiser step on a batch of mined triplet groups; returns the loss."""
        self.model.train()
        loss = self.learner.batch_loss(self.model, self.frames, batch, self.settings)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return float(loss.detach())

    # --- validation ----------------------------------------------------------------------------------------
    def validate_record(self, epoch: int) -> EpochRecord:
        evaluation = self.learner.validate(self.model, self.data, self.val_gt, self.settings)
        return EpochRecord(epoch, 0.0, 0, 0, 0, self.optimizer.param_groups[0]["lr"], 0.0, 0.0, 0.0, evaluation.recall)

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
        self.learner.save_model(out, self.model, self.metadata(epoch, recall))

    def save_state(self, out: Path, history: list[EpochRecord], best_epoch: int, best_recall: dict[int, float]) -> None:
        """A complete state folder for this epoch, then the pointer to it (the commit), then old folders go."""
        epoch = history[-1].epoch
        folder = out / "state" / f"epoch_{epoch:04d}"
        self.learner.save_model(folder, self.model, self.metadata(epoch, history[-1].recall))
        tensors, rest = ckpt.flatten_optimizer(self.optimizer.state_dict())
        tensors["miner.cache"] = torch.as_tensor(self.miner.cache_array(len(self.data.query)))
        ckpt.save_tensors(folder / ckpt.STATE_FILE, tensors)
        write_history(out / "history.csv", history)
        ckpt.save_json(out / ckpt.STATE_JSON, {
            "state_dir": str(folder.relative_to(out)),
            "settings": self.settings.resume_key(),
            self.learner.config_key: self.learner.config(),
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
        check_same(state["settings"], self.settings.resume_key(), out / ckpt.STATE_JSON)
        key = self.learner.config_key
        if key not in state:
            raise SeqvprError(f"{out / ckpt.STATE_JSON}: not a state of this kind of run (no {key!r} entry)")
        check_same(state[key], self.learner.config(), out / ckpt.STATE_JSON)
        folder = out / state["state_dir"]
        self.model.load_state_dict(self.learner.load_weights(folder))
        tensors = ckpt.read_tensors(folder / ckpt.STATE_FILE)
        self.optimizer.load_state_dict(ckpt.unflatten_optimizer(tensors, state["optimizer"]))
        self.scheduler.load_state_dict(state["scheduler"])
        self.miner.load_cache(tensors["miner.cache"].numpy())
        history = [_record_from_dict(r) for r in state["history"]]
        best = {int(k): float(v) for k, v in state["best_recall"].items()}
        return history, int(state["best_epoch"]), best


def _optimizer(model: nn.Module, settings: LoopSettings) -> torch.optim.Optimizer:
    if settings.optimizer == "sgd":
        return torch.optim.SGD(
            model.parameters(), lr=settings.lr, momentum=settings.momentum, weight_decay=settings.weight_decay
        )
    return torch.optim.Adam(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)


def check_same(saved: dict, current: dict, path: Path) -> None:
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


def write_history(path: Path, history: list[EpochRecord]) -> None:
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
