"""Data-parallel steps under ``torchrun``: a learner's batch loss run through torch's DistributedDataParallel.

A learner calls its model several times a step (anchors, positives, negatives; JIST its frames too) and its loss
may hold trainable parameters (JIST's CosFace heads). So the module DistributedDataParallel wraps is the whole
step, ``LearnerStep``: the model and the loss as its submodules, ``learner.batch_loss`` as its forward. Its
gradients are averaged over the ranks during backward, bucket by bucket; a parameter no rank used keeps no
gradient, so the optimiser skips it as it would alone. On CUDA the model's BatchNorm layers become SyncBatchNorm:
each layer normalises with the whole batch's statistics, as one process computing the whole batch does.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

if TYPE_CHECKING:
    from seqvpr.training.mining import Triplet
    from seqvpr.training.learner import LoopSettings, SequenceLearner, Step

StepLoss = Callable[["Sequence[Triplet]", "Step", np.random.Generator], "dict[str, torch.Tensor]"]


class LearnerStep(nn.Module):
    """One optimiser step's loss as a module: ``forward(batch, step, rng)`` is ``learner.batch_loss`` on the model
    and loss it holds (what DistributedDataParallel wraps)."""

    def __init__(self, learner: SequenceLearner, model: nn.Module, loss: nn.Module | None,
                 settings: LoopSettings) -> None:
        super().__init__()
        self.learner, self.settings = learner, settings
        self.model, self.loss = model, loss

    def forward(self, batch: Sequence[Triplet], step: Step, rng: np.random.Generator) -> dict[str, torch.Tensor]:
        return self.learner.batch_loss(self.model, self.loss, batch, step, rng, self.settings)


def synced_batch_norm(model: nn.Module, device: torch.device) -> nn.Module:
    """On CUDA, the model with its BatchNorm layers as SyncBatchNorm (in place: the same parameters and buffers,
    so the optimiser and the saved weights are unchanged); elsewhere the model as it is (gloo has no SyncBatchNorm)."""
    if device.type != "cuda":
        return model
    return nn.SyncBatchNorm.convert_sync_batchnorm(model)


def data_parallel_step(learner: SequenceLearner, model: nn.Module, loss: nn.Module | None,
                       settings: LoopSettings, device: torch.device) -> StepLoss:
    """The step's loss through DistributedDataParallel (its construction is collective: every rank calls this at
    the same point, after any resumed weights are loaded; rank 0's parameters are sent to the others)."""
    step = LearnerStep(learner, synced_batch_norm(model, device), loss, settings)
    wrapped = nn.parallel.DistributedDataParallel(step, find_unused_parameters=learner.unused_parameters)
    return lambda batch, at, rng: wrapped(batch, at, rng)


def single_process_step(learner: SequenceLearner, model: nn.Module, loss: nn.Module | None,
                        settings: LoopSettings) -> StepLoss:
    """The step's loss in one process: ``learner.batch_loss`` as it is."""
    return lambda batch, at, rng: learner.batch_loss(model, loss, batch, at, rng, settings)

