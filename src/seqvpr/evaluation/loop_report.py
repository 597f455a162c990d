"""The loop-closure report: a drive's trajectory with its accepted loops drawn as edges (right green, wrong red,
grey without ground truth) and the precision-recall curve over the score, from plain arrays (what
``seqvpr.localization.loop_files`` writes for ``seqvpr loops --report``). ``index.html`` and its PNGs are written
atomically.
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from seqvpr.evaluation.localization_report import metrics_table_html
from seqvpr.evaluation.report import figure_html, page_html, summary_html
from seqvpr.io import atomic_folder

RIGHT, WRONG, UNKNOWN = "#2e7d32", "#c62828", "#757575"


@dataclass(frozen=True)
class LoopTrace:
    """One drive's loops as arrays: ``where`` [N, 2] (positions; unused without them), each frame's
    ``match`` (-1 none), ``accepted``, ``correct`` (None without ground truth), and the PR curve (None likewise)."""

    where: np.ndarray
    match: np.ndarray
    accepted: np.ndarray
    correct: np.ndarray | None
    precision: np.ndarray | None
    recall: np.ndarray | None
    positioned: bool


def write_loop_report(out_dir: Path, *, title: str, summary: str, trace: LoopTrace,
                      metrics: Sequence[tuple[str, str]]) -> Path:
    """``out_dir/index.html``: the summary, the measures, the trajectory with the loops and the PR curve."""
    with atomic_folder(Path(out_dir), "index.html") as tmp:
        sections = [f"<h1>{html.escape(title)}</h1>", summary_html(summary), "<h2>Measures</h2>",
                    metrics_table_html(metrics), "<h2>The drive and its loops</h2>"]
        plot_loops(trace, tmp / "loops.png")
        sections.append(figure_html("loops.png", "the trajectory with accepted loops", (
            "With positions: the drive (grey) and each accepted loop as an edge from the frame to its match. "
            "Without: each frame's best earlier frame (grey) and the accepted ones over it. Green right, red wrong, "
            "grey without ground truth.")))
        if trace.precision is not None and len(trace.precision):
            plot_pr(trace, tmp / "pr.png")
            sections += ["<h2>Precision and recall</h2>", figure_html("pr.png", "precision-recall of loop closures", (
                "Precision against recall as the score threshold falls: a frame with a true revisit is a positive; "
                "an accepted match anywhere else is a false positive."))]
        (tmp / "index.html").write_text(page_html(title, sections), encoding="utf-8")
    return Path(out_dir) / "index.html"


def plot_loops(trace: LoopTrace, path: Path) -> None:
    """With positions, the trajectory and one edge per accepted loop; without, each frame's match against the frame
    (the revisit shows as a line parallel to the diagonal), accepted loops coloured."""
    from seqvpr.evaluation.plots import new_figure, save_figure

    fig = new_figure(7.0, 5.0)
    ax = fig.add_subplot(1, 1, 1)
    rows = np.flatnonzero(trace.accepted & (trace.match >= 0))
    colors = [UNKNOWN if trace.correct is None else (RIGHT if trace.correct[r] else WRONG) for r in rows]
    if trace.positioned:
        _draw_edges(ax, trace, rows, colors)
    else:
        _draw_matches(ax, trace, rows, colors)
    ax.set_title(f"{len(rows)} accepted loops")
    save_figure(fig, path)


def _draw_edges(ax: Any, trace: LoopTrace, rows: np.ndarray, colors: list[str]) -> None:
    from matplotlib.collections import LineCollection

    ax.plot(trace.where[:, 0], trace.where[:, 1], color="#bdbdbd", linewidth=1.0, zorder=1)
    if len(rows):
        segments = np.stack([trace.where[rows], trace.where[trace.match[rows]]], axis=1)
        ax.add_collection(LineCollection(segments, colors=colors, linewidths=0.8, alpha=0.8, zorder=2))
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    ax.set_aspect("equal", adjustable="datalim")


def _draw_matches(ax: Any, trace: LoopTrace, rows: np.ndarray, colors: list[str]) -> None:
    found = np.flatnonzero(trace.match >= 0)
    ax.scatter(found, trace.match[found], s=2, color="#bdbdbd", label="best earlier frame", zorder=1)
    if len(rows):
        ax.scatter(rows, trace.match[rows], s=8, c=colors, label="accepted loop", zorder=2)
    ax.set_xlabel("frame")
    ax.set_ylabel("matched earlier frame")
    ax.legend(loc="upper left", fontsize="small")


def plot_pr(trace: LoopTrace, path: Path) -> None:
    from seqvpr.evaluation.plots import new_figure, save_figure

    fig = new_figure(5.0, 4.0)
    ax = fig.add_subplot(1, 1, 1)
    ax.step(trace.recall, trace.precision, where="post", color="#1565c0")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    save_figure(fig, path)
