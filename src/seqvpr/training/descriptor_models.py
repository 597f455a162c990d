"""Models trained on frame descriptors (SeqMatchNet, SeqNet): the frames on the device, and mining over every
training window with the ``SequenceMiner`` and the learner's distance kernel."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from seqvpr.sequences.windows import window_frames
from seqvpr.training.mining import DistanceRows, MiningConfig, SequenceMiner, Triplet
from seqvpr.training.trainer import SequenceLearner, TrainingContext, TrainingData

CACHE_KEY = "miner.cache"


@dataclass(frozen=True)
class TrainingFrames:
    """The training frames on the device as the learner prepared them, with every frame's window start (-1: none)."""

    query: torch.Tensor
    reference: torch.Tensor
    query_starts: np.ndarray
    reference_starts: np.ndarray
    length: int
    device: torch.device

    def query_windows(self, rows: np.ndarray) -> torch.Tensor:
        """Frame rows [n, L] of the windows of query rows ``rows``."""
        return torch.as_tensor(window_frames(self.query_starts[rows], self.length), device=self.device)

    def reference_windows(self, rows: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(window_frames(self.reference_starts[rows], self.length), device=self.device)


class DescriptorLearner(SequenceLearner):
    """A learner over frame descriptors. Subclasses give ``input_frames``, ``mining_kernel``, ``mining_features``
    and the batch loss; mining is the ``SequenceMiner`` (n hardest margin-violating negatives of a random pool
    plus the query's cached ones), whose cache is part of the resumable state."""

    frames: TrainingFrames
    miner: SequenceMiner

    def input_frames(self, descriptors: np.ndarray, device: torch.device) -> torch.Tensor:
        """A traversal's frame descriptors as the model's training input on ``device``."""
        return torch.as_tensor(np.ascontiguousarray(descriptors), dtype=torch.float32, device=device)

    def mining_kernel(self, context: TrainingContext, settings) -> DistanceRows:
        """The miner's kernel over ``mining_features`` outputs."""
        raise NotImplementedError

    def mining_features(self, model: torch.nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
        """Query and reference features of every training frame for the kernel."""
        raise NotImplementedError

    def check_data(self, data: TrainingData) -> None:
        data.require_descriptors()

    def prepare(self, context: TrainingContext, settings) -> None:
        data, device = context.data, context.device
        self.frames = TrainingFrames(
            self.input_frames(data.query.descriptors, device), self.input_frames(data.reference.descriptors, device),
            context.query_starts, context.reference_starts, self.spec.length, device,
        )
        mining = MiningConfig(settings.negatives, settings.negative_pool, settings.margin)
        self.miner = SequenceMiner(self.mining_kernel(context, settings), context.query_starts, context.positives,
                                   context.near, mining)

    def rounds(self, trainable: np.ndarray, rng: np.random.Generator, settings) -> list[np.ndarray]:
        """The trainable queries in a random order, in chunks of ``refresh_every`` (None: one round per epoch)."""
        order = rng.permutation(trainable)
        refresh = settings.refresh_every or max(len(order), 1)
        return [order[begin : begin + refresh] for begin in range(0, len(order), refresh)]

    def mine(self, model: torch.nn.Module, queries: np.ndarray, rng: np.random.Generator) -> list[Triplet]:
        tick = time.perf_counter()
        query_features, reference_features = self.mining_features(model)
        self.features_seconds += time.perf_counter() - tick
        return self.miner.mine(query_features, reference_features, queries, rng)

    def state_tensors(self) -> dict[str, torch.Tensor]:
        return {CACHE_KEY: torch.as_tensor(self.miner.cache_array(len(self.frames.query)))}

    def load_state_tensors(self, tensors: dict[str, torch.Tensor]) -> None:
        self.miner.load_cache(tensors[CACHE_KEY].numpy())
