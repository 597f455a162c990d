"""SeqMatchNet training: per-frame transform, sequence triplet loss, sequence-based online hard-negative mining.

The loop itself is ``trainer.train_sequence_model``; this module is its SeqMatchNet adapter. One epoch visits the
training queries in a seeded random order, in chunks of ``refresh_every`` queries. Before each chunk the current
model transforms every training frame and the miner ranks all reference windows by the kernel's sequence
distance. After each epoch the model is validated on its own split (neither train nor test);
the best one by Recall@K is kept. Every epoch leaves a complete resumable state, so ``resume=True`` continues a
killed run to the same weights as an uninterrupted one (deterministic on CPU for a seed).

Same name as ``seqvpr.models.seqmatchnet``: SeqMatchNet's learner; its model there.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from seqvpr import checks
from seqvpr.data.ground_truth import GroundTruth
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.models.seqmatchnet import FrameTransform, TransformConfig, load_seqmatchnet, save_seqmatchnet
from seqvpr.matchers.rows import transform_traversal
from seqvpr.matchers.sequence import SequenceMatcher
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.training.losses import sequence_triplet_loss, window_part
from seqvpr.training.settings import SeqMatchNetSettings
from seqvpr.training.mining import DistanceRows, Triplet, mining_kernel
from seqvpr.training.descriptor_models import DescriptorLearner
from seqvpr.training.trainer import (
    check_training_inputs,
    EpochRecord,
    Step,
    SilentMonitor,
    TrainingContext,
    TrainingData,
    TrainingMonitor,
    TrainResult,
    train_sequence_model,
)

# The loop's data, records and monitors are part of SeqMatchNet training's public names (re-exported).
__all__ = [
    "EpochRecord", "SilentMonitor", "TrainingData", "TrainingMonitor", "TrainResult", "SeqMatchNetSettings",
    "SeqMatchNetLearner", "evaluate_transform", "train_seqmatchnet",
]



def train_seqmatchnet(
    data: TrainingData,
    transform: TransformConfig | None = None,
    settings: SeqMatchNetSettings = SeqMatchNetSettings(),
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
    check_training_inputs(data, settings, SeqMatchNetSettings)
    if transform is not None:
        checks.instance(transform, "transform", TransformConfig, "a TransformConfig (or None)")
    transform = transform or TransformConfig(data.dim)
    if transform.in_dim != data.dim:
        raise SeqvprError(f"transform expects {transform.in_dim}-D input but the descriptors are {data.dim}-D")
    learner = SeqMatchNetLearner(transform, settings.sequence)
    return train_sequence_model(data, learner, settings, out_dir, resume=resume, monitor=monitor)


class SeqMatchNetLearner(DescriptorLearner):
    """SeqMatchNet as a learner: a per-frame transform; mining and loss use the sequence distance of the
    transformed frames (``settings.mining`` / ``settings.loss``: all frames or the centre frame only)."""

    config_key = "transform"

    def __init__(self, transform: TransformConfig, spec: SequenceSpec) -> None:
        self.transform, self.spec = transform, spec

    def config(self) -> dict[str, Any]:
        return self.transform.as_dict()

    def build_model(self, settings: SeqMatchNetSettings) -> FrameTransform:
        return FrameTransform(self.transform, seed=settings.seed)

    def mining_kernel(self, context: TrainingContext, settings: SeqMatchNetSettings) -> DistanceRows:
        return mining_kernel(settings.mining, self.spec, context.data.reference.segment_ids)

    def mining_features(self, model: FrameTransform) -> tuple[torch.Tensor, torch.Tensor]:
        """Every training frame through the current model."""
        return model(self.frames.query), model(self.frames.reference)

    def batch_loss(
        self, model: FrameTransform, loss: None, batch: Sequence[Triplet], step: Step, rng: np.random.Generator,
        settings: SeqMatchNetSettings,
    ) -> dict[str, torch.Tensor]:
        frames = self.frames
        q_frames = frames.query_windows([t.query for t in batch])
        negatives = np.concatenate([t.negatives for t in batch])
        r_frames = frames.reference_windows(np.concatenate([[t.positive for t in batch], negatives]).astype(np.int64))
        owner = torch.as_tensor(np.repeat(np.arange(len(batch)), [len(t.negatives) for t in batch]), device=frames.device)
        unique, inverse = torch.unique(r_frames, return_inverse=True)
        q_windows = model(frames.query[q_frames.reshape(-1)]).view(*q_frames.shape, -1)
        r_windows = model(frames.reference[unique])[inverse]
        spec = self.spec
        total = sequence_triplet_loss(
            q_windows, r_windows[: len(batch)], r_windows[len(batch) :], owner, settings.margin,
            window_part(settings.loss, spec.length, spec.offset),
        )
        return {"total": total}

    def validate(self, model: FrameTransform, data: TrainingData, gt: GroundTruth, settings: SeqMatchNetSettings) -> Evaluation:
        return evaluate_transform(
            model, data.val_reference, data.val_query, gt, self.spec, settings.ks, settings.device,
        )

    def save_model(self, folder: Path, model: FrameTransform, metadata: dict[str, Any]) -> None:
        save_seqmatchnet(folder, model, metadata)

    def load_weights(self, folder: Path) -> dict[str, torch.Tensor]:
        model, _ = load_seqmatchnet(folder)
        return model.state_dict()


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
    return evaluate_match(SequenceMatcher(settings).topk(ref, qry), gt, ks)
