"""``seqvpr match``, ``seqvpr eval`` and ``seqvpr extract``: parse, call the library, print.

Same name as ``seqvpr.maps.match``: matching at the command line; matching against a map there."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click

from seqvpr.cli.options import (
    COUNT, DEVICE, NONNEGATIVE, OUT_FOLDER, Number, bag_topic_options, extraction_options, extraction_settings,
    given_image_size, locks_output, parse_ks, parse_size,
)
from seqvpr.cli.help import SectionedCommand, for_methods, option, section
from seqvpr.cli.progress import tqdm_progress
from seqvpr.errors import SeqvprError
from seqvpr.methods import METHODS

#: the manifest of a match's --out folder (written last; the marker that the folder is a run's output)
RUN_FILE = "run.json"

MATCH_EPILOG = """\b
Examples:
  seqvpr match --reference day.mat --query night.mat --seq-len 5 --radius 2f
  seqvpr match --reference summer/ --query winter/ --frames 17:2000 --radius 1f --seq-len 10
  seqvpr match --reference dataset.toml --query dataset.toml --json
  seqvpr match --reference ref.npz --query qry.npz --radius 25m --velocities 0.8:1.2:0.1
  seqvpr match -r ref.npz -q qry.npz --radius 25m --model runs/seqnet --model runs/seqmatchnet --method hvpr
  seqvpr match -r day/ -q night/ --radius 25m --model runs/cosplace-r18 --method matching -L 5
  seqvpr match --map maps/summer -q winter.npy --radius 1f -L 5
  seqvpr match -r run1.bag -q run2.bag --topic /camera/image_raw --gps-topic /fix --descriptor efficientnet-lite0
"""

#: ``seqvpr match --help``'s sections, in order
MATCH_SECTIONS = ("Input", "Sequences", "Method", "Map", "Ground truth and scoring", "Descriptors", "Output", "Compute")
#: the methods that search sequence descriptors with faiss, alone or as a shortlist (--index, --rerank)
RETRIEVAL_METHODS = tuple(m.name for m in METHODS.values() if m.family in ("retrieval", "hierarchical"))


@click.command(cls=SectionedCommand, epilog=MATCH_EPILOG, sections=MATCH_SECTIONS,
               listings={"Method": ("METHOD is one of:", [(m.name, m.summary) for m in METHODS.values()])})
@option("Input", "--reference", "-r", help="Reference traversal: descriptor file, image folder, .db or .toml.")
@option("Input", "--map", "map_dir", type=click.Path(),
        help="A saved map (seqvpr map build) as the reference, instead of --reference: the query is described as the "
             "map was (--frames then cuts the query only), and frame matching reads the map in chunks.")
@option("Input", "--query", "-q", required=True, help="Query traversal (same kinds as --reference).")
@option("Sequences", "--seq-len", "-L", type=COUNT, help="Frames per sequence window.  [default: 1, or the --model's L]")
@option("Sequences", "--align", type=click.Choice(["centered", "causal"]), default="centered", show_default=True,
        help="Window around the frame (centred) or ending at it (causal, for online use).")
@option("Method", "--method", type=click.Choice(list(METHODS)), metavar="METHOD",
        help="How to match: one of the methods listed below.  [default: matching, or the --model's method]")
@option("Method", "--model", "model_dirs", type=click.Path(), multiple=True,
        help="A seqvpr train --out or seqvpr import --out folder (repeatable, one per kind): SeqMatchNet transforms "
             "the frames that sequence matching compares; SeqNet and JIST give sequence descriptors (--method seqnet "
             "/ jist, implied); JIST and CosPlace describe the images themselves, at the folder's image size unless "
             "--image-size is given (CosPlace implies --method single; any other method but jist runs on its frames).")
@option("Sequences", "--boundary", type=click.Choice(["drop", "shift"]), default="drop", show_default=True,
        help="At segment ends: drop frames whose window does not fit, or shift the window inward.")
@option("Sequences", "--velocities", default="1", show_default=True,
        help="Reference frames per query frame to search: V, V1,V2 or MIN:MAX:STEP (SeqSLAM slopes); at most 1000 "
             "velocities (cone, hybrid: trajectories), each in (0, 100].")
@option("Method", "--steps", default="1:2", show_default=True,
        help=for_methods("adaptive", "casevpr", "graph") + "the fewest and most reference frames a query frame may "
             "move (MIN:MAX).")
@option("Method", "--contrast-window", type=Number(int, 2), default=10, show_default=True,
        help=for_methods("seqslam", "seqslam-hybrid") + "reference frames each distance is standardised against "
             "(OpenSeqSLAM2's r_window); widen it where frames are dense relative to the tolerance.")
@option("Ground truth and scoring", "--radius",
        help="Ground-truth tolerance: metres (25m) or frames (2f). Default 25m with positions.")
@option("Ground truth and scoring", "--ground-truth", "gt_file", type=click.Path(),
        help="Ground truth file: GT .mat (GThard/GTsoft), VPR-Bench .npy or a dense boolean matrix .npy/.npz.")
@option("Ground truth and scoring", "--gt-layout", type=click.Choice(["ref-query", "query-ref"]),
        help="A dense ground-truth matrix's layout when its shape does not say (a square one).")
@option("Input", "--frames", help="Keep source frames START:STOP of both traversals (e.g. 17:2000).")
@option("Input", "--msls-subtask", type=click.Choice(["all", "s2w", "w2s", "o2n", "n2o", "d2n", "n2d"]),
        help="An MSLS query side: keep the frames subtask_index.csv marks for this subtask.")
@section("Descriptors", extraction_options)
@option("Method", "--index", "index_kind", type=click.Choice(["flat", "hnsw"]), default="flat", show_default=True,
        help=for_methods(*RETRIEVAL_METHODS) + "the faiss index of the sequence descriptors: exact (flat) or "
             "approximate (HNSW).")
@option("Map", "--shortlist", type=NONNEGATIVE, default=0, show_default=True,
        help="With --map: re-rank only the windows placed by each query frame's S nearest map frames (the map's "
             "faiss index, seqvpr map index) by exact sequence distance (0: exhaustive).")
@option("Map", "--shortlist-history", "history", type=NONNEGATIVE, default=0, show_default=True,
        help="With --shortlist: the H query frames before each window place candidates too, carried forward at one "
             "frame per frame (where the robot just was; raises the shortlist's recall).")
@option("Map", "--nprobe", type=COUNT, default=16, show_default=True, help="IVF lists a --shortlist search visits.")
@option("Method", "--rerank", type=NONNEGATIVE, default=0, show_default=True,
        help=for_methods(*RETRIEVAL_METHODS) + "re-rank the top N by exact sequence distance (0: off; "
             "hvpr and casevpr: 20).")
@option("Descriptors", "--pca-dim", default=0, show_default=True, type=NONNEGATIVE,
        help="PCA-whiten descriptors to this many dimensions, fitted on the reference (0: off).")
@option("Ground truth and scoring", "--uniqueness", type=NONNEGATIVE, default=None,
        help="Rank queries for PR by SeqSLAM's windowed uniqueness (best minus the best outside this many frames of "
             "it; OpenSeqSLAM2's r_window is 10), not by distance.")
@option("Ground truth and scoring", "--k", "ks", default="1,5,10,20", show_default=True, help="Recall@K values.")
@option("Ground truth and scoring", "--no-positive", type=click.Choice(["exclude", "miss"]), default="exclude",
        show_default=True, help="Queries with no positive: excluded from the denominator, or counted as misses.")
@option("Descriptors", "--no-normalize", is_flag=True, help="Do not L2-normalise descriptors before matching.")
@option("Compute", "--dtype", type=click.Choice(["float32", "float64"]), default="float32", show_default=True,
        help="Floating-point precision of the distances.")
@option("Compute", "--device", type=DEVICE, default="cpu", show_default=True, help="torch device, e.g. cpu or cuda.")
@option("Compute", "--memory-budget", default="2G", show_default=True,
        help="Most bytes of distance matrix held at once (e.g. 512M; at least 1K, at most 1P); 'none' for the whole "
             "matrix.")
@option("Output", "--out", "out_dir", default="seqvpr-out", show_default=True, type=OUT_FOLDER,
        help="Folder for predictions.csv and run.json.")
@option("Output", "--json", "as_json", is_flag=True, help="Print one JSON object on stdout instead of the table.")
@section("Input", bag_topic_options("reference", "query"))
@locks_output("out_dir")
def match(**options: Any) -> None:
    """Match QUERY against REFERENCE with sequences of --seq-len frames; print Recall@K and write predictions."""
    k_values = _checked_options(options)
    models, method = _models_and_method(options)
    settings, search = _settings(options, method, models, k_values)
    from seqvpr import distributed
    from seqvpr.api import match as match_reference
    from seqvpr.evaluation.scoring import evaluate_match

    inputs = _map_sides(options, settings) if options["map_dir"] else _traversal_sides(options, models, settings)
    with distributed.process_group(options["device"]) as world:
        result = match_reference(inputs.reference, inputs.query, method, models=models, settings=settings,
                                 shortlist=options["shortlist"], history=options["history"], nprobe=options["nprobe"],
                                 rerank=options["rerank"], index=options["index_kind"],
                                 progress=tqdm_progress if world.is_root else None, cache_dir=options["cache_dir"],
                                 skip_bad=options["skip_bad"], engine=options["engine"], **search)
    if result is None:  # another rank of a sharded match: rank 0 scores and writes
        return
    evaluation = evaluate_match(result, inputs.gt, k_values, options["no_positive"], options["uniqueness"])
    run = _run_settings({**options, "reference": options["map_dir"] or options["reference"]}, method, models,
                        inputs.descriptor,
                        inputs.gt.description, {**settings.as_dict(), **search})
    run.update(inputs.record)
    if inputs.sharded:
        run["ranks"] = world.size
    if options["shortlist"]:
        run["shortlist"] = _shortlist_record(options, result, inputs.gt, inputs.index_spec)
    shown = (result.reference, result.query) if options["map_dir"] else (inputs.reference, inputs.query)
    _write_and_print(options, result, inputs.gt, evaluation, run, run_label(method, settings.sequence.length, options), shown)


def _settings(options: dict[str, Any], method: str, models: dict, k_values: tuple[int, ...]):
    """The one place the options become the library's settings: the match's (``seqvpr.api.match_settings``: L is
    the method's or its model's when -L is not given) and the method's own search settings."""
    from seqvpr.api import match_settings
    from seqvpr.sequences.windows import parse_steps, parse_velocities

    settings = match_settings(method, models, options["seq_len"], k=_top_k(k_values, options["uniqueness"]),
                              align=options["align"],
                              boundary=options["boundary"], velocities=parse_velocities(options["velocities"]),
                              normalize=not options["no_normalize"], dtype=options["dtype"], device=options["device"],
                              memory_budget=parse_size(options["memory_budget"]))
    return settings, {"steps": parse_steps(options["steps"]), "contrast_window": options["contrast_window"]}


@dataclass(frozen=True)
class MatchInputs:
    """What a match reads: the reference as the matcher takes it (a described traversal, a saved or a sharded
    map), the query, their ground truth, the descriptor's name and run.json's entries about the reference."""

    reference: Any
    query: Any
    gt: Any
    descriptor: str
    record: dict[str, Any]
    sharded: bool = False
    index_spec: str | None = None


def _traversal_sides(options: dict[str, Any], models: dict, settings) -> MatchInputs:
    """``--reference`` and ``--query`` loaded, cut, checked against L, ground truth resolved, both described."""
    from seqvpr.data.sources import load_pair
    from seqvpr.methods import image_model
    from seqvpr.evaluation.ground_truth import ground_truth_of_kept, resolve_ground_truth

    _sharded_reference(None)
    reference, query = load_pair(options["reference"], options["query"], options["frames"])
    if options["msls_subtask"]:
        query = _msls_subtask(options["query"], options["msls_subtask"], options["frames"])
    _check_length(settings.sequence.length, reference, query)
    gt = resolve_ground_truth(reference, query, options["radius"], options["gt_file"], options["reference"],
                              whole=not options["frames"],
                              layout=options["gt_layout"])
    has_images = reference.image_paths is not None
    pair = (reference, query)
    reference, query = _frames(reference, query, models, options)
    gt = ground_truth_of_kept(gt, pair, (reference, query))
    _say_skipped(pair, (reference, query))
    image = image_model(models)
    descriptor = image.kind if image else options["descriptor"] if has_images else "file"
    record = {"image_size": list(given_image_size(options) or image.image_size)} if image else {}
    return MatchInputs(reference, query, gt, descriptor, record)


def _map_sides(options: dict[str, Any], settings) -> MatchInputs:
    """``--map`` opened (a sharded one as its shards), the query loaded and cut, checked against L, ground truth
    resolved on the map's frame table; the map describes the query as it described its frames."""
    from seqvpr.data.sources import load_traversal
    from seqvpr.data.traversal import slice_frame_range
    from seqvpr.maps.files import open_map, open_sharded_map
    from seqvpr.evaluation.ground_truth import resolve_ground_truth

    sharded = _sharded_reference(options["map_dir"])
    reference = open_sharded_map(options["map_dir"]) if sharded else open_map(options["map_dir"])
    info = reference.open_shard(0).info if sharded else reference.info
    _check_map_options(options, info.description["descriptor"])
    query = slice_frame_range(load_traversal(options["query"], "query"), options["frames"])
    table = reference.frames
    _check_length(settings.sequence.length, table, query)
    gt = resolve_ground_truth(table, query, options["radius"], options["gt_file"], layout=options["gt_layout"])
    record = {"map": options["map_dir"], **({"shards": len(reference.shards)} if sharded else {})}
    return MatchInputs(reference, query, gt, info.description["descriptor"], record, sharded,
                 (info.index or {}).get("spec"))


def _checked_options(options: dict[str, Any]) -> tuple[int, ...]:
    """The options checked before any model or data is read: the K values parsed (returned), --out replaceable (and
    holding none of the inputs), the reference and shortlist options coherent."""
    from seqvpr.io import check_out_folder

    k_values = parse_ks(options["ks"])
    if options["pca_dim"] < 0:
        raise SeqvprError(f"--pca-dim must be 0 (off) or positive, got {options['pca_dim']}")
    inputs = [options[k] for k in ("reference", "query", "map_dir", "gt_file", "cache_dir")]
    check_out_folder(options["out_dir"], RUN_FILE, inputs + list(options["model_dirs"]))
    if bool(options["map_dir"]) == bool(options["reference"]):
        raise SeqvprError("give the reference as --reference or as --map (one of them)")
    if options["shortlist"] < 0 or (options["shortlist"] and not options["map_dir"]):
        raise SeqvprError(f"--shortlist S needs S >= 0 and a --map with an index (got {options['shortlist']})")
    if options["history"] < 0 or (options["history"] and not options["shortlist"]):
        raise SeqvprError(f"--shortlist-history H needs H >= 0 and a --shortlist (got {options['history']})")
    return k_values


def _msls_subtask(query: str, subtask: str, frames: str | None):
    """The MSLS query side with only the frames of ``subtask``."""
    from seqvpr.data.loaders.msls import is_msls_side, load_msls_side
    from seqvpr.data.traversal import slice_frame_range

    if not is_msls_side(Path(query)):
        raise SeqvprError(f"--msls-subtask needs an MSLS query folder (seq_info.csv, images/): {query} is not one")
    return slice_frame_range(load_msls_side(query, subtask), frames)


def _check_length(length: int, reference, query) -> None:
    """-L longer than every segment of either traversal is one line before any image is described."""
    from seqvpr.sequences.windows import check_length

    for side, traversal in (("reference", reference), ("query", query)):
        check_length(length, traversal.segment_ids, f"{side} {traversal.source or traversal.name}")


def _top_k(k_values: tuple[int, ...], uniqueness: int | None) -> int:
    """Matches kept per query: the largest K asked, and with --uniqueness E at least 2E + 2, so that a match outside
    the exclusion window is in the list (the ones inside are the best match's neighbours)."""
    return max(max(k_values), 2 * uniqueness + 2 if uniqueness is not None else 0)


def run_label(method: str, length: int, options: dict[str, Any]) -> str:
    """The table's row label: the method, L, and the re-ranking or shortlist that shaped the result."""
    label = f"{method} L={length}"
    if options.get("rerank"):
        label += f" + rerank {options['rerank']}"
    if options.get("shortlist"):
        label += f" + shortlist {options['shortlist']}" + (f" (history {options['history']})" if options.get("history") else "")
    return label


def _say_skipped(pair, kept) -> None:
    """Name on stderr the images --skip-bad left out."""
    from seqvpr.features.describe import dropped_frames

    for original, described in zip(pair, kept):
        skipped = dropped_frames(original, described)
        if skipped:
            click.echo(f"skipped {len(skipped)} unreadable images of {original.name}: {', '.join(skipped)}", err=True)


def _sharded_reference(map_dir: str | None) -> bool:
    """Whether --map names a sharded map; under torchrun it must (ranks share a sharded map's work)."""
    from seqvpr.distributed import from_environment
    from seqvpr.maps.files import is_sharded_map

    sharded = bool(map_dir) and is_sharded_map(map_dir)
    if from_environment().size > 1 and not sharded:
        raise SeqvprError("under torchrun, seqvpr match shares the work of a sharded map (seqvpr map shard MAP "
                          "--shards N); give one as --map, or run without torchrun")
    return sharded


def _shortlist_record(options: dict[str, Any], result, gt, index_spec: str) -> dict[str, Any]:
    """run.json's shortlist entry (its settings and recall), the recall printed."""
    from seqvpr.maps.match import shortlist_recall

    record = {"per_frame": options["shortlist"], "history": options["history"], "index": index_spec,
              "nprobe": options["nprobe"],
              "recall": shortlist_recall(result, gt)}
    click.echo(f"shortlist: {record['recall']:.3f} of the scored queries have a true place among their candidates",
               err=True)
    return record


def _check_map_options(options: dict[str, Any], built: str) -> None:
    """With --map the map decides how frames are described: a different --descriptor, or --pca-dim, is an error."""
    from click.core import ParameterSource

    if options["pca_dim"]:
        raise SeqvprError("--pca-dim does not apply to --map (build the map from whitened descriptors instead)")
    source = click.get_current_context().get_parameter_source("descriptor")
    if source not in (ParameterSource.DEFAULT, None) and options["descriptor"] != built:
        raise SeqvprError(f"--descriptor {options['descriptor']} differs from the map's {built} descriptors "
                          f"({options['map_dir']}): leave it out, the map decides")


def _models_and_method(options: dict[str, Any]) -> tuple[dict, str]:
    """The --model folders loaded by kind, and the method (--method or the models' own), checked together."""
    from seqvpr.methods import check_run, implied_method
    from seqvpr.models.registry import load_models, model_kinds

    kinds = model_kinds(options["model_dirs"])
    method = options["method"] or implied_method(kinds)
    check_run(method, kinds, options["rerank"])  # before any model or data is read (-L: with the settings)
    if "jist" in kinds and options["pca_dim"]:
        raise SeqvprError("--pca-dim does not apply to a JIST --model (its SeqGeM pools the encoder's own descriptors)")
    return load_models(kinds.values(), options["device"]), method


def _frames(reference, query, models: dict, options: dict[str, Any]):
    """Frame descriptors for the method: the image model's (JIST, CosPlace) or the extraction options', then
    PCA-whitened if asked."""
    from seqvpr.methods import describe_for_models
    from seqvpr.features.describe import describe_pair, whiten_pair

    descriptor, patchnorm, extraction = extraction_settings(options, options["device"])
    reference, query = describe_for_models(
        reference, query, models,
        lambda r, q: describe_pair(r, q, descriptor, patchnorm, tqdm_progress, **extraction), options["device"],
        given_image_size(options), options["engine"],
    )
    if not options["pca_dim"]:
        return reference, query
    reference, query, used = whiten_pair(reference, query, options["pca_dim"])
    if used < options["pca_dim"]:
        click.echo(f"PCA-whitening to {used} dimensions (at most reference frames - 1 and descriptor size)", err=True)
    return reference, query


def _run_settings(options: dict[str, Any], method: str, models: dict, descriptor: str, rule: str, match: dict) -> dict:
    """Everything that decided the run, for run.json."""
    folders = [str(f) for f in options["model_dirs"]]
    kinds = list(models)
    return {
        "reference": options["reference"], "query": options["query"], "frames": options["frames"], "radius": options["radius"],
        "ground_truth": options["gt_file"], "ground_truth_rule": rule, "descriptor": descriptor, "method": method,
        "index": None if METHODS[method].family == "matching" else options["index_kind"], "rerank": options["rerank"],
        "pooling": options["pooling"], "pca_dim": options["pca_dim"], "no_positive": options["no_positive"],
        "image_normalization": options["normalize"] if descriptor.startswith("torchscript:") else None,
        "model": folders[0] if len(folders) == 1 else folders or None,
        "model_kind": kinds[0] if len(kinds) == 1 else kinds or None, **match,
    }


def _write_and_print(options: dict[str, Any], result, gt, evaluation, run: dict, label: str, pair) -> None:
    """--out as one folder (``seqvpr.io.atomic_folder``): predictions.csv, correspondences.csv (when the method pairs
    frames) and run.json last, swapped in whole; then the table (or one JSON object) on stdout."""
    from seqvpr.evaluation.predictions import save_correspondences, save_match_predictions
    from seqvpr.evaluation.summary import evaluation_json, recall_table
    from seqvpr.io import atomic_folder
    from seqvpr.evaluation.scoring import match_correspondences

    out = Path(options["out_dir"])
    pairs = match_correspondences(result)
    with atomic_folder(out, RUN_FILE) as tmp:
        save_match_predictions(tmp / "predictions.csv", result, gt)
        if pairs is not None:
            save_correspondences(tmp / "correspondences.csv", result, pairs, gt)
        (tmp / RUN_FILE).write_text(json.dumps(evaluation_json(evaluation, run), indent=2, default=str))
    if options["as_json"]:
        click.echo(json.dumps(evaluation_json(evaluation, run), default=str))
        return
    click.echo(f"reference: {pair[0]!r}\nquery:     {pair[1]!r}\nground truth: {gt.description}")
    click.echo(recall_table(evaluation, label))
    if evaluation.frame_precision == evaluation.frame_precision:  # not NaN
        click.echo(f"frame-level precision of the top-1 matches' correspondences: {evaluation.frame_precision:.3f}")
    click.echo(f"predictions: {out / 'predictions.csv'}")
    if pairs is not None:
        click.echo(f"correspondences: {out / 'correspondences.csv'}")


@click.command(name="eval", epilog="\b\nExample:\n  seqvpr eval seqvpr-out/predictions.csv --reference day.mat --query night.mat --radius 2f")
@click.argument("predictions", type=click.Path())
@click.option("--reference", "-r", required=True, help="The reference traversal the predictions index.")
@click.option("--query", "-q", required=True, help="The query traversal.")
@click.option("--radius", help="Ground-truth tolerance: 25m or 2f.")
@click.option("--ground-truth", "gt_file", type=click.Path(), help="Ground truth file (GT .mat, VPR-Bench .npy or a dense matrix).")
@click.option("--gt-layout", type=click.Choice(["ref-query", "query-ref"]),
              help="A dense ground-truth matrix's layout when its shape does not say (a square one).")
@click.option("--k", "ks", default="1,5,10,20", show_default=True, help="Recall@K values.")
@click.option("--no-positive", type=click.Choice(["exclude", "miss"]), default="exclude", show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@bag_topic_options("reference", "query")
def eval_command(predictions, reference, query, radius, gt_file, gt_layout, ks, no_positive, as_json) -> None:
    """Score a predictions CSV (query, references, distances) against ground truth."""
    k_values = parse_ks(ks)
    from seqvpr.data.sources import load_pair
    from seqvpr.evaluation.predictions import evaluate_predictions
    from seqvpr.evaluation.summary import evaluation_json, recall_table
    from seqvpr.evaluation.ground_truth import resolve_ground_truth

    ref, qry = load_pair(reference, query)
    gt = resolve_ground_truth(ref, qry, radius, gt_file, reference, whole=True, layout=gt_layout)
    evaluation = evaluate_predictions(predictions, ref, qry, gt, k_values, no_positive)
    if as_json:
        click.echo(json.dumps(evaluation_json(evaluation, {"predictions": predictions, "ground_truth_rule": gt.description})))
    else:
        click.echo(recall_table(evaluation, Path(predictions).name))
