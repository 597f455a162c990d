"""``seqvpr loops``: loop closures within a drive (several drives: sessions), written as ``loops.csv``, a stamp-pair
edge file and ``run.json``, with recall at 100 % precision and PR-AUC where ground truth exists. Parse, call the
library (``seqvpr.localization.loops``: ``loops``), print."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from seqvpr.cli.help import SectionedCommand, option, section
from seqvpr.cli.options import (
    COUNT, DEVICE, FINITE, NONNEGATIVE, OUT_FOLDER, bag_topic_options, extraction_options, frame_description,
    locks_output,
)
from seqvpr.cli.progress import tqdm_progress

LOOPS_SECTIONS = ("Input", "Method", "Loops", "Descriptors", "Ground truth and scoring", "Output", "Compute")
LOOPS_EPILOG = """\b
Examples:
  seqvpr loops run.bag --topic /camera/image_raw --exclude 30s --out loops/
  seqvpr loops monday/ tuesday/ --descriptor efficientnet-lite0 -L 10 --radius 15m --out loops/
  seqvpr loops drive.npz --exclude 200f --radius 2f --out loops/
  seqvpr loops long_drive.npz --shortlist 10 --out loops/
"""


@click.command(cls=SectionedCommand, sections=LOOPS_SECTIONS, epilog=LOOPS_EPILOG)
@click.argument("sources", nargs=-1, required=True)
@option("Output", "--out", "out_dir", required=True, type=OUT_FOLDER, help="The run folder to write.")
@option("Input", "--frames", help="Keep source frames START:STOP of every source (e.g. 17:601).")
@option("Method", "--method", type=click.Choice(["matching", "single", "seqmatchnet"]), default="matching",
        show_default=True, help="matching: causal sequence matching; single: one frame; seqmatchnet: through --model.")
@option("Method", "-L", "--seq-len", type=COUNT, default=5, show_default=True, help="Frames of a causal window.")
@option("Method", "--model", "model_dirs", type=click.Path(), multiple=True,
        help="A JIST or CosPlace model that describes the images, and/or a SeqMatchNet model (repeatable).")
@option("Loops", "--exclude", help="The recent past a loop may not come from: seconds, frames or metres travelled "
        "before the frame, e.g. 30s, 200f or 50m.  [default: 30s where the drive has timestamps, else 100f]")
@option("Loops", "--threshold", type=FINITE, help="Score a loop needs to be accepted.  [default: the method's, 0.1]")
@option("Loops", "--exclusion", type=NONNEGATIVE, default=10, show_default=True,
        help="Frames around the best that are not 'another place' for the score.")
@option("Loops", "--shortlist", type=NONNEGATIVE, default=0, show_default=True,
        help="For long drives: each frame's candidates are the windows its frames' S nearest eligible frames place "
             "(a frame index that grows with the drive), re-ranked exactly: O(N S) instead of every earlier window "
             "(0).")
@option("Loops", "--shortlist-index", default="hnsw:32", show_default=True,
        help="The growing frame index of --shortlist: hnsw:M (approximate, fast) or flat (exact).")
@option("Ground truth and scoring", "--radius",
        help="A match within this of the frame is right (25m with positions, 2f by frame index); adds the PR "
             "curve, recall at 100 % precision and PR-AUC.")
@option("Output", "--report", is_flag=True, help="Also write DIR/report/index.html: the trajectory with the "
        "accepted loops as edges (right green, wrong red) and the PR curve.")
@section("Descriptors", extraction_options)
@option("Compute", "--device", type=DEVICE, default="cpu", show_default=True, help="torch device, e.g. cpu or cuda.")
@section("Input", bag_topic_options("sources"))
@locks_output("out_dir")
def loops(sources: tuple[str, ...], out_dir: str, frames: str | None, method: str, seq_len: int,
          model_dirs: tuple[str, ...], exclude: str | None, threshold: float | None, exclusion: int,
          shortlist: int, shortlist_index: str, radius: str | None, report: bool, device: str, **options: Any) -> None:
    """Find loop closures in SOURCES: for each frame, the best earlier frame outside --exclude by causal sequence
    matching (each source a session, in time order; earlier sessions are eligible whole). Writes loops.csv (a row
    per frame), loops_tum.txt (accepted loops as stamp pairs) and run.json."""
    from seqvpr.localization.loops import loops as find_drive_loops
    from seqvpr.io import check_out_folder
    from seqvpr.localization.loop_files import RUN_FILE, loop_summary, write_loops

    check_out_folder(out_dir, RUN_FILE, [*sources, *model_dirs])
    description, extraction = frame_description(options, device)
    found, scored = find_drive_loops(sources, method=method, seq_len=seq_len, exclude=exclude, exclusion=exclusion,
                                     shortlist=shortlist, shortlist_index=shortlist_index,
                                     threshold=threshold, radius=radius, models=model_dirs or None,
                                     description=description, frames=frames, progress=tqdm_progress, **extraction)
    write_loops(out_dir, found, scored, {"sources": list(sources)}, report)
    click.echo(summary_text(loop_summary(found, scored)))
    click.echo(f"wrote {out_dir}" + (f" (report: {Path(out_dir) / 'report' / 'index.html'})" if report else ""))


def summary_text(summary: dict[str, Any]) -> str:
    """The run in a few lines."""
    shortlist = summary.get("shortlist")
    lines = [f"frames {summary['frames']} in {len(summary['sessions'])} session(s), {summary['method']} L="
             f"{summary['seq_len']}" + (f" (shortlist {shortlist['per_frame']}, {shortlist['index']})" if shortlist
                                        else "") +
             f", exclude {summary['exclude']}: {summary['accepted']} loops accepted "
             f"(score >= {summary['threshold']:g})"]
    if "radius" in summary:
        lines.append(f"within {summary['radius']}: {summary['true_revisits']} frames revisit, "
                     f"{summary['accepted_correct']} accepted loops right; recall at 100% precision "
                     f"{summary['recall_at_100_precision']:.3f}, PR-AUC {summary['pr_auc']:.3f}")
    return "\n".join(lines)
