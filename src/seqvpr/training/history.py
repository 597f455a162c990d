"""What each epoch of a training run did, and ``history.csv``: one row per epoch (epoch 0 is the untrained model)."""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from seqvpr.io import atomic_write

HISTORY_FILE = "history.csv"


@dataclass
class EpochRecord:
    """What one epoch did: loss (and its named parts), triplets, skipped queries, optimiser steps, time split,
    validation recall."""

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
    steps: int = 0
    parts: dict[str, float] = field(default_factory=dict)


def record_from_dict(values: dict[str, Any]) -> EpochRecord:
    """An ``EpochRecord`` from its JSON form (recall keys back to integers)."""
    values = dict(values)
    values["recall"] = {int(k): float(v) for k, v in values["recall"].items()}
    return EpochRecord(**values)


def write_history(path: Path, history: list[EpochRecord]) -> None:
    """One CSV row per epoch; loss parts (JIST's sequence and image losses) get a ``loss_<name>`` column each."""
    ks = sorted(history[0].recall)
    parts = sorted({name for record in history for name in record.parts})
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["epoch", "loss", *[f"loss_{name}" for name in parts], "triplets", "queries_used",
                     "queries_skipped", "lr", "epoch_s", "mining_s", "features_s", *[f"val_R@{k}" for k in ks]])
    for r in history:
        writer.writerow([r.epoch, f"{r.loss:.6f}", *[f"{r.parts.get(name, 0.0):.6f}" for name in parts], r.triplets,
                         r.queries_used, r.queries_skipped, f"{r.lr:.3g}", f"{r.epoch_seconds:.3f}",
                         f"{r.mining_seconds:.3f}", f"{r.features_seconds:.3f}", *[f"{r.recall[k]:.4f}" for k in ks]])
    with atomic_write(path) as handle:
        handle.write(buffer.getvalue())
