"""What the one training loop (``trainer``) works with: the training data, the settings it reads, the steps and
context it hands a learner, and ``SequenceLearner``, the model-specific parts a model kind writes (SeqMatchNet,
SeqNet, JIST). Kept apart from the loop so that the loop's helpers (``parallel``, ``resume``) read these types
without importing the loop."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn

from seqvpr.data.ground_truth import GroundTruth, Radius
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.training.history import EpochRecord
from seqvpr.training.mining import Triplet


@dataclass(frozen=True)
class TrainingData:
    """Training and validation traversals with their radii (positives, negatives, validation ground truth).
    Descriptor models need descriptors on all four, JIST needs images; traversals that carry descriptors must
    agree on their size."""

    reference: Traversal
    query: Traversal
    val_reference: Traversal
    val_query: Traversal
    positive_radius: Radius
    negative_radius: Radius
    val_radius: Radius

    def __post_init__(self) -> None:
        self._check_dimensions()
        if self.negative_radius.unit != self.positive_radius.unit:
            raise SeqvprError("positive and negative radii must have the same unit (both m or both f)")
        if self.negative_radius.value < self.positive_radius.value:
            raise SeqvprError(
                f"negative radius {self.negative_radius} is smaller than the positive radius {self.positive_radius}"
            )

    def traversals(self) -> dict[str, Traversal]:
        return {name: getattr(self, name) for name in ("reference", "query", "val_reference", "val_query")}

    def _check_dimensions(self) -> None:
        described = {name: t for name, t in self.traversals().items() if t.descriptors is not None}
        dims = {name: t.descriptors.shape[1] for name, t in described.items()}
        if len(set(dims.values())) > 1:
            first, *others = described
            odd = next(name for name in others if dims[name] != dims[first])
            raise SeqvprError(
                f"descriptor dimensions differ: {described[first].source or first} has {dims[first]}, "
                f"{described[odd].source or odd} ({odd.replace('_', ' ')}) has {dims[odd]}"
            )

    def require_descriptors(self) -> None:
        """Fail with one line unless all four traversals carry descriptors."""
        for name, traversal in self.traversals().items():
            if traversal.descriptors is None:
                raise SeqvprError(f"{traversal.source or name}: training needs descriptors (describe the images first)")

    @property
    def dim(self) -> int:
        self.require_descriptors()
        return int(self.reference.descriptors.shape[1])


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
    """The fields of a (frozen dataclass) settings object the loop itself reads."""

    batch_size: int
    epochs: int
    select_k: int
    ks: tuple[int, ...]
    select_untrained: bool
    seed: int
    device: str

    def as_dict(self) -> dict[str, Any]: ...

    def resume_key(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class Step:
    """Where an optimiser step is: its epoch (1-based) and its index among all steps of the run (0-based)."""

    epoch: int
    index: int


@dataclass(frozen=True)
class TrainingContext:
    """What the loop derives from the data once, for the learner: window starts of the training traversals under
    the learner's spec (-1: no window), positives and non-negatives (within the negative radius), the device."""

    data: TrainingData
    spec: SequenceSpec
    query_starts: np.ndarray
    reference_starts: np.ndarray
    positives: GroundTruth
    near: GroundTruth
    device: torch.device


class SequenceLearner:
    """The model-specific parts of a training run. Subclasses set ``config_key`` and ``spec`` and implement the
    methods that raise ``NotImplementedError``; the others are defaults (no loss parameters, SGD/Adam with StepLR,
    consecutive batches, no mixed precision, no state of its own)."""

    #: key of the model config in ``train_state.json`` (checked on resume)
    config_key: str = "model"
    #: the training windows
    spec: SequenceSpec = SequenceSpec(1)
    #: seconds of the current epoch's mining spent computing features with the model (the loop resets it)
    features_seconds: float = 0.0
    #: whether some trainable parameters take no part in a step (JIST's heads of the other groups)
    unused_parameters: bool = False

    def config(self) -> dict[str, Any]:
        """The model config that must match when a run is resumed (JSON-able)."""
        raise NotImplementedError

    def check_data(self, data: TrainingData) -> None:
        """Fail with one line when the data lacks what this model trains from."""

    def prepare(self, context: TrainingContext, settings: LoopSettings) -> None:
        """Set up what mining and the loss need (frames on the device, the miner)."""

    def build_model(self, settings: LoopSettings) -> nn.Module:
        """A fresh model (called right after ``torch.manual_seed(settings.seed)``; the loop moves it to the device)."""
        raise NotImplementedError

    def build_loss(self, settings: LoopSettings) -> nn.Module | None:
        """A loss with trainable parameters (built right after the model), or None."""
        return None

    def build_optimizer(
        self, model: nn.Module, loss: nn.Module | None, settings: LoopSettings
    ) -> tuple[torch.optim.Optimizer, Any]:
        """The optimiser and its per-epoch scheduler (or None): SGD or Adam with StepLR, from the settings."""
        return sgd_or_adam(model, settings)

    def rounds(self, trainable: np.ndarray, rng: np.random.Generator, settings: LoopSettings) -> list[np.ndarray]:
        """The query rows of each mining round of one epoch, drawn from ``rng``."""
        raise NotImplementedError

    def mine(self, model: nn.Module, queries: np.ndarray, rng: np.random.Generator) -> list[Triplet]:
        """Triplets for ``queries`` with the current model (called in eval mode under ``torch.no_grad``)."""
        raise NotImplementedError

    def loss_terms(self, batch: Sequence[Triplet]) -> int:
        """How many terms the batch's loss averages (the triplet losses: one per query and negative): ranks that
        share a batch weigh their parts by it, so their averaged gradients are the whole batch's."""
        return sum(len(t.negatives) for t in batch) or len(batch)

    def batches(self, triplets: list[Triplet], settings: LoopSettings) -> list[list[Triplet]]:
        """The round's triplets in optimiser batches of ``batch_size`` (the last one may be smaller)."""
        size = settings.batch_size
        return [triplets[begin : begin + size] for begin in range(0, len(triplets), size)]

    def batch_loss(
        self, model: nn.Module, loss: nn.Module | None, batch: Sequence[Triplet], step: Step, rng: np.random.Generator,
        settings: LoopSettings,
    ) -> dict[str, torch.Tensor]:
        """The differentiable loss of a batch (``"total"``, plus named parts) at optimiser step ``step``."""
        raise NotImplementedError

    def mixed_precision(self, settings: LoopSettings) -> bool:
        """Whether steps run under CUDA autocast with a gradient scaler."""
        return False

    def validate(self, model: nn.Module, data: TrainingData, gt: GroundTruth, settings: LoopSettings) -> Evaluation:
        """Recall@``settings.ks`` on the validation traversals."""
        raise NotImplementedError

    def save_model(self, folder: Path, model: nn.Module, metadata: dict[str, Any]) -> None:
        """Write the model folder (weights + config with ``metadata``)."""
        raise NotImplementedError

    def load_weights(self, folder: Path) -> dict[str, torch.Tensor]:
        """The state dict saved by ``save_model`` in ``folder``."""
        raise NotImplementedError

    def state_tensors(self) -> dict[str, torch.Tensor]:
        """The learner's own resumable state (e.g. a miner's negative cache)."""
        return {}

    def load_state_tensors(self, tensors: dict[str, torch.Tensor]) -> None:
        pass


class TrainingRun(Protocol):
    """What a run's state files are written from and restored into (``resume.RunState``): the data, the learner and
    its settings, the model, its trainable loss, the optimiser and its scheduler."""

    data: TrainingData
    learner: SequenceLearner
    settings: LoopSettings
    model: nn.Module
    loss: nn.Module | None
    optimizer: torch.optim.Optimizer
    scheduler: Any


def sgd_or_adam(model: nn.Module, settings: Any) -> tuple[torch.optim.Optimizer, Any]:
    """SGD (with momentum) or Adam over the model's parameters, and StepLR every ``lr_step`` epochs."""
    if settings.optimizer == "sgd":
        optimizer = torch.optim.SGD(
            model.parameters(), lr=settings.lr, momentum=settings.momentum, weight_decay=settings.weight_decay
        )
    else:
        optimizer = torch.optim.Adam(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    return optimizer, torch.optim.lr_scheduler.StepLR(optimizer, settings.lr_step, settings.lr_gamma)

