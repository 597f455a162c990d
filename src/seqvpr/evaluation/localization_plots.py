"""The localisation report's plots: a replay on the map (estimates at their map frame's position, coloured by
status) and over time (estimate against ground truth, score against the threshold, latency).

A frame's *category* is its status, with "localised" split by whether its map frame is correct: the one colour key
of every plot and of the page's status table, so a colour means the same everywhere.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection

from seqvpr.evaluation.plots import CORRECT_COLOR, GT_COLOR, WRONG_COLOR, new_figure, save_figure

STATUSES = ("warming up", "localised", "uncertain", "lost")
MAP_COLOR = "#9e9e9e"


@dataclass(frozen=True)
class Category:
    """One colour key entry: a status (or localised and correct / wrong / without ground truth), how it is drawn."""

    name: str
    status: str
    color: str
    marker: str


CATEGORIES = (
    Category("localised, correct", "localised", CORRECT_COLOR, "o"),
    Category("localised, wrong", "localised", WRONG_COLOR, "o"),
    Category("localised, no true place (wrong)", "localised", "#7f0000", "o"),
    Category("localised", "localised", "#333333", "o"),
    Category("uncertain", "uncertain", "#ff9f1c", "o"),
    Category("lost", "lost", "#7b3294", "x"),
    Category("warming up", "warming up", "#bdbdbd", "o"),
)
BY_NAME = {c.name: c for c in CATEGORIES}


def categories(status: np.ndarray, correct: np.ndarray | None, truth: np.ndarray | None) -> np.ndarray:
    """Each frame's category name: its status, localised split into correct / wrong (``correct``) and no ground
    truth (``truth`` < 0: no true map frame); unsplit without ``correct``."""
    out = np.asarray(status, dtype=object).copy()
    localized = out == "localised"
    if correct is not None:
        correct = np.asarray(correct, dtype=bool)
        out[localized & correct] = "localised, correct"
        out[localized & ~correct] = "localised, wrong"
        if truth is not None:
            out[localized & (np.asarray(truth) < 0)] = "localised, no true place (wrong)"
    return out


def category_counts(cats: np.ndarray) -> dict[str, int]:
    """Frames per category, in the colour key's order, categories with no frame left out."""
    return {c.name: int((cats == c.name).sum()) for c in CATEGORIES if (cats == c.name).any()}


def legend_label(name: str, count: int) -> str:
    """A colour key entry: the category and its number of frames, e.g. 'uncertain (12)'."""
    return f"{name} ({count})"


def placed_rows(estimate: np.ndarray, best: np.ndarray) -> np.ndarray:
    """The map row a frame is drawn at: its estimate, else (lost) the best map frame it no longer names, else -1."""
    return np.where(np.asarray(estimate) >= 0, estimate, best).astype(np.int64)


# ----------------------------------------------------------------------------------------------- on the map


@dataclass(frozen=True)
class LocalizationTrace:
    """A replay, one entry per query frame: its frame number (and seconds, with timestamps), the map row the
    localiser names (-1: none) and its best one, status, score, latency [n, stages] in ms, whether the best map row
    is correct and a true map row (-1: no ground truth) when known; the map's and the query's positions [.., 2]."""

    frames: np.ndarray
    estimate: np.ndarray
    best: np.ndarray
    status: np.ndarray
    score: np.ndarray
    latency: np.ndarray
    stages: tuple[str, ...]
    correct: np.ndarray | None = None
    truth: np.ndarray | None = None
    seconds: np.ndarray | None = None
    map_positions: np.ndarray | None = None
    query_positions: np.ndarray | None = None

    def categories(self) -> np.ndarray:
        """Each frame's colour key entry: its status, localised split by correctness where known."""
        return categories(self.status, self.correct, self.truth)

    def rows(self) -> np.ndarray:
        """The map row each frame is drawn at (its estimate, else the best one it no longer names; -1: none)."""
        return placed_rows(self.estimate, self.best)

    def time_axis(self) -> tuple[np.ndarray, str]:
        """Seconds since the first frame when the query has timestamps, else its frame numbers; and the label."""
        if self.seconds is not None:
            seconds = np.asarray(self.seconds, dtype=float)
            return seconds - seconds[0], "time since the first query frame (s)"
        return np.asarray(self.frames), "query frame"


def plot_map_view(trace: LocalizationTrace, path: Path) -> list[str]:
    """The map's positions as a grey line, the query's true positions in blue where known, and each estimate at
    its map frame's position coloured by category; returns the colour key's labels (with counts)."""
    assert trace.map_positions is not None
    map_positions = np.asarray(trace.map_positions, dtype=float)[:, :2]
    fig = new_figure(9.5, 7.0)
    ax = fig.add_subplot()
    ax.plot(map_positions[:, 0], map_positions[:, 1], "-", color=MAP_COLOR, lw=3, alpha=0.6, label="map", zorder=1)
    if trace.query_positions is not None:
        truth = np.asarray(trace.query_positions, dtype=float)[:, :2]
        ax.plot(truth[:, 0], truth[:, 1], "-", color=GT_COLOR, lw=1, label="query, true position", zorder=2)
    rows, cats = trace.rows(), trace.categories()
    if trace.query_positions is not None:
        _draw_errors(ax, map_positions, rows, cats, np.asarray(trace.query_positions, dtype=float)[:, :2])
    labels = _draw_categories(ax, lambda mask: map_positions[rows[mask]].T, rows, cats)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Estimates on the map (each at its map frame's position)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False, fontsize=9, markerscale=2)
    save_figure(fig, path)
    return labels


def _draw_errors(ax: Axes, map_positions: np.ndarray, rows: np.ndarray, cats: np.ndarray, truth: np.ndarray) -> None:
    """A thin red line from each wrong localised estimate to where the query truly was: how far off it is."""
    wrong = np.flatnonzero((cats == "localised, wrong") & (rows >= 0))
    if len(wrong):
        segments = np.stack([map_positions[rows[wrong]], truth[wrong]], axis=1)
        ax.add_collection(LineCollection(segments, colors=WRONG_COLOR, linewidths=0.8, alpha=0.7, zorder=3,
                                         label="wrong estimate → true position"))


def _draw_categories(ax: Axes, where, rows: np.ndarray, cats: np.ndarray) -> list[str]:
    """Scatter each category's frames that have a map row at ``where(mask)`` (x, y); a legend entry for every
    category with frames, counting all of them (drawn or not, e.g. warming up)."""
    labels = []
    for name, count in category_counts(cats).items():
        c = BY_NAME[name]
        mask = (cats == name) & (rows >= 0)
        x, y = where(mask) if mask.any() else ([], [])
        label = legend_label(name, count)
        ax.scatter(x, y, s=14 if c.marker == "x" else 10, c=c.color, marker=c.marker, linewidths=1 if c.marker == "x"
                   else 0, label=label, zorder=4 if name == "localised, wrong" else 3)
        labels.append(label)
    return labels


# ----------------------------------------------------------------------------------------------- over time


def plot_over_time(trace: LocalizationTrace, threshold: float, threshold_source: str, path: Path) -> list[str]:
    """Three panels over the replay: the map frame of each estimate (by category) against the true one, the score
    against the threshold (labelled with where it came from), and the latency per frame; returns the colour key's
    labels (with counts)."""
    fig = new_figure(11.0, 9.0)
    top, middle, bottom = fig.subplots(3, 1, sharex=True, height_ratios=(3.0, 1.4, 1.4))
    x, x_label = trace.time_axis()
    if trace.truth is not None and (trace.truth >= 0).any():
        has = trace.truth >= 0
        top.plot(x[has], trace.truth[has], ".", color=GT_COLOR, ms=2, label="true map frame", zorder=2)
    rows = trace.rows()
    labels = _draw_categories(top, lambda mask: (x[mask], rows[mask]), rows, trace.categories())
    top.set_ylabel("map frame (row of the map)")
    top.set_title("Estimate against ground truth")
    _score_panel(middle, x, trace.score, threshold, threshold_source)
    _latency_panel(bottom, x, trace.latency, trace.stages)
    bottom.set_xlabel(x_label)
    for ax in (top, middle, bottom):
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False, fontsize=9, markerscale=2)
    save_figure(fig, path)
    return labels


def _score_panel(ax: Axes, x: np.ndarray, score: np.ndarray, threshold: float, source: str) -> None:
    """The score per frame and the threshold, labelled with its value and where it came from."""
    ax.plot(x, score, color="#444444", lw=0.8, label="score")
    label = textwrap.fill(f"threshold {threshold:.4g}: {source}", 34)
    ax.axhline(threshold, color=WRONG_COLOR, lw=1.0, ls="--", label=label)
    ax.set_ylabel("score (higher: surer)")


def _latency_panel(ax: Axes, x: np.ndarray, latency: np.ndarray, stages: Sequence[str]) -> None:
    """Total milliseconds per frame, and describing the frame where that took any time."""
    latency = np.asarray(latency, dtype=float)
    names = list(stages)
    for stage, color, style in (("describe", "#1f77b4", "--"), ("total", "#222222", "-")):  # total drawn on top
        if stage in names and (stage == "total" or latency[:, names.index(stage)].any()):
            ax.plot(x, latency[:, names.index(stage)], style, color=color, lw=0.9, label=f"{stage} (ms)")
    ax.set_ylabel("latency (ms per frame)")
    ax.set_ylim(bottom=0.0)
