"""What ``seqvpr loops --out DIR`` writes, committed as one folder (``io.atomic_folder``; ``run.json`` last):

    DIR/loops.csv       one row per frame: frame, frame_name, session, match, match_name, match_session, distance,
                        score, accepted, correct (empty without ground truth)
    DIR/loops_tum.txt   the accepted loops as stamp pairs (``stamp stamp score``; frame rows where the drive has
                        no timestamps; over several sessions, the two sessions' names follow): a loop closure
                        carries no relative pose, and a back-end's own front end (scan or image registration)
                        turns a pair of stamps into a pose-graph edge
    DIR/run.json        settings, sessions, counts, recall at 100 % precision, PR-AUC and the PR curve
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.io import atomic_folder
from seqvpr.localization.loops import Loops, ScoredLoops

RUN_FILE = "run.json"
LOOPS_FILE = "loops.csv"
EDGES_FILE = "loops_tum.txt"
COLUMNS = ("frame", "frame_name", "session", "match", "match_name", "match_session", "distance", "score", "accepted",
           "correct")


def loop_summary(loops: Loops, scored: ScoredLoops | None) -> dict[str, Any]:
    """What ``run.json`` and the command print: settings, sessions, counts and, with ground truth, the figures."""
    settings = loops.settings
    summary: dict[str, Any] = {
        "method": settings.method, "seq_len": settings.window, "exclude": str(loops.exclusion),
        "exclusion": settings.exclusion, "threshold": settings.accept, "frames": int(len(loops.match)),
        "sessions": [{"name": name, "frames": int((loops.drive.sessions == s).sum())}
                     for s, name in enumerate(loops.drive.session_names)],
        "with_candidates": int((loops.match >= 0).sum()), "accepted": int(loops.accepted.sum()),
    }
    if settings.shortlist:
        summary["shortlist"] = {"per_frame": settings.shortlist, "index": settings.shortlist_index}
    if scored is not None:
        summary.update({
            "radius": scored.radius, "true_revisits": int(scored.revisit.sum()),
            "accepted_correct": int((loops.accepted & scored.correct).sum()),
            "recall_at_100_precision": round(scored.pr.recall_at_100_precision, 6), "pr_auc": round(scored.pr.auc, 6),
            "pr_curve": {"score": (-scored.pr.thresholds).round(6).tolist(), "precision": scored.pr.precision.round(6)
                         .tolist(), "recall": scored.pr.recall.round(6).tolist()},
        })
    return summary


def write_loops(out: str | Path, loops: Loops, scored: ScoredLoops | None, record: dict[str, Any],
                report: bool = False) -> Path:
    """The run's folder at ``out``, replacing an earlier run's (never a folder of something else); with ``report``,
    ``report/index.html`` too (the trajectory with its loops, the PR curve)."""
    with atomic_folder(out, RUN_FILE) as tmp:
        write_loops_csv(tmp / LOOPS_FILE, loops, scored)
        write_edges(tmp / EDGES_FILE, loops)
        summary = loop_summary(loops, scored)
        if report:
            write_report(tmp / "report", loops, scored, summary)
        (tmp / RUN_FILE).write_text(json.dumps({**record, **summary}, indent=2) + "\n")
    return Path(out)


def write_report(folder: Path, loops: Loops, scored: ScoredLoops | None, summary: dict[str, Any]) -> Path:
    """The loop page: the drive with its accepted loops (by position where it has positions) and the measures."""
    from seqvpr.evaluation.loop_report import LoopTrace, write_loop_report

    frames = loops.drive.frames
    positioned = frames.positions is not None
    where = np.asarray(frames.positions, dtype=np.float64)[:, :2] if positioned else np.zeros((len(frames), 2))
    trace = LoopTrace(where, loops.match, loops.accepted, None if scored is None else scored.correct,
                      None if scored is None else scored.pr.precision, None if scored is None else scored.pr.recall,
                      positioned)
    keys = ("frames", "with_candidates", "accepted", "true_revisits", "accepted_correct", "recall_at_100_precision",
            "pr_auc", "exclude", "threshold")
    metrics = [(key.replace("_", " "), str(summary[key])) for key in keys if key in summary]
    text = f"{summary['method']} L={summary['seq_len']} over {len(summary['sessions'])} session(s)"
    return write_loop_report(folder, title="seqvpr loops", summary=text, trace=trace, metrics=metrics)


def write_loops_csv(path: Path, loops: Loops, scored: ScoredLoops | None) -> None:
    frames = loops.drive.frames
    names = frames.image_names() or [str(i) for i in frames.frame_index]
    sessions = loops.drive.sessions
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for i, match in enumerate(loops.match.tolist()):
            found = match >= 0
            writer.writerow([i, names[i], loops.drive.session_names[sessions[i]], match if found else "",
                             names[match] if found else "",
                             loops.drive.session_names[sessions[match]] if found else "",
                             f"{loops.distance[i]:.6g}" if found else "", f"{loops.score[i]:.6g}",
                             int(loops.accepted[i]), "" if scored is None or not found else int(scored.correct[i])])


def write_edges(path: Path, loops: Loops) -> None:
    """Accepted loops as ``stamp_frame stamp_match score`` lines (frame rows without timestamps); over several
    sessions, each line ends with the two sessions' names too (their clocks may overlap)."""
    stamps, sessions, names = loops.drive.frames.timestamps, loops.drive.sessions, loops.drive.session_names
    key = (lambda row: f"{float(stamps[row]):.9f}") if stamps is not None else str  # noqa: E731
    several = len(names) > 1
    with open(path, "w") as handle:
        what = "timestamps (s)" if stamps is not None else "frame rows (the drive has no timestamps)"
        handle.write(f"# seqvpr loop closures: {what} of the frame and of its match, and the score"
                     + (", then the session of each" if several else "") + "\n")
        for i in np.flatnonzero(loops.accepted).tolist():
            match = int(loops.match[i])
            tail = f" {_token(names[sessions[i]])} {_token(names[sessions[match]])}" if several else ""
            handle.write(f"{key(i)} {key(match)} {loops.score[i]:.6f}{tail}\n")


def _token(name: str) -> str:
    """A session's name as one whitespace-free token."""
    return "_".join(str(name).split()) or "_"
