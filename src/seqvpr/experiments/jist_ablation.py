"""JIST's ablation on one split and one budget: joint training against each branch alone, untrained SeqGeM over the
same starting encoder, SeqNet trained on the same split, and sequence matching for reference; then the trained
joint model's robustness to the window length and to the order of the frames in a window.

Every row is scored on the test pair through ``seqvpr.match`` (what ``seqvpr match --model`` runs), at the
training length. The JIST rows share every setting but ``branches``: ``joint`` (sequence triplets + CosPlace
classification), ``sequence`` (the triplets alone) and ``images`` (classification alone, then SeqGeM over the
frames it learned). The untrained row is the model every run starts from (same seed, same construction). SeqNet
and sequence matching read the patch-normalised frames (seqvpr's weight-free descriptor of images).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from seqvpr.data.ground_truth import GroundTruth, Radius, ground_truth_within_radius
from seqvpr.data.traversal import Traversal
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation
from seqvpr.evaluation.scoring import evaluate_match
from seqvpr.io import atomic_file_set
from seqvpr.sequences.match_settings import MatchSettings
from seqvpr.models.configs import JIST_BRANCHES
from seqvpr.sequences.windows import SequenceSpec
from seqvpr.threads import ensure_policy

Pair = tuple[Traversal, Traversal]
#: SeqNet's budget in the ablation: 8 epochs at lr 1e-2, halved every 3 (the benchmark's, about 1 min an epoch on
#: Nordland on 2 CPU cores)
SEQNET_ABLATION = {"epochs": 8, "lr": 1e-2, "lr_step": 3}
#: the window orders the robustness table scores: as recorded, reversed, and shuffled within each window
ORDERS = ("forward", "reversed", "shuffled")


@dataclass(frozen=True)
class JistSplit:
    """Training, selection and test pairs (reference, query) of one route, and the ground-truth radius."""

    train: Pair
    select: Pair
    test: Pair
    radius: Radius


@dataclass(frozen=True)
class AblationRow:
    """One row: its name, what it is, its test evaluation, and its training's best epoch and seconds (None: not
    trained)."""

    name: str
    what: str
    test: Evaluation
    best_epoch: int | None = None
    seconds: float | None = None


def run_jist_ablation(
    split: JistSplit,
    values: dict[str, Any],
    out_dir: str | Path,
    *,
    classification: Sequence[Traversal] | None = None,
    variants: Sequence[str] = JIST_BRANCHES,
    seqnet: dict[str, Any] | None = None,
    monitor: Callable[[str], Any] | None = None,
) -> list[AblationRow]:
    """Train every JIST variant into ``out_dir/<variant>`` (a finished run is reused, a stopped one resumed) and
    SeqNet into ``out_dir/seqnet``, then score each on the test pair; returns the table's rows, joint first."""
    from seqvpr.training.data import training_data
    from seqvpr.training.jist import check_cells, jist_setup, train_jist

    ensure_policy()
    unknown = [v for v in variants if v not in JIST_BRANCHES]
    if unknown or not variants:
        raise SeqvprError(f"JIST variant {(unknown or [''])[0]!r} is not known (choose from: {', '.join(JIST_BRANCHES)})")
    out = Path(out_dir)
    config, settings = jist_setup(values)
    data = training_data("jist", split.train, split.select, split.radius)
    check_cells(settings.grouping, data.negative_radius)  # before any training: a bad split is one line
    rows = []
    for variant in variants:
        folder = out / variant
        result = train_jist(data, replace(config, branches=variant), settings, folder,
                            resume=(folder / "train_state.json").is_file(),
                            monitor=monitor(variant) if monitor else None, classification=classification)
        seconds = sum(r.epoch_seconds for r in result.history)
        rows.append(AblationRow(f"JIST {variant}", BRANCH_NAMES[variant], score_model(result.folder, split),
                                result.best_epoch, seconds))
    start = save_start(out / "start", config, settings)
    rows.append(AblationRow("SeqGeM untrained", "the same starting encoder, untrained (every run's epoch 0)",
                            score_model(start, split)))
    rows += patchnorm_rows(split, config.seq_length, out / "seqnet", seqnet or SEQNET_ABLATION,
                           monitor("seqnet") if monitor else None)
    return rows


BRANCH_NAMES = {
    "joint": "sequence triplets + CosPlace classification (the paper's)",
    "sequence": "sequence triplets alone",
    "images": "CosPlace classification alone, then SeqGeM",
}


def save_start(folder: Path, config, settings) -> Path:
    """The model every JIST run starts from (the training loop seeds torch with ``settings.seed`` and builds the
    model first), saved as a model folder."""
    from seqvpr.models.jist import build_jist, save_jist

    torch.manual_seed(settings.seed)
    save_jist(folder, build_jist(config), config, {"image_size": [settings.width, settings.height],
                                                   "sequence": {"length": config.seq_length}})
    return folder


def score_model(folder: Path, split: JistSplit, length: int | None = None, device: str = "cpu") -> Evaluation:
    """A JIST model folder scored on the test pair as ``seqvpr match --model`` scores it (its length unless
    ``length``; frames described on ``device``)."""
    from seqvpr.methods import describe_for_models
    from seqvpr.models.registry import load_trained_model

    models = {"jist": load_trained_model(folder, device)}
    described = describe_for_models(*split.test, models, lambda r, q: (r, q), device=device)
    return score("jist", described, split, length or models["jist"].length, models)


def score(method: str, pair: Pair, split: JistSplit, length: int, models: dict | None = None) -> Evaluation:
    """Recall@1/5/10 of one method on a described test pair at ``length``, through ``seqvpr.match``."""
    from seqvpr.api import match

    result = match(*pair, method, models=models or {}, settings=MatchSettings(SequenceSpec(length), k=10))
    return evaluate_match(result, split_truth(split), (1, 5, 10))


def split_truth(split: JistSplit) -> GroundTruth:
    """The ground truth of the split's test pair (queries against the reference, within the split's radius)."""
    query, reference = split.test[1], split.test[0]
    return ground_truth_within_radius(query, reference, split.radius)


def patchnorm_rows(split: JistSplit, length: int, folder: Path, seqnet: dict[str, Any], monitor=None) -> list[AblationRow]:
    """SeqNet trained on the split's patch-normalised frames, and sequence matching over them."""
    from seqvpr.features.describe import describe
    from seqvpr.models.registry import load_trained_model
    from seqvpr.training.data import training_data
    from seqvpr.training.seqnet import train_seqnet
    from seqvpr.training.settings import SeqNetSettings

    train, select, test = ((describe(r), describe(q)) for r, q in (split.train, split.select, split.test))
    settings = SeqNetSettings(sequence=SequenceSpec(length), **seqnet)
    result = train_seqnet(training_data("seqnet", train, select, split.radius), settings, folder,
                          resume=(folder / "train_state.json").is_file(), monitor=monitor)
    models = {"seqnet": load_trained_model(result.folder)}
    return [
        AblationRow("SeqNet", "trained on the split's patch-normalised frames", score("seqnet", test, split, length,
                    models), result.best_epoch, sum(r.epoch_seconds for r in result.history)),
        AblationRow("SeqGeM, patch-normalised", "untrained SeqGeM over the patch-normalised frames",
                    score("seqgem", test, split, length)),
        AblationRow("sequence matching", "patch-normalised frames, no training", score("matching", test, split, length)),
    ]


# --- robustness: window length and frame order -------------------------------------------------------------------


def robustness_rows(folder: Path, split: JistSplit, lengths: Sequence[int] = (3, 5, 10), seed: int = 0
                    ) -> list[tuple[str, dict[str, Evaluation]]]:
    """The trained model at each length (forward order) and at its training length with each window's frames
    reversed and shuffled, beside sequence matching over the same frame descriptors: rows of
    (condition, {"JIST": ..., "sequence matching": ...})."""
    from seqvpr.methods import describe_for_models
    from seqvpr.models.registry import load_trained_model

    model = load_trained_model(folder)
    reference, query = describe_for_models(*split.test, {"jist": model}, lambda r, q: (r, q))
    pool = model.module.sequence_pool
    truth = split_truth(split)
    rows = []
    for length in lengths:
        rows.append((f"L = {length}", ordered_scores(reference, query, truth, length, "forward", pool, seed)))
    for order in ORDERS[1:]:
        rows.append((f"L = {model.length}, {order}",
                     ordered_scores(reference, query, truth, model.length, order, pool, seed)))
    return rows


def ordered_scores(reference: Traversal, query: Traversal, truth: GroundTruth, length: int, order: str,
                   pool: torch.nn.Module, seed: int = 0) -> dict[str, Evaluation]:
    """JIST's SeqGeM retrieval and sequence matching over the same frames, each query window's frames put in
    ``order`` (``ORDERS``; the reference's windows stay as recorded): Recall@1/5/10 of each."""
    from seqvpr.results import MatchResult, TopK
    from seqvpr.sequences.topk import best_of

    spec = SequenceSpec(length)
    ref_rows, ref_frames = centered_windows(len(reference), spec)
    qry_rows, qry_frames = centered_windows(len(query), spec)
    qry_frames = reorder_windows(qry_frames, order, seed)
    ref_unit = _unit(reference.descriptors)
    qry_unit = _unit(query.descriptors)
    distances = {
        "JIST": torch.cdist(_pooled(pool, qry_unit, qry_frames), _pooled(pool, ref_unit, ref_frames)).double().numpy(),
        "sequence matching": aligned_distances(qry_unit, ref_unit, qry_frames, ref_frames),
    }
    scores = {}
    if order == "forward":  # as recorded: what seqvpr match --model JIST --method matching -L length runs
        from seqvpr.api import match

        scores["sequence matching"] = evaluate_match(match(reference, query, "matching", seq_len=length, k=10),
                                                     truth, (1, 5, 10))
        distances.pop("sequence matching")
    for name, values in distances.items():
        candidates = np.broadcast_to(ref_rows, values.shape)
        rows, dists = best_of(candidates, values, 10)
        indices = np.full((len(query), 10), -1, np.int64)
        top = np.full((len(query), 10), np.inf)
        indices[qry_rows, : rows.shape[1]], top[qry_rows, : rows.shape[1]] = rows, dists  # fewer than 10 windows: -1/inf
        has = np.zeros(len(query), bool)
        has[qry_rows] = True
        result = MatchResult(reference, query, TopK(indices, top, has), MatchSettings(spec, k=10))
        scores[name] = evaluate_match(result, truth, (1, 5, 10))
    return scores


def centered_windows(n: int, spec: SequenceSpec) -> tuple[np.ndarray, np.ndarray]:
    """The frames with a whole window under ``spec`` (one segment) and each window's frame rows [n_windows, L]."""
    from seqvpr.sequences.windows import window_frames, window_starts

    starts = window_starts(np.zeros(n, np.int64), spec.length, spec.offset, spec.boundary)
    rows = np.flatnonzero(starts >= 0)
    return rows, window_frames(starts[rows], spec.length)


def reorder_windows(frames: np.ndarray, order: str, seed: int = 0) -> np.ndarray:
    """Window frame rows [n, L] as recorded, each reversed, or each shuffled by a seeded generator."""
    if order == "forward":
        return frames
    if order == "reversed":
        return frames[:, ::-1].copy()
    if order == "shuffled":
        rng = np.random.default_rng(seed)
        return np.take_along_axis(frames, rng.permuted(np.tile(np.arange(frames.shape[1]), (len(frames), 1)), axis=1), 1)
    raise SeqvprError(f"window order {order!r} is not known (choose from: {', '.join(ORDERS)})")


def aligned_distances(query: torch.Tensor, reference: torch.Tensor, query_frames: np.ndarray,
                      reference_frames: np.ndarray) -> np.ndarray:
    """Sequence matching's distance of every (query window, reference window): the mean over positions l of the
    Euclidean distance between the query window's l-th frame and the reference window's l-th frame."""
    frames = torch.cdist(query.double(), reference.double())
    total = torch.zeros(len(query_frames), len(reference_frames), dtype=torch.float64)
    for position in range(query_frames.shape[1]):
        total += frames[torch.as_tensor(query_frames[:, position])][:, torch.as_tensor(reference_frames[:, position])]
    return (total / query_frames.shape[1]).numpy()


def _unit(descriptors: np.ndarray) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.as_tensor(np.asarray(descriptors, np.float32)), dim=1)


def _pooled(pool: torch.nn.Module, frames: torch.Tensor, windows: np.ndarray) -> torch.Tensor:
    with torch.no_grad():
        return pool.eval()(frames[torch.as_tensor(windows)]).float()


# --- tables --------------------------------------------------------------------------------------------------------


def ablation_markdown(rows: Sequence[AblationRow]) -> str:
    lines = ["| row | R@1 | R@5 | R@10 | queries | best epoch | train s | what |", "|---|---:|---:|---:|---:|---:|---:|---|"]
    for row in rows:
        recall = " | ".join(f"{row.test.recall[k]:.3f}" for k in (1, 5, 10))
        epoch = "–" if row.best_epoch is None else str(row.best_epoch)
        seconds = "–" if row.seconds is None else f"{row.seconds:.0f}"
        lines.append(f"| {row.name} | {recall} | {row.test.queries_evaluated} | {epoch} | {seconds} | {row.what} |")
    return "\n".join(lines)


def ablation_csv(rows: Sequence[AblationRow]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["row", "R@1", "R@5", "R@10", "queries_evaluated", "best_epoch", "train_seconds", "what"])
    for row in rows:
        writer.writerow([row.name, *[f"{row.test.recall[k]:.4f}" for k in (1, 5, 10)], row.test.queries_evaluated,
                         "" if row.best_epoch is None else row.best_epoch,
                         "" if row.seconds is None else f"{row.seconds:.1f}", row.what])
    return buffer.getvalue()


def robustness_markdown(rows: Sequence[tuple[str, dict[str, Evaluation]]]) -> str:
    lines = ["| test windows | JIST R@1 | JIST R@5 | sequence matching R@1 | sequence matching R@5 |",
             "|---|---:|---:|---:|---:|"]
    for condition, scores in rows:
        cells = " | ".join(f"{scores[name].recall[k]:.3f}" for name in ("JIST", "sequence matching") for k in (1, 5))
        lines.append(f"| {condition} | {cells} |")
    return "\n".join(lines)


def write_jist_ablation(rows: Sequence[AblationRow], robustness: Sequence[tuple[str, dict[str, Evaluation]]],
                        out_dir: str | Path) -> tuple[Path, Path]:
    """``ablation.csv`` and ``ablation.md`` (both tables) in ``out_dir``, committed as one pair."""
    out = Path(out_dir)
    with atomic_file_set(out, ("ablation.csv", "ablation.md"), "ablation.md") as tmp:
        (tmp / "ablation.csv").write_text(ablation_csv(rows))
        (tmp / "ablation.md").write_text(ablation_markdown(rows) + "\n\n" + robustness_markdown(robustness) + "\n")
    return out / "ablation.csv", out / "ablation.md"
