"""The ``seqvpr`` command: a thin layer that parses options and calls the stage functions of ``seqvpr.pipeline``."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
import sys
from collections.abc import Callable
from pathlib import Path

import click
import numpy as np
import torch
from tqdm import tqdm

from seqvpr.data.groundtruth import GroundTruth, parse_radius
from seqvpr.data.sources import ground_truth_spec, load_traversal
from seqvpr.data.traversal import Traversal, parse_frame_range
from seqvpr.synthetic.world import CONDITIONS as DEMO_CONDITIONS
from seqvpr.errors import SeqvprError
from seqvpr.evaluation.metrics import Evaluation, evaluate
from seqvpr.evaluation.predictions import read_predictions, write_predictions
from seqvpr.features.patchnorm import PatchNormConfig
from seqvpr.io import atomic_write
from seqvpr.features.extraction import POOLINGS, ExtractorConfig
from seqvpr.pipeline import (
    DESCRIPTORS,
    MatchResult,
    MatchSettings,
    describe,
    evaluate_match,
    ground_truth,
    match_traversals,
    netvlad_extractor,
    rerank_match,
    retrieve_traversals,
    whiten_pair,
)
from seqvpr.sequences.windows import SequenceSpec

RETRIEVAL_METHODS = ("smoothing", "delta", "concat", "seqgem", "seqgem-signed")
MODEL_METHODS = ("seqnet", "jist")  # retrieval methods that are a --model of that kind


def tqdm_progress(total: int, label: str) -> Callable[[int], None]:
    """A tqdm bar on stderr (hidden when stderr is not a terminal); returns its update function."""
    bar = tqdm(total=total, desc=label, unit="frame", file=sys.stderr, leave=False, disable=None)
    return bar.update


def parse_frames(text: str | None) -> tuple[int | None, int | None]:
    """``--frames START:STOP`` -> a half-open range of source frame indices."""
    return parse_frame_range(text, "--frames")


def parse_ks(text: str) -> tuple[int, ...]:
    """``1,5,10,20`` -> (1, 5, 10, 20)."""
    try:
        ks = tuple(sorted({int(x) for x in text.split(",") if x.strip()}))
    except ValueError:
        raise SeqvprError(f"--k {text!r}: expected comma-separated positive integers, e.g. 1,5,10,20") from None
    if not ks or ks[0] < 1:
        raise SeqvprError(f"--k {text!r}: expected comma-separated positive integers, e.g. 1,5,10,20")
    return ks


def parse_velocities(text: str) -> tuple[float, ...]:
    """``1`` or ``0.8,1,1.2`` or ``0.8:1.2:0.1`` (min:max:step) -> velocities."""
    try:
        if ":" in text:
            lo, hi, step = (float(x) for x in text.split(":"))
            if step <= 0 or hi < lo:
                raise ValueError
            return tuple(float(v) for v in np.round(np.arange(lo, hi + step / 2, step), 6))
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise SeqvprError(f"--velocities {text!r}: expected V, V1,V2,... or MIN:MAX:STEP") from None


def parse_size(text: str | None) -> int | None:
    """``512M``, ``2G`` or plain bytes -> bytes; ``none`` -> no budget."""
    if text is None or text.lower() == "none":
        return None
    units = {"k": 1024, "m": 1024**2, "g": 1024**3}
    try:
        scale = units.get(text[-1].lower(), 1)
        return int(float(text[:-1] if text[-1].lower() in units else text) * scale)
    except (ValueError, IndexError):
        raise SeqvprError(f"--memory-budget {text!r}: expected bytes such as 512M or 2G") from None


def parse_thumbnail(text: str, option: str = "--thumbnail") -> tuple[int, int]:
    """``WIDTHxHEIGHT`` -> (width, height), both positive."""
    try:
        width, height = (int(x) for x in text.lower().split("x"))
        if width < 1 or height < 1:
            raise ValueError
        return width, height
    except ValueError:
        raise SeqvprError(f"{option} {text!r}: expected WIDTHxHEIGHT, e.g. 64x32") from None


def load_pair(reference: str, query: str, frames: str | None) -> tuple[Traversal, Traversal]:
    """Both traversals, sliced to the ``--frames`` range."""
    start, stop = parse_frames(frames)
    ref = load_traversal(reference, "reference")
    qry = load_traversal(query, "query")
    if start is not None or stop is not None:
        ref, qry = ref.slice_frames(start, stop), qry.slice_frames(start, stop)
    return ref, qry


def describe_pair(
    ref: Traversal, qry: Traversal, config: PatchNormConfig, descriptor: str = "patchnorm", **extraction
) -> tuple[Traversal, Traversal]:
    """Both traversals with descriptors (images become descriptors, with a progress bar); a NetVLAD head is
    initialised on the reference images (the query's when only it has images)."""
    extractor = extraction.get("extractor")
    if descriptor != "patchnorm" and extractor is not None and extractor.pooling == "netvlad":
        images = ref.image_paths if ref.image_paths is not None else qry.image_paths
        if images is not None:
            extraction["model"] = netvlad_extractor(extractor, images, extraction.get("device", "cpu"), tqdm_progress)
    return (describe(ref, descriptor, config, tqdm_progress, **extraction),
            describe(qry, descriptor, config, tqdm_progress, **extraction))


def extraction_options(function):
    """How images become descriptors: patch-normalised thumbnails or a backbone with GeM or NetVLAD pooling."""
    options = [
        click.option("--descriptor", type=click.Choice(list(DESCRIPTORS)), default="patchnorm", show_default=True,
                     help="How images become descriptors (descriptor files are used as they are)."),
        click.option("--thumbnail", default="64x32", show_default=True, help="patchnorm: grayscale thumbnail WIDTHxHEIGHT."),
        click.option("--patch", default=8, show_default=True, type=int, help="patchnorm: patch side in pixels."),
        click.option("--weights", default="imagenet", show_default=True,
                     help="Backbone weights: 'imagenet' (EfficientNet-Lite0's packaged weights) or a checkpoint path."),
        click.option("--pooling", type=click.Choice(list(POOLINGS)), default="gem", show_default=True,
                     help="Backbone pooling: GeM, or NetVLAD with clusters from k-means of local features."),
        click.option("--clusters", default=64, show_default=True, type=int, help="netvlad: number of clusters."),
        click.option("--image-size", default="320x240", show_default=True, help="Backbone input WIDTHxHEIGHT."),
        click.option("--batch-size", "extract_batch", default=32, show_default=True, type=int,
                     help="Images per backbone batch."),
        click.option("--cache-dir", type=click.Path(), help="Cache extracted descriptors here (keyed by model and images)."),
        click.option("--skip-bad", is_flag=True, help="Skip unreadable images (listed on stderr) instead of failing."),
    ]
    for option in reversed(options):
        function = option(function)
    return function


def extraction_settings(descriptor, thumbnail, patch, weights, pooling, clusters, image_size, extract_batch, cache_dir,
                        skip_bad, device="cpu") -> tuple[str, PatchNormConfig, dict]:
    """The parsed extraction options: descriptor name, patchnorm config, keyword arguments of ``describe``."""
    width, height = parse_thumbnail(thumbnail)
    image_width, image_height = parse_thumbnail(image_size, "--image-size")
    backbone = descriptor if descriptor != "patchnorm" else "efficientnet-lite0"
    config = ExtractorConfig(backbone, weights, pooling, image_width, image_height, extract_batch, clusters)
    return descriptor, PatchNormConfig(width, height, patch), {
        "extractor": config, "device": device, "cache_dir": cache_dir, "skip_bad": skip_bad,
    }


MODEL_KINDS = {"seqvpr-seqmatchnet": "seqmatchnet", "seqvpr-seqnet": "seqnet", "seqvpr-jist": "jist"}
MODEL_NAMES = {"seqmatchnet": "SeqMatchNet", "seqnet": "SeqNet", "jist": "JIST"}


@dataclass(frozen=True)
class TrainedModel:
    """A model folder of ``seqvpr train``: its kind, the module, its sequence length and (JIST) image size."""

    kind: str
    module: torch.nn.Module
    length: int
    image_size: tuple[int, int] | None = None


def model_kind(model_dir: str) -> str:
    """'seqmatchnet', 'seqnet' or 'jist', from the ``format`` in the folder's config.json."""
    from seqvpr.models import files as ckpt

    folder = Path(model_dir)
    if not folder.is_dir():
        raise SeqvprError(f"{folder}: no such model folder (expected {ckpt.MODEL_FILE} and {ckpt.CONFIG_FILE} inside)")
    config = ckpt.read_json(folder / ckpt.CONFIG_FILE)
    kind = MODEL_KINDS.get(config.get("format"))
    if kind is None:
        raise SeqvprError(f"{folder / ckpt.CONFIG_FILE}: unknown model format {config.get('format')!r} "
                          f"(expected one of: {', '.join(MODEL_KINDS)})")
    return kind


def load_trained_model(model_dir: str, kind: str, device: str = "cpu") -> TrainedModel:
    """The model of a ``seqvpr train`` folder of the given kind, with its L (and JIST's image size; its encoder
    is moved to ``device``, where it reads the images)."""
    from seqvpr.models import files as ckpt

    if kind == "seqnet":
        from seqvpr.models.seqnet import load_seqnet

        seqnet, config = load_seqnet(model_dir)
        return TrainedModel(kind, seqnet, int(config.get("L") or seqnet.w))
    if kind == "jist":
        from seqvpr.training.jist import load_jist

        try:
            jist = load_jist(model_dir).to(device)
        except (RuntimeError, AssertionError) as error:
            raise SeqvprError(f"device {device!r} is not usable here ({str(error).splitlines()[0]})") from None
        meta = ckpt.read_json(Path(model_dir) / ckpt.CONFIG_FILE)
        width, height = meta.get("image_size") or (640, 480)
        return TrainedModel(kind, jist, int(meta["config"]["seq_length"]), (int(width), int(height)))
    from seqvpr.models.seqmatchnet import load_seqmatchnet

    transform, config = load_seqmatchnet(model_dir)
    return TrainedModel(kind, transform, int(config.get("sequence", {}).get("length", 1)))


def resolve_method(method: str | None, kind: str | None) -> str:
    """The matching method: --method, or the --model's own (SeqNet, JIST), or sequence matching; a method and a
    model that do not go together are a one-line error."""
    if method is None:
        return kind if kind in MODEL_METHODS else "matching"
    if method in MODEL_METHODS and kind != method:
        found = "no --model" if kind is None else f"a {MODEL_NAMES[kind]} --model"
        raise SeqvprError(f"--method {method} needs a {MODEL_NAMES[method]} --model "
                          f"(seqvpr train {method} --out), got {found}")
    if kind in MODEL_METHODS and method != kind:
        raise SeqvprError(f"a {MODEL_NAMES[kind]} --model gives sequence descriptors itself: use --method {kind} "
                          f"(or leave --method out), not --method {method}")
    return method


def describe_for_model(
    ref: Traversal, qry: Traversal, model: TrainedModel | None, device: str,
    describe_both: Callable[[Traversal, Traversal], tuple[Traversal, Traversal]],
) -> tuple[Traversal, Traversal]:
    """Frame descriptors of both traversals: a JIST model's encoder reads the images at its image size, anything
    else is ``describe_both`` (the extraction options)."""
    if model is None or model.kind != "jist":
        return describe_both(ref, qry)
    from seqvpr.training.jist import ImageStore, describe_with_jist

    store = ImageStore(*model.image_size)
    return (describe_with_jist(model.module, ref, *model.image_size, device, store=store),
            describe_with_jist(model.module, qry, *model.image_size, device, store=store))


def transform_for_model(
    ref: Traversal, qry: Traversal, model: TrainedModel | None, device: str
) -> tuple[Traversal, Traversal]:
    """Both traversals through a SeqMatchNet model's per-frame transform; unchanged for other models."""
    if model is None or model.kind != "seqmatchnet":
        return ref, qry
    from seqvpr.pipeline import transform_traversal

    return transform_traversal(ref, model.module, device), transform_traversal(qry, model.module, device)


def retrieval_of(method: str, model: TrainedModel | None) -> tuple[str, torch.nn.Module | None]:
    """The ``retrieve_traversals`` method and module of a --method: SeqNet's own, JIST's SeqGeM pool, or none."""
    if method == "seqnet":
        return "seqnet", model.module
    if method == "jist":
        return "seqgem", model.module.sequence_pool
    return method, None


def resolve_ground_truth(ref: Traversal, qry: Traversal, radius: str | None, gt_file: str | None, reference: str) -> GroundTruth:
    """Ground truth from --ground-truth, --radius, or the description file's [ground_truth] table."""
    spec = ground_truth_spec(reference)
    if gt_file is None and radius is None and spec is not None:
        return ground_truth(ref, qry, spec.radius, spec.file)
    return ground_truth(ref, qry, parse_radius(radius) if radius else None, gt_file)


def recall_table(evaluation: Evaluation, label: str, width: int = 14) -> str:
    """A small text table: one row with R@K for each K, AUC and R@100P, and the query counts."""
    ks = list(evaluation.recall)
    header = f"{'':<{width}}" + "".join(f"{'R@' + str(k):>8}" for k in ks) + f"{'PR-AUC':>8}{'R@100P':>8}"
    row = f"{label:<{width}}" + "".join(f"{evaluation.recall[k]:>8.3f}" for k in ks)
    row += f"{evaluation.pr.auc:>8.3f}{evaluation.pr.recall_at_100_precision:>8.3f}"
    counts = (
        f"queries evaluated: {evaluation.queries_evaluated}; excluded: {evaluation.queries_excluded} "
        f"(no window: {evaluation.excluded_no_window}, no positive: {evaluation.excluded_no_positive}, "
        f"policy: {evaluation.no_positive})"
    )
    return "\n".join([header, row, counts])


def evaluation_json(evaluation: Evaluation, settings: dict) -> dict:
    return {
        "recall": {str(k): v for k, v in evaluation.recall.items()},
        "pr_auc": evaluation.pr.auc,
        "recall_at_100_precision": evaluation.pr.recall_at_100_precision,
        "queries_evaluated": evaluation.queries_evaluated,
        "queries_excluded": evaluation.queries_excluded,
        "excluded_no_window": evaluation.excluded_no_window,
        "excluded_no_positive": evaluation.excluded_no_positive,
        "settings": settings,
    }


def save_predictions(path: Path, result: MatchResult, gt: GroundTruth) -> None:
    """Predictions CSV in source frame indices, for queries that have a window."""
    top = result.topk
    rows = np.flatnonzero(top.has_window)
    ref_frames = result.reference.frame_index
    refs = np.where(top.indices[rows] >= 0, ref_frames[np.maximum(top.indices[rows], 0)], -1)
    names = result.query.frame_names()
    correct = gt.contains(rows, top.indices[rows, 0])
    write_predictions(
        path,
        result.query.frame_index[rows],
        [names[i] for i in rows],
        refs,
        top.distances[rows],
        correct,
        gt.has_positive()[rows],
    )


MATCH_EPILOG = """\b
Examples:
  seqvpr match --reference day.mat --query night.mat --seq-len 5 --radius 2f
  seqvpr match --reference summer/ --query winter/ --frames 17:2000 --radius 1f --seq-len 10
  seqvpr match --reference dataset.toml --query dataset.toml --json
  seqvpr match --reference ref.npz --query qry.npz --radius 25m --velocities 0.8:1.2:0.1
"""


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.version_option(package_name="seqvpr")
def cli() -> None:
    """Sequence-based visual place recognition: match a query traversal against a reference traversal."""


@cli.command(epilog=MATCH_EPILOG)
@click.option("--reference", "-r", required=True, help="Reference traversal: descriptor file, image folder, .db or .toml.")
@click.option("--query", "-q", required=True, help="Query traversal (same kinds as --reference).")
@click.option("--seq-len", "-L", type=int, help="Frames per sequence window.  [default: 1, or the --model's L]")
@click.option("--align", type=click.Choice(["centered", "causal"]), default="centered", show_default=True,
              help="Window around the frame (centred) or ending at it (causal, for online use).")
@click.option("--model", "model_dir", type=click.Path(),
              help="A seqvpr train --out folder: SeqMatchNet transforms the descriptors first; SeqNet and JIST give "
                   "sequence descriptors (--method seqnet / jist, implied), JIST describing the images itself.")
@click.option("--boundary", type=click.Choice(["drop", "shift"]), default="drop", show_default=True,
              help="At segment ends: drop frames whose window does not fit, or shift the window inward.")
@click.option("--velocities", default="1", show_default=True,
              help="Reference frames per query frame to search: V, V1,V2 or MIN:MAX:STEP (SeqSLAM slopes).")
@click.option("--radius", help="Ground-truth tolerance: metres (25m) or frames (2f). Default 25m with positions.")
@click.option("--ground-truth", "gt_file", type=click.Path(), help="Ground truth file: GT .mat (GThard/GTsoft) or VPR-Bench .npy.")
@click.option("--frames", help="Keep source frames START:STOP of both traversals (e.g. 17:2000).")
@extraction_options
@click.option("--method", type=click.Choice(["matching", *RETRIEVAL_METHODS, *MODEL_METHODS]),
              help="Sequence matching over frames, or one descriptor per window (smoothing, Delta, concatenation, "
                   "SeqGeM with p=3; seqgem-signed keeps negative parts; seqnet / jist: the --model's) searched with "
                   "faiss.  [default: matching, or the --model's method]")
@click.option("--index", "index_kind", type=click.Choice(["flat", "hnsw"]), default="flat", show_default=True,
              help="faiss index for --method other than matching: exact (flat) or approximate (HNSW).")
@click.option("--rerank", type=int, default=0, show_default=True,
              help="Hierarchical: re-rank the top N of --method by exact sequence distance (HVPR; 0: off).")
@click.option("--pca-dim", default=0, show_default=True, type=int,
              help="PCA-whiten descriptors to this many dimensions, fitted on the reference (0: off).")
@click.option("--k", "ks", default="1,5,10,20", show_default=True, help="Recall@K values.")
@click.option("--no-positive", type=click.Choice(["exclude", "miss"]), default="exclude", show_default=True,
              help="Queries with no positive: excluded from the denominator, or counted as misses.")
@click.option("--no-normalize", is_flag=True, help="Do not L2-normalise descriptors before matching.")
@click.option("--dtype", type=click.Choice(["float32", "float64"]), default="float32", show_default=True)
@click.option("--device", default="cpu", show_default=True, help="torch device, e.g. cpu or cuda.")
@click.option("--memory-budget", default="2G", show_default=True,
              help="Most bytes of distance matrix held at once (e.g. 512M); 'none' for the whole matrix.")
@click.option("--out", "out_dir", default="seqvpr-out", show_default=True, type=click.Path(),
              help="Folder for predictions.csv and run.json.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout instead of the table.")
def match(reference, query, seq_len, align, model_dir, boundary, velocities, radius, gt_file, frames, descriptor, thumbnail,
          patch, weights, pooling, clusters, image_size, extract_batch, cache_dir, skip_bad, method, index_kind, rerank,
          pca_dim, ks, no_positive, no_normalize, dtype, device, memory_budget, out_dir, as_json) -> None:
    """Match QUERY against REFERENCE with sequences of --seq-len frames; print Recall@K and write predictions."""
    descriptor, patchnorm, extraction = extraction_settings(
        descriptor, thumbnail, patch, weights, pooling, clusters, image_size, extract_batch, cache_dir, skip_bad, device
    )
    if pca_dim < 0:
        raise SeqvprError(f"--pca-dim must be 0 (off) or positive, got {pca_dim}")
    kind = model_kind(model_dir) if model_dir is not None else None
    method = resolve_method(method, kind)
    if kind == "jist" and pca_dim:
        raise SeqvprError("--pca-dim does not apply to a JIST --model (its SeqGeM pools the encoder's own descriptors)")
    if rerank < 0 or (rerank and method == "matching"):
        raise SeqvprError(f"--rerank N needs N >= 0 and a --method other than matching (got {rerank}, {method})")
    k_values = parse_ks(ks)
    speeds, budget = parse_velocities(velocities), parse_size(memory_budget)
    if seq_len is not None:
        SequenceSpec(seq_len, align, boundary, speeds)  # bad options fail before any data is read
    model = load_trained_model(model_dir, kind, device) if model_dir is not None else None
    ref, qry = load_pair(reference, query, frames)
    gt = resolve_ground_truth(ref, qry, radius, gt_file, reference)
    has_images = ref.image_paths is not None
    ref, qry = describe_for_model(ref, qry, model, device,
                                  lambda r, q: describe_pair(r, q, patchnorm, descriptor, **extraction))
    if pca_dim:
        ref, qry, used = whiten_pair(ref, qry, pca_dim)
        if used < pca_dim:
            click.echo(f"PCA-whitening to {used} dimensions (at most reference frames - 1 and descriptor size)", err=True)
    ref, qry = transform_for_model(ref, qry, model, device)
    if seq_len is None:
        seq_len = model.length if model is not None else 1
    spec = SequenceSpec(seq_len, align, boundary, speeds)
    settings = MatchSettings(spec, max(k_values), not no_normalize, dtype, device, budget)
    if method == "matching":
        result = match_traversals(ref, qry, settings, tqdm_progress)
    else:
        shortlist = replace(settings, k=max(rerank, settings.k))
        name, module = retrieval_of(method, model)
        result = retrieve_traversals(ref, qry, name, shortlist, index=index_kind, model=module)
        if rerank:
            result = rerank_match(result, settings)
    evaluation = evaluate_match(result, gt, k_values, no_positive)
    used_descriptor = "jist" if kind == "jist" else descriptor if has_images else "file"
    run = {
        "reference": reference, "query": query, "frames": frames, "radius": radius, "ground_truth": gt_file,
        "ground_truth_rule": gt.description, "descriptor": used_descriptor,
        "method": method, "index": index_kind if method != "matching" else None, "rerank": rerank,
        "pooling": pooling, "pca_dim": pca_dim, "no_positive": no_positive, "model": model_dir, "model_kind": kind,
        **settings.as_dict(),
    }
    out = Path(out_dir)
    save_predictions(out / "predictions.csv", result, gt)
    with atomic_write(out / "run.json") as handle:
        json.dump(evaluation_json(evaluation, run), handle, indent=2, default=str)
    if as_json:
        click.echo(json.dumps(evaluation_json(evaluation, run), default=str))
        return
    click.echo(f"reference: {ref!r}\nquery:     {qry!r}\nground truth: {gt.description}")
    click.echo(recall_table(evaluation, f"L={seq_len}"))
    click.echo(f"predictions: {out / 'predictions.csv'}")


@cli.command(name="eval", epilog="\b\nExample:\n  seqvpr eval seqvpr-out/predictions.csv --reference day.mat --query night.mat --radius 2f")
@click.argument("predictions", type=click.Path())
@click.option("--reference", "-r", required=True, help="The reference traversal the predictions index.")
@click.option("--query", "-q", required=True, help="The query traversal.")
@click.option("--radius", help="Ground-truth tolerance: 25m or 2f.")
@click.option("--ground-truth", "gt_file", type=click.Path(), help="Ground truth file (GT .mat or VPR-Bench .npy).")
@click.option("--k", "ks", default="1,5,10,20", show_default=True, help="Recall@K values.")
@click.option("--no-positive", type=click.Choice(["exclude", "miss"]), default="exclude", show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
def eval_command(predictions, reference, query, radius, gt_file, ks, no_positive, as_json) -> None:
    """Score a predictions CSV (query, references, distances) against ground truth."""
    k_values = parse_ks(ks)
    ref, qry = load_pair(reference, query, None)
    gt = resolve_ground_truth(ref, qry, radius, gt_file, reference)
    table = read_predictions(predictions)
    q_rows = _rows_of(qry.frame_index, table.query, predictions, "query")
    r_rows = _rows_of(ref.frame_index, table.references, predictions, "reference")
    indices = np.full((len(qry), table.references.shape[1]), -1, dtype=np.int64)
    distances = np.full(indices.shape, np.inf)
    indices[q_rows], distances[q_rows] = r_rows, table.distances
    has_window = np.zeros(len(qry), dtype=bool)
    has_window[q_rows] = True
    evaluation = evaluate(indices, distances, has_window, gt, k_values, no_positive)
    if as_json:
        click.echo(json.dumps(evaluation_json(evaluation, {"predictions": predictions, "ground_truth_rule": gt.description})))
    else:
        click.echo(recall_table(evaluation, Path(predictions).name[:14]))


def _rows_of(frame_index: np.ndarray, wanted: np.ndarray, path: str, what: str) -> np.ndarray:
    """Rows of a traversal holding the given source frame indices (-1 stays -1); unknown indices are an error."""
    lookup = {int(f): row for row, f in enumerate(frame_index)}
    flat = wanted.ravel()
    rows = np.array([lookup.get(int(f), -2) if f >= 0 else -1 for f in flat], dtype=np.int64)
    if (rows == -2).any():
        missing = int(flat[np.flatnonzero(rows == -2)[0]])
        raise SeqvprError(f"{path}: {what} frame {missing} is not in the {what} traversal")
    return rows.reshape(wanted.shape)


@cli.command(epilog="""\b
Examples:
  seqvpr demo                      # about 3 minutes on 2 cores
  seqvpr demo --quick              # a smaller world, under a minute
  seqvpr demo --condition winter --seed 3 --out demo-winter
""")
@click.option("--out", "out_dir", default="seqvpr-demo", show_default=True, type=click.Path(),
              help="Folder for the rendered world, the descriptor cache, the model and the report.")
@click.option("--quick", is_flag=True, help="A smaller world (200 frames per traversal) and a short training run.")
@click.option("--seed", default=0, show_default=True, type=int, help="Seed of the world and of training.")
@click.option("--frames", "n_frames", type=int, help="Frames per traversal.  [default: 600; --quick: 200]")
@click.option("--condition", type=click.Choice(list(DEMO_CONDITIONS)), default="night", show_default=True,
              help="The query drive's condition (the reference is driven by day).")
@click.option("--epochs", type=int, help="SeqMatchNet training epochs.  [default: 30; --quick: 10]")
@click.option("--no-train", is_flag=True, help="Skip SeqMatchNet training (matching baselines only).")
@click.option("--device", default="cpu", show_default=True, help="torch device, e.g. cpu or cuda.")
def demo(out_dir, quick, seed, n_frames, condition, epochs, no_train, device) -> None:
    """Render a synthetic route world, describe it with EfficientNet-Lite0, match single images and sequences,
    train SeqMatchNet, and write an HTML report (OUT/report/index.html)."""
    from seqvpr.cli_training import TqdmMonitor
    from seqvpr.experiments.demo import DemoSettings, recall_rows, run_demo

    settings = DemoSettings.quick() if quick else DemoSettings()
    changes = {"seed": seed, "condition": condition, "train": not no_train, "device": device}
    if n_frames is not None:
        changes["frames"] = n_frames
    if epochs is not None:
        changes["epochs"] = epochs
    settings = replace(settings, **changes)
    if settings.frames < 50:
        raise SeqvprError(f"--frames must be at least 50, got {settings.frames}")
    if settings.epochs < 1:
        raise SeqvprError(f"--epochs must be at least 1, got {settings.epochs}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise SeqvprError(f"{out}: --out exists and is not a folder")
    click.echo(f"rendering a {settings.frames}-frame world (seed {seed}; query: {condition}) into {out / 'world'}")
    result = run_demo(out, settings, progress=tqdm_progress, monitor=TqdmMonitor("seqmatchnet "),
                      echo=lambda text: click.echo(text))
    click.echo(f"test route, correct within {settings.radius_m:g} m:")
    click.echo(recall_rows(result.runs))
    click.echo("seconds: " + ", ".join(f"{stage} {value:.0f}" for stage, value in result.seconds.items()))
    click.echo(f"report: {result.report}")
    world = out / "world"
    click.echo(
        f"the same from the command line: seqvpr match -r {world / 'test_reference'} -q {world / 'test_query'} "
        f"--descriptor efficientnet-lite0 --image-size {settings.width}x{settings.height} --radius "
        f"{settings.radius_m:g}m -L 5 --cache-dir {out / 'cache'}"
    )


@cli.command(epilog="""\b
Examples:
  seqvpr extract images/ --out ref.npz
  seqvpr extract images/ --descriptor resnet50 --weights cosplace_r50.pth --image-size 512x384 --out ref.npz
  seqvpr match --reference ref.npz --query qry.npz --radius 25m -L 5
""")
@click.argument("images")
@extraction_options
@click.option("--cluster-images", help="netvlad: traversal whose images initialise the clusters  [default: IMAGES]; "
              "extract the query with the reference's images here so both share one NetVLAD head.")
@click.option("--role", type=click.Choice(["reference", "query"]), default="reference", show_default=True,
              help="Which side of a dbStruct or description file to read.")
@click.option("--device", default="cpu", show_default=True, help="torch device, e.g. cpu or cuda.")
@click.option("--out", "out_file", required=True, type=click.Path(),
              help="Traversal file (.npz: descriptors, positions, segments, frame_index) for seqvpr match.")
def extract(images, descriptor, thumbnail, patch, weights, pooling, clusters, image_size, extract_batch, cache_dir,
            skip_bad, cluster_images, role, device, out_file) -> None:
    """Describe the images of a traversal (image folder, @UTM folder, dbStruct...) and save a traversal file."""
    from seqvpr.data.sources import save_traversal_npz

    descriptor, patchnorm, extraction = extraction_settings(
        descriptor, thumbnail, patch, weights, pooling, clusters, image_size, extract_batch, cache_dir, skip_bad, device
    )
    traversal = load_traversal(images, role)
    if traversal.image_paths is None:
        raise SeqvprError(f"{images}: holds descriptors, not images; nothing to extract")
    if descriptor != "patchnorm" and pooling == "netvlad":
        source = load_traversal(cluster_images, "reference") if cluster_images else traversal
        if source.image_paths is None:
            raise SeqvprError(f"{cluster_images}: --cluster-images must be a traversal of images")
        extraction["model"] = netvlad_extractor(extraction["extractor"], source.image_paths, device, tqdm_progress)
    described = describe(traversal, descriptor, patchnorm, tqdm_progress, **extraction)
    skipped = len(traversal) - len(described)
    if skipped:
        kept = set(int(i) for i in described.frame_index)
        names = [p.name for i, p in zip(traversal.frame_index, traversal.image_paths) if int(i) not in kept]
        click.echo(f"skipped {skipped} unreadable images: {', '.join(names)}", err=True)
    save_traversal_npz(Path(out_file), described)
    click.echo(f"{out_file}: {len(described)} frames, {described.descriptors.shape[1]}-D {descriptor} descriptors")


@cli.command(epilog="""\b
Example:
  seqvpr benchmark bench/benchmark.toml --out runs/benchmark
""")
@click.argument("config_file", metavar="CONFIG")
@click.option("--out", "out_dir", default="seqvpr-benchmark", show_default=True, type=click.Path(),
              help="Folder for trained models, results.csv and results.md.")
def benchmark(config_file, out_dir) -> None:
    """Every method of CONFIG on every dataset's test split: one table like the papers', plus a length table."""
    from seqvpr.experiments.benchmark import main_table, length_table, read_config, run_benchmark, write_results
    from seqvpr.cli_training import JistProgress, TqdmMonitor

    config = read_config(config_file)
    out = Path(out_dir)
    monitors = lambda method: JistProgress(None, f"{method} ") if method == "jist" else TqdmMonitor(f"{method} ")  # noqa: E731
    rows = run_benchmark(config, out, progress=tqdm_progress, monitors=monitors,
                         echo=lambda text: click.echo(text, err=True))
    csv_path, md_path = write_results(rows, config, out)
    click.echo(f"Methods at L={config.seq_len}:\n{main_table(rows, config)}\n")
    click.echo(f"Sequence length (R@{config.ks[0]}):\n{length_table(rows, config)}\n")
    click.echo(f"results: {csv_path}, {md_path}")


def _register_training_commands() -> None:
    from seqvpr.cli_training import ablate, train

    cli.add_command(train)
    cli.add_command(ablate)


_register_training_commands()


def main() -> None:
    """Entry point: run the CLI; a SeqvprError becomes one line on stderr and exit status 2."""
    try:
        cli.main(standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as error:
        error.show()
        sys.exit(error.exit_code)
    except SeqvprError as error:
        click.echo(f"seqvpr: error: {error}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
