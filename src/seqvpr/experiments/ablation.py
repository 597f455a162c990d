"""SeqMatchNet's Table 1: loss {single, seqmatch} x mining {single, seqmatch}, plus the untransformed baseline.

Each variant is trained on the same data with the same settings (only the loss and the mining differ), its best
checkpoint by validation recall is tested with sequence matching at the training L, and the untransformed
descriptors are tested the same way.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from seqvpr.data.ground_truth import GroundTruth
from seqvpr.data.traversal import Traversal
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.io import atomic_file_set
from seqvpr.models.seqmatchnet import TransformConfig
from seqvpr.matchers.sequence import SequenceMatcher
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.models.seqmatchnet import load_seqmatchnet
from seqvpr.training.state import STATE_JSON
from seqvpr.training.seqmatchnet import (
    TrainingData,
    TrainingMonitor,
    TrainResult,
    SeqMatchNetSettings,
    evaluate_transform,
    train_seqmatchnet,
)
from seqvpr.threads import ensure_policy

VARIANTS: tuple[tuple[str, str], ...] = (
    ("single", "single"),
    ("single", "seqmatch"),
    ("seqmatch", "single"),
    ("seqmatch", "seqmatch"),
)


@dataclass(frozen=True)
class AblationRow:
    """One row of the table: the variant's name, its test evaluation, and its training run (None: baseline)."""

    name: str
    loss: str | None
    mining: str | None
    test: Evaluation
    training: TrainResult | None


def run_ablation(
    data: TrainingData,
    test_reference: Traversal,
    test_query: Traversal,
    test_gt: GroundTruth,
    transform: TransformConfig,
    settings: SeqMatchNetSettings,
    out_dir: str | Path,
    *,
    variants: Sequence[tuple[str, str]] = VARIANTS,
    monitor: Callable[[str], TrainingMonitor] | None = None,
) -> list[AblationRow]:
    """Train every (loss, mining) variant into ``out_dir/<loss>-<mining>`` and test it; baseline first.

    A variant whose folder already holds a run with the same settings is resumed (finished runs are reused).
    """
    ensure_policy()  # the one thread policy (seqvpr.threads)
    out = Path(out_dir)
    spec = settings.sequence
    baseline = evaluate_match(
        SequenceMatcher(MatchSettings(spec, k=max(settings.ks), device=settings.device)).topk(test_reference, test_query),
        test_gt,
        settings.ks,
    )
    rows = [AblationRow("untransformed", None, None, baseline, None)]
    for loss, mining in variants:
        name = f"{loss}-{mining}"
        folder = out / name
        variant = replace(settings, loss=loss, mining=mining)
        result = train_seqmatchnet(
            data, transform, variant, folder,
            resume=(folder / STATE_JSON).is_file(),
            monitor=monitor(name) if monitor else None,
        )
        model, _ = load_seqmatchnet(folder)
        test = evaluate_transform(model, test_reference, test_query, test_gt, spec, settings.ks, settings.device)
        rows.append(AblationRow(f"{loss}/{mining}", loss, mining, test, result))
    return rows


def ablation_markdown(rows: Sequence[AblationRow], ks: Sequence[int]) -> str:
    """The table as markdown: loss, mining, R@K..., best epoch."""
    header = "| loss | mining | " + " | ".join(f"R@{k}" for k in ks) + " | best epoch |"
    lines = [header, "|" + "---|" * (len(ks) + 3)]
    for row in rows:
        recall = " | ".join(f"{row.test.recall[k]:.3f}" for k in ks)
        if row.training is None:
            lines.append(f"| untransformed | – | {recall} | – |")
        else:
            lines.append(f"| {row.loss} | {row.mining} | {recall} | {row.training.best_epoch} |")
    return "\n".join(lines)


def ablation_csv(rows: Sequence[AblationRow], ks: Sequence[int]) -> str:
    """The table as CSV: loss, mining, R@K..., best epoch, queries evaluated."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["loss", "mining", *[f"R@{k}" for k in ks], "best_epoch", "queries_evaluated"])
    for row in rows:
        writer.writerow([row.loss or "untransformed", row.mining or "", *[f"{row.test.recall[k]:.4f}" for k in ks],
                         "" if row.training is None else row.training.best_epoch, row.test.queries_evaluated])
    return buffer.getvalue()


def write_ablation(rows: Sequence[AblationRow], ks: Sequence[int], out_dir: str | Path) -> tuple[Path, Path]:
    """``ablation.csv`` and ``ablation.md`` in ``out_dir`` (beside the variants' runs), committed as one pair
    (``seqvpr.io.atomic_file_set``): never one run's csv beside another's md."""
    out = Path(out_dir)
    with atomic_file_set(out, ("ablation.csv", "ablation.md"), "ablation.md") as tmp:
        (tmp / "ablation.csv").write_text(ablation_csv(rows, ks))
        (tmp / "ablation.md").write_text(ablation_markdown(rows, ks) + "\n")
    return out / "ablation.csv", out / "ablation.md"


def ablation_json(rows: Sequence[AblationRow]) -> list[dict]:
    """The rows as JSON-ready dicts: loss, mining, recall, best epoch."""
    return [{"loss": r.loss, "mining": r.mining, "recall": {str(k): v for k, v in r.test.recall.items()},
             "best_epoch": None if r.training is None else r.training.best_epoch} for r in rows]
