"""``seqvpr localize``: replay a query traversal as a stream through the online localiser over a saved map; with
``--calibrate``, pick and store the score threshold that reaches a target precision."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import click

from seqvpr.cli.options import (
    DEVICE,
    COUNT, FINITE, FRACTION, NONNEGATIVE, NONNEGATIVE_FLOAT, POSITIVE, parse_ks, OUT_FILE, OUT_FOLDER,
    ENGINE_CHOICE, ENGINE_HELP, bag_topic_options, locks_output, with_options
)
from seqvpr.cli.help import SectionedCommand, option, section
from seqvpr.cli.progress import tqdm_progress
from seqvpr.errors import SeqvprError, SeqvprWarning

#: the manifest of a localize --out folder (written last; the marker that the folder is a run's output)
RUN_FILE = "run.json"


#: ``seqvpr localize --help``'s sections, in order
LOCALIZE_SECTIONS = ("Input", "Method", "Map", "Localiser", "Ground truth and scoring", "Output", "Compute")


#: the options that open a localiser (method, map, localiser, device): ``seqvpr localize`` and ``seqvpr node``
localizer_options = with_options([
    option("Method", "--method", type=click.Choice(["matching", "single", "seqmatchnet", "hmm"]), default=None,
        help="matching: exact causal sequence matching; single: one frame; seqmatchnet: on a map built through it; "
             "hmm: the topological filter (stops, speed changes).  [default: matching, or seqmatchnet with its "
             "--model]"),
    option("Method", "-L", "--seq-len", type=COUNT, default=5, show_default=True, help="Frames of a causal window."),
    option("Method", "--model", "model_dirs", multiple=True, type=click.Path(),
        help="The model(s) the map was built through."),
    option("Map", "--shortlist", type=NONNEGATIVE, default=0, show_default=True,
        help="Re-rank only candidates from the map's frame index, S per query frame (0: exact over the map)."),
    option("Map", "--shortlist-history", "history", type=NONNEGATIVE, default=0, show_default=True,
        help="With --shortlist: the H frames before the window place candidates too."),
    option("Map", "--nprobe", type=COUNT, default=16, show_default=True, help="IVF lists a shortlist search visits."),
    option("Localiser", "--threshold", type=FINITE,
        help="Score from which an estimate is localised [default: the map's calibrated one for these settings, else "
             "the method's default]."),
    option("Localiser", "--lost-after", type=COUNT, default=5, show_default=True,
        help="Frames below the threshold before 'lost'."),
    option("Localiser", "--exclusion", type=NONNEGATIVE, default=10, show_default=True,
        help="Frames around the best that are not 'another place' for the score."),
    option("Localiser", "--keyframe-distance", type=NONNEGATIVE_FLOAT, default=0.0, show_default=True,
        help="Skip frames closer than this (descriptor distance) to the last kept one (0: keep all)."),
    option("Method", "--min-step", type=NONNEGATIVE, default=0, show_default=True,
        help="hmm: fewest map frames moved per frame."),
    option("Method", "--max-step", type=NONNEGATIVE, default=2, show_default=True,
        help="hmm: most map frames moved per frame (at most 1000)."),
    option("Method", "--floor", type=FRACTION, default=1e-3, show_default=True,
        help="hmm: chance per frame of a jump anywhere."),
    option("Method", "--sharpness", type=POSITIVE, default=1.5, show_default=True,
        help="hmm: how sharply worse distances count."),
    option("Compute", "--device", type=DEVICE, default="cpu", show_default=True,
        help="torch device, e.g. cpu or cuda."),
    option("Compute", "--engine", type=ENGINE_CHOICE, default="auto", show_default=True,
           help=ENGINE_HELP),
])


@click.command("localize", cls=SectionedCommand, sections=LOCALIZE_SECTIONS, epilog="""\b
Examples:
  seqvpr localize --map maps/summer -q winter/ --radius 1f --calibrate --target-precision 0.99
  seqvpr localize --map maps/summer -q winter2/ --radius 1f --out localised
  seqvpr localize --map maps/summer -q winter2/ --method hmm --radius 1f""")
@option("Input", "--map", "map_dir", required=True, type=click.Path(), help="A map folder (seqvpr map build).")
@option("Input", "-q", "--query", required=True, type=click.Path(),
        help="The query traversal, replayed frame by frame.")
@option("Input", "--frames", help="Keep query frames START:STOP (e.g. 17:2000).")
@localizer_options
@option("Ground truth and scoring", "--radius", help="Ground truth: within this distance (e.g. 25m, 2f).")
@option("Ground truth and scoring", "--ground-truth", "gt_file", type=click.Path(),
        help="Ground truth file (GT .mat, VPR-Bench .npy or a dense matrix).")
@option("Ground truth and scoring", "--gt-layout", type=click.Choice(["ref-query", "query-ref"]),
        help="A dense ground-truth matrix's layout when its shape does not say (a square one).")
@option("Ground truth and scoring", "--calibrate", is_flag=True,
        help="Pick the threshold reaching --target-precision on this query, store it with the map (needs ground "
             "truth) and write the run at it.")
@option("Ground truth and scoring", "--target-precision", type=FRACTION, default=0.99, show_default=True,
        help="With --calibrate: the precision the threshold must reach.")
@option("Ground truth and scoring", "--k", "ks", default="1,5,10,20", show_default=True, help="Recall@K values.")
@option("Localiser", "--resume-state", type=click.Path(), help="Start from a saved localiser state.")
@option("Output", "--save-state", type=OUT_FILE, help="Save the localiser's state after the last frame.")
@option("Output", "--out", "out_dir", default="seqvpr-localize", show_default=True, type=OUT_FOLDER,
        help="Folder for stream.csv, run.json and report/.")
@option("Output", "--json", "as_json", is_flag=True, help="Print one JSON object instead of the summary.")
@section("Input", bag_topic_options("query"))
@locks_output("out_dir")
def localize(**options: Any) -> None:
    """Replay QUERY frame by frame through a localiser over MAP: one estimate, score and status per frame."""
    from seqvpr.data.sources import load_traversal
    from seqvpr.data.traversal import slice_frame_range
    from seqvpr.io import check_out_folder, check_output_apart
    from seqvpr.localization.replay import replay
    from seqvpr.evaluation.ground_truth import resolve_ground_truth

    k_values = parse_ks(options["ks"])
    if options["calibrate"] and not (options["radius"] or options["gt_file"]):
        raise SeqvprError("--calibrate needs ground truth: give --radius or --ground-truth")
    if not 0.0 < options["target_precision"] <= 1.0:
        raise SeqvprError(f"--target-precision must be in (0, 1], got {options['target_precision']}")
    inputs = [options[k] for k in ("map_dir", "query", "gt_file", "resume_state", "save_state")]
    check_out_folder(options["out_dir"], RUN_FILE, inputs + list(options["model_dirs"]))
    if options["save_state"]:  # resuming from the file it saves to is the documented update in place
        check_output_apart(options["save_state"], [options["query"], options["gt_file"]], "--save-state")
    from seqvpr import distributed

    with distributed.process_group(options["device"]) as world:  # under torchrun over a sharded map: ranks share it
        localizer = open_localizer(options, max(k_values))
        if options["save_state"]:
            localizer.check_state_path(options["save_state"])  # not on the map or a model: before any frame
        query = slice_frame_range(load_traversal(options["query"], "query"), options["frames"])
        gt = resolve_ground_truth(localizer.saved.frames, query, options["radius"], options["gt_file"],
                                  layout=options["gt_layout"]) \
            if (options["radius"] or options["gt_file"]) else None
        if options["resume_state"]:
            localizer.restore(options["resume_state"])
        run = replay(localizer, query, tqdm_progress(len(query), "localize") if world.is_root else None)
    if not world.is_root:  # rank 0 reports and writes
        return
    if options["save_state"]:
        localizer.save_state(options["save_state"])
    if options["calibrate"]:
        run = _calibrate(options, localizer, run, gt)
    elif localizer.uses_default_threshold:
        warnings.warn(f"threshold {localizer.threshold:g} is {localizer.threshold_source}", SeqvprWarning)
    _report(options, localizer, run, gt, k_values)


def open_localizer(options: dict[str, Any], k: int):
    """The localiser the options describe (settings checked before any frame is read)."""
    from seqvpr.localization import Localizer
    from seqvpr.sequences.filter import FilterSettings

    steps = FilterSettings(options["min_step"], options["max_step"], options["floor"], options["sharpness"])
    return Localizer.open(options["map_dir"], list(options["model_dirs"]) or None, options["device"],
                          engine=options["engine"], method=options["method"],
                          seq_len=options["seq_len"], k=k, shortlist=options["shortlist"], history=options["history"],
                          nprobe=options["nprobe"], threshold=options["threshold"], lost_after=options["lost_after"],
                          exclusion=options["exclusion"], keyframe_distance=options["keyframe_distance"], filter=steps)


def _calibrate(options: dict[str, Any], localizer, run, gt):
    """Choose the threshold on this replay, store it in the map's localizer.json with what it was chosen on, and
    return the replay as it goes at that threshold (reported like any run)."""
    from datetime import datetime, timezone

    from seqvpr.localization.calibration import find_threshold
    from seqvpr.localization.localizer import calibration_source, store_calibration
    from seqvpr.localization.replay import correct_best, at_threshold

    positives = int((run.scored & gt.has_positive()).sum())
    found = find_threshold(run.score[run.scored], correct_best(run, gt)[run.scored], options["target_precision"],
                           positives)
    record = {"threshold": found.threshold, "target_precision": options["target_precision"],
              "precision": found.precision,
              "recall": found.recall, "reached": found.reached, "calibration": str(options["query"]),
              "query_frames": options["frames"], "ground_truth": _truth_text(options), "frames": int(run.scored.sum()),
              "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    store_calibration(options["map_dir"], localizer.settings, record)
    localizer.threshold, localizer.threshold_source = found.threshold, calibration_source(record)
    if not options["as_json"]:
        reached = "reached" if found.reached else "NOT reachable on this traversal (the threshold accepts nothing)"
        click.echo(f"calibrated: threshold {found.threshold:.4f} for precision >= {options['target_precision']}: {reached}; "
                   f"stored in {Path(options['map_dir']) / 'localizer.json'} for {localizer.settings.key()}\n"
                   "the figures below are on the frames it was chosen on", err=True)
    return at_threshold(run, found.threshold, localizer.settings.lost_after, localizer.threshold_source)


def _truth_text(options: dict[str, Any]) -> str | None:
    """The ground truth as given: ``radius R`` or the file."""
    return f"radius {options['radius']}" if options["radius"] else (str(options["gt_file"]) if options["gt_file"] else None)


def _report(options: dict[str, Any], localizer, run, gt, k_values) -> None:
    """--out as one folder (``seqvpr.io.atomic_folder``): stream.csv, the report page and run.json last, swapped in
    whole; the summary (or JSON) on stdout."""
    from seqvpr.io import atomic_folder
    from seqvpr.localization.replay import correct_best, score_replay, write_stream

    scores = score_replay(run, gt, k_values) if gt is not None else None
    summary = _summary(options, localizer, run, scores)
    with atomic_folder(Path(options["out_dir"]), RUN_FILE) as tmp:
        write_stream(tmp / "stream.csv", run, localizer.saved.frames, correct_best(run, gt) if gt is not None else None,
                     localizer.saved.sessions_of_rows)
        if scores is not None:
            _write_page(tmp / "report", summary, run, gt, localizer)
        (tmp / RUN_FILE).write_text(json.dumps(summary, indent=2))
    click.echo(json.dumps(summary) if options["as_json"] else _summary_text(summary))


def _summary(options: dict[str, Any], localizer, run, scores) -> dict[str, Any]:
    """What the replay did and, with ground truth, how well: everything run.json holds."""
    from seqvpr.localization.localizer import stored_calibration

    statuses = {s: int((run.status == s).sum()) for s in ("warming up", "localised", "uncertain", "lost")}
    calibration = stored_calibration(options["map_dir"], localizer.settings) if options["threshold"] is None else None
    summary: dict[str, Any] = {"map": options["map_dir"], "query": options["query"], "query_frames": options["frames"],
                               "ground_truth": _truth_text(options), "frames": len(run.best),
                               "settings": localizer.settings.key(), "threshold": run.threshold,
                               "threshold_source": run.threshold_source, "calibration": calibration,
                               "target_precision": None if calibration is None else calibration["target_precision"],
                               "status": statuses, "skipped_by_gating": int((~run.kept).sum())}
    if scores is None:
        return summary
    e = scores.evaluation
    summary.update({"recall": {str(k): v for k, v in e.recall.items()}, "pr_auc": e.pr.auc,
                    "recall_at_100_precision": e.pr.recall_at_100_precision, "queries_evaluated": e.queries_evaluated,
                    "localised_correct": scores.localized_correct, "localised_wrong": scores.localized_wrong,
                    "precision_of_localised": scores.precision, "recall_of_localised": scores.recall,
                    "time_to_correct": [{"frames": f, "seconds": s} for f, s in scores.time_to_correct],
                    "latency_ms": scores.latency})
    return summary


def _summary_text(s: dict[str, Any]) -> str:
    status = ", ".join(f"{k} {v}" for k, v in s["status"].items())
    lines = [f"{s['frames']} frames: {status}", f"threshold {s['threshold']:.4f}: {s['threshold_source']}"]
    if "recall" in s:
        recall = "  ".join(f"R@{k} {v:.3f}" for k, v in s["recall"].items())
        lines.append(f"{recall}  PR-AUC {s['pr_auc']:.3f}  R@100P {s['recall_at_100_precision']:.3f}")
        target = "" if s["target_precision"] is None else f" (target {s['target_precision']})"
        lines.append(f"localised: {s['localised_correct']} correct, {s['localised_wrong']} wrong: precision "
                     f"{s['precision_of_localised']:.3f}{target}, recall {s['recall_of_localised']:.3f}")
        first = s["time_to_correct"][0]
        lines.append("first correct localised estimate: " + ("never" if first["frames"] is None else
                     f"after {first['frames']} frames" + ("" if first["seconds"] is None else
                                                          f" ({first['seconds']:.1f} s)")))
        total = s["latency_ms"].get("total", {})
        lines.append("latency ms per frame: " + ", ".join(f"{k} {v:.2f}" for k, v in total.items()))
    return "\n".join(lines)


def _write_page(folder: Path, summary: dict[str, Any], run, gt, localizer) -> None:
    """The report page: the replay as plain arrays, the threshold and where it came from, the measures."""
    import numpy as np

    from seqvpr.evaluation.localization_report import (
        LocalizationTrace, describe_replay, localization_metric_rows, write_localization_report,
    )
    from seqvpr.localization.replay import STAGES, correct_best

    truth = np.array([p[len(p) // 2] if len(p) else -1 for p in (gt.positives_of(i) for i in range(len(run.best)))])
    trace = LocalizationTrace(run.query.frame_index, run.index, run.best, run.status, run.score, run.latency, STAGES,
                              correct_best(run, gt), truth, run.query.timestamps, localizer.saved.frames.positions,
                              run.query.positions)
    write_localization_report(folder, title="seqvpr localisation", summary=describe_replay(summary), trace=trace,
                              threshold=run.threshold, threshold_source=run.threshold_source,
                              metrics=localization_metric_rows(summary))
