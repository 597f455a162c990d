"""SeqNet training: a temporal Conv1d sequence descriptor learned with a triplet loss and online hard mining.

The loop is ``trainer.train_sequence_model``; this module is its SeqNet adapter (``SeqNetLearner``):

* model: ``SeqNet(in_dim, out_dim, w)`` (Conv1d over the window, temporal mean, L2), on L2-normalised frames
  (as ``sequence_descriptors`` and the retrieval matcher feed it at test time);
* mining features: the SeqNet descriptor of every training frame's window (a zero placeholder for frames
  without one); kernel ``seqnet_rows``: Euclidean distance between the query windows' descriptors and every
  reference window's descriptor (one GEMM, clamped sqrt), +inf for reference frames without a window. The
  miner's positive is the nearest reference window (in descriptor space) within the positive radius; negatives
  are the hardest of ``negative_pool`` random candidates plus the query's cached ones, outside the negative
  radius, kept only if they violate the margin, at most ``negatives``;
* loss ``seqnet_triplet_loss``: the triplet hinge on Euclidean distances of SeqNet descriptors, the mean over
  every (query, positive, negative) of the batch;
* validation: ``RetrievalMatcher(settings, "seqnet", model)`` (faiss flat index) + ``evaluate_match``;
* model folder: ``models.seqnet.save_seqnet`` / ``load_seqnet``.

Same name as ``seqvpr.models.seqnet``: SeqNet's learner; its model there.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from seqvpr.data.ground_truth import GroundTruth
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.matchers.retrieval import RetrievalMatcher
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.descriptors import SeqNet
from seqvpr.sequences.matching import frame_distances
from seqvpr.sequences.windows import SequenceSpec, window_frames
from seqvpr.models.seqnet import load_seqnet, save_seqnet
from seqvpr.training.losses import DEFAULT_MARGIN, euclidean, triplet_hinge
from seqvpr.training.settings import SeqNetSettings
from seqvpr.training.mining import DistanceRows, Triplet
from seqvpr.training.descriptor_models import DescriptorLearner
from seqvpr.training.trainer import (
    Step,
    check_training_inputs,
    TrainingContext,
    TrainingData,
    TrainingMonitor,
    TrainResult,
    train_sequence_model,
)

FEATURE_BATCH = 4096  # windows per forward pass when computing mining features


def train_seqnet(
    data: TrainingData,
    settings: SeqNetSettings = SeqNetSettings(),
    out_dir: str | Path = "seqnet-run",
    *,
    resume: bool = False,
    monitor: TrainingMonitor | None = None,
) -> TrainResult:
    """Train a SeqNet on ``data``'s descriptors; the best model by validation R@``select_k`` goes to ``out_dir``
    (``model.safetensors`` + ``config.json``, read by ``load_seqnet``), with ``history.csv`` and the resumable
    state of the last finished epoch (``resume=True`` continues it, or starts over when there is none)."""
    check_training_inputs(data, settings, SeqNetSettings)
    learner = SeqNetLearner(data.dim, settings.out_dim or data.dim, settings.w, settings.sequence)
    return train_sequence_model(data, learner, settings, out_dir, resume=resume, monitor=monitor)


# --- kernel and loss ---------------------------------------------------------------------------------------------


def seqnet_descriptors(model: SeqNet, frames: torch.Tensor, starts: np.ndarray, length: int) -> torch.Tensor:
    """SeqNet descriptor [n, out_dim] of the window starting at each of ``starts`` (all >= 0) over ``frames``."""
    rows = torch.as_tensor(window_frames(starts, length), device=frames.device)
    return model(frames[rows.reshape(-1)].view(len(rows), length, -1))


def frame_window_descriptors(model: SeqNet, frames: torch.Tensor, starts: np.ndarray, length: int) -> torch.Tensor:
    """Per frame row, the descriptor of its window ([n_frames, out_dim]); zeros (a placeholder) where none."""
    out = torch.zeros(len(starts), model.out_dim, dtype=frames.dtype, device=frames.device)
    rows = np.flatnonzero(np.asarray(starts) >= 0)
    for begin in range(0, len(rows), FEATURE_BATCH):
        part = rows[begin : begin + FEATURE_BATCH]
        out[torch.as_tensor(part, device=frames.device)] = seqnet_descriptors(model, frames, starts[part], length)
    return out


def seqnet_rows(query_starts: np.ndarray, reference_starts: np.ndarray) -> DistanceRows:
    """The SeqNet mining kernel over per-frame window descriptors (``frame_window_descriptors``).

    For each given query window start, the Euclidean distance from that window's descriptor to every reference
    frame's window descriptor (one GEMM, clamped sqrt), +inf for reference frames without a window. A window's
    descriptor depends only on its start, so any query row with that start stands for it.
    """
    query_starts, reference_starts = np.asarray(query_starts), np.asarray(reference_starts)
    representative = np.full(len(query_starts), -1, dtype=np.int64)
    valid = np.flatnonzero(query_starts >= 0)
    representative[query_starts[valid][::-1]] = valid[::-1]  # first row of each start
    no_window = torch.as_tensor(reference_starts < 0)

    def rows(query: torch.Tensor, reference: torch.Tensor, starts: np.ndarray) -> torch.Tensor:
        picked = representative[np.asarray(starts, dtype=np.int64)]
        if (picked < 0).any():
            raise SeqvprError("seqnet kernel: a query window start that no query frame has")
        q = query[torch.as_tensor(picked, device=query.device)]
        distances = frame_distances(q, reference)
        return distances.masked_fill(no_window.to(distances.device)[None, :], float("inf"))

    return rows


def seqnet_triplet_loss(
    query: torch.Tensor,
    positive: torch.Tensor,
    negative: torch.Tensor,
    owner: torch.Tensor,
    margin: float = DEFAULT_MARGIN,
) -> torch.Tensor:
    """Mean over triplets of max(|q_b - p_b| - |q_b - n_t| + margin, 0) for each negative t owned by query b."""
    d_ap = euclidean(query, positive)
    d_an = euclidean(query[owner], negative)
    return triplet_hinge(d_ap[owner], d_an, margin)


# --- the adapter -------------------------------------------------------------------------------------------------


class SeqNetLearner(DescriptorLearner):
    """SeqNet as a learner of ``trainer.train_sequence_model``."""

    config_key = "seqnet"

    def __init__(self, in_dim: int, out_dim: int, w: int, spec: SequenceSpec) -> None:
        self.in_dim, self.out_dim, self.w, self.spec = in_dim, out_dim, w, spec

    def config(self) -> dict[str, Any]:
        return {"in_dim": self.in_dim, "out_dim": self.out_dim, "w": self.w}

    def build_model(self, settings: SeqNetSettings) -> SeqNet:
        return SeqNet(self.in_dim, self.out_dim, self.w)

    def input_frames(self, descriptors: np.ndarray, device: torch.device) -> torch.Tensor:
        """L2-normalised frames, as ``sequence_descriptors`` feeds SeqNet at test time."""
        return F.normalize(super().input_frames(descriptors, device), dim=1)

    def mining_kernel(self, context: TrainingContext, settings: SeqNetSettings) -> DistanceRows:
        return seqnet_rows(context.query_starts, context.reference_starts)

    def mining_features(self, model: SeqNet) -> tuple[torch.Tensor, torch.Tensor]:
        frames, length = self.frames, self.spec.length
        return (frame_window_descriptors(model, frames.query, frames.query_starts, length),
                frame_window_descriptors(model, frames.reference, frames.reference_starts, length))

    def batch_loss(
        self, model: SeqNet, loss: None, batch: Sequence[Triplet], step: Step, rng: np.random.Generator,
        settings: SeqNetSettings,
    ) -> dict[str, torch.Tensor]:
        frames, length = self.frames, self.spec.length
        queries = np.asarray([t.query for t in batch], dtype=np.int64)
        references = np.concatenate([[t.positive for t in batch], *[t.negatives for t in batch]]).astype(np.int64)
        owner = torch.as_tensor(np.repeat(np.arange(len(batch)), [len(t.negatives) for t in batch]),
                                device=frames.device)
        q = seqnet_descriptors(model, frames.query, frames.query_starts[queries], length)
        r = seqnet_descriptors(model, frames.reference, frames.reference_starts[references], length)
        return {"total": seqnet_triplet_loss(q, r[: len(batch)], r[len(batch) :], owner, settings.margin)}

    def validate(self, model: SeqNet, data: TrainingData, gt: GroundTruth, settings: SeqNetSettings) -> Evaluation:
        match = MatchSettings(self.spec, k=max(settings.ks), device=settings.device)
        result = RetrievalMatcher(match, "seqnet", model).topk(data.val_reference, data.val_query)
        return evaluate_match(result, gt, settings.ks)

    def save_model(self, folder: Path, model: SeqNet, metadata: dict[str, Any]) -> None:
        save_seqnet(folder, model, metadata)

    def load_weights(self, folder: Path) -> dict[str, torch.Tensor]:
        model, _ = load_seqnet(folder)
        return model.state_dict()
