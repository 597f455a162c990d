"""The report's matplotlib plots: Recall@K and precision-recall curves, and distance matrices with the GT band.

Figures are drawn on matplotlib's Agg canvas (no display needed) and written as PNGs at a fixed dpi. Matrices larger
than ``MAX_DRAWN`` on a side are block-reduced before drawing (minimum distance, any positive), so the low-distance
band and the ground-truth band both survive the reduction.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Colormap, to_hex
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import FixedLocator, NullLocator, ScalarFormatter

from seqvpr.errors import SeqvprError

DPI = 100
MAX_DRAWN = 1000  # largest number of rows / columns of a distance matrix that is drawn as is
CORRECT_COLOR = "#2ca02c"
WRONG_COLOR = "#d62728"
GT_COLOR = "#1f9bff"
NO_WINDOW_COLOR = "#d9d9d9"
LEGEND_COLUMNS = 2  # columns of the method legends below the curves

Extent = tuple[float, float, float, float]


@dataclass(frozen=True)
class MethodResult:
    """One row of the report: a method's name, Recall@K for K=1..K_max, its PR curve and summary figures."""

    name: str
    recall_at_k: dict[int, float]
    precision: np.ndarray
    recall: np.ndarray
    pr_auc: float
    recall_at_100_precision: float
    frame_precision: float = float("nan")  # share of the top-1 matches' per-frame correspondences that are right


@dataclass(frozen=True)
class DistanceView:
    """A distance matrix to draw: [n_query, n_reference] (NaN where no window), GT positives mask, top-1 path, and
    what its colours and axes show (the colour bar's and the axes' labels)."""

    title: str
    distances: np.ndarray
    positives: np.ndarray
    top1: np.ndarray
    correct: np.ndarray
    distance_label: str = "distance"
    query_label: str = "query frame"
    reference_label: str = "reference frame"


def check_distance_view(view: DistanceView) -> None:
    """Raise SeqvprError unless the matrix, mask and path of ``view`` agree in shape (before any drawing)."""
    d = np.asarray(view.distances)
    if d.ndim != 2:
        raise SeqvprError(f"distance view {view.title!r}: distances must be 2-D, got shape {d.shape}")
    if np.shape(view.positives) != d.shape:
        raise SeqvprError(f"distance view {view.title!r}: positives {np.shape(view.positives)} != distances {d.shape}")
    if np.shape(view.top1) != (d.shape[0],) or np.shape(view.correct) != (d.shape[0],):
        raise SeqvprError(f"distance view {view.title!r}: top1 and correct need shape ({d.shape[0]},)")
    top1 = np.asarray(view.top1)
    if len(top1) and (top1.min(initial=0) < -1 or top1.max(initial=-1) >= d.shape[1]):
        raise SeqvprError(f"distance view {view.title!r}: top1 holds a reference outside 0..{d.shape[1] - 1}")


def method_colors(names: Sequence[str]) -> dict[str, str]:
    """One distinct colour per method name, in order, so a method looks the same in the table and every plot:
    tab10 up to 10 methods, tab20 up to 20, else evenly spaced samples of turbo."""
    n = len(names)
    if n <= 10:
        rgba = [colormaps["tab10"](i) for i in range(n)]
    elif n <= 20:
        rgba = [colormaps["tab20"](i) for i in range(n)]
    else:
        rgba = list(colormaps["turbo"](np.linspace(0.0, 1.0, n)))
    return {name: to_hex(color) for name, color in zip(names, rgba)}


def legend_below(fig: Figure, ax: Axes, n_entries: int) -> None:
    """The axes' legend under the plot, outside the curves, in up to ``LEGEND_COLUMNS`` columns."""
    if n_entries:
        fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncol=min(n_entries, LEGEND_COLUMNS),
                   frameon=False, fontsize=8, handlelength=1.5, columnspacing=1.0)


def legend_height(n_entries: int) -> float:
    """Inches a figure grows by to hold a legend of ``n_entries`` below its axes."""
    return 0.25 * math.ceil(n_entries / LEGEND_COLUMNS)


def new_figure(width: float, height: float) -> Figure:
    """A figure on an Agg canvas (never a display) with constrained layout, at the report's dpi."""
    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: Path) -> None:
    """Write ``fig`` as a PNG at the report's dpi."""
    fig.savefig(path, format="png", dpi=DPI, facecolor="white")


# ----------------------------------------------------------------------------------------------- curves


def plot_recall_at_k(methods: Sequence[MethodResult], colors: dict[str, str], path: Path) -> None:
    """Recall@K against K, one line per method; log-x once K reaches 10 so the small Ks stay readable."""
    fig = new_figure(5.6, 4.2 + legend_height(len(methods)))
    ax = fig.add_subplot()
    k_max = 1
    for m in methods:
        ks = sorted(k for k, v in m.recall_at_k.items() if v is not None and math.isfinite(v))
        if not ks:
            continue
        k_max = max(k_max, ks[-1])
        marker = "o" if len(ks) <= 12 else None
        ax.plot(ks, [m.recall_at_k[k] for k in ks], label=m.name, color=colors[m.name], lw=2, marker=marker, ms=4)
    if k_max >= 10:
        ax.set_xscale("log")
        ticks = [t for t in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000) if t <= k_max]
        ax.xaxis.set_major_locator(FixedLocator(ticks))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_locator(NullLocator())
    ax.set_xlim(0.9 if k_max >= 10 else 0.5, k_max * 1.1 if k_max >= 10 else k_max + 0.5)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("K")
    ax.set_ylabel("recall")
    ax.set_title("Recall@K")
    ax.grid(True, which="major", alpha=0.3)
    legend_below(fig, ax, len(ax.get_legend_handles_labels()[0]))
    save_figure(fig, path)


def plot_pr_curves(methods: Sequence[MethodResult], colors: dict[str, str], path: Path) -> None:
    """Precision against recall of the top-1 match over all distance thresholds, one line per method."""
    fig = new_figure(5.6, 4.2 + legend_height(len(methods)))
    ax = fig.add_subplot()
    for m in methods:
        recall, precision = np.asarray(m.recall, float), np.asarray(m.precision, float)
        label = f"{m.name} (AUC {m.pr_auc:.3f})"
        if len(recall):
            # Start at recall 0 with the first precision so the curve reaches the y-axis.
            ax.plot(np.r_[0.0, recall], np.r_[precision[0], precision], label=label, color=colors[m.name], lw=2)
        else:
            ax.plot([], [], label=label, color=colors[m.name], lw=2)
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_title("Precision–recall (top-1 match)")
    ax.grid(True, alpha=0.3)
    legend_below(fig, ax, len(methods))
    save_figure(fig, path)


# ----------------------------------------------------------------------------------------------- distance matrices


def block_steps(shape: tuple[int, int], limit: int = MAX_DRAWN) -> tuple[int, int]:
    """Rows and columns per drawn cell so that neither side of the drawn matrix exceeds ``limit``."""
    return max(1, math.ceil(shape[0] / limit)), max(1, math.ceil(shape[1] / limit))


def block_reduce(a: np.ndarray, steps: tuple[int, int], fill: Any, reduce: Callable[..., np.ndarray]) -> np.ndarray:
    """Reduce ``a`` over blocks of ``steps`` cells (edges padded with ``fill``), e.g. min keeps a thin valley."""
    sq, sr = steps
    if sq == 1 and sr == 1:
        return a
    q, r = a.shape
    padded = np.full((math.ceil(q / sq) * sq, math.ceil(r / sr) * sr), fill, dtype=a.dtype)
    padded[:q, :r] = a
    return reduce(padded.reshape(padded.shape[0] // sq, sq, padded.shape[1] // sr, sr), axis=(1, 3))


def drawable_distances(distances: np.ndarray, steps: tuple[int, int]) -> np.ndarray:
    """Block-minimum of the finite distances (NaN where a block has none), so the low-distance band survives."""
    d = np.where(np.isfinite(distances), distances, np.inf).astype(np.float32, copy=False)
    small = block_reduce(d, steps, np.inf, np.min)
    return np.where(np.isfinite(small), small, np.nan)


def color_limits(drawn: np.ndarray) -> tuple[float, float]:
    """Robust colour range (1st to 99th percentile of finite values), so a few outliers don't wash it out."""
    finite = drawn[np.isfinite(drawn)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, [1, 99])
    return (float(lo), float(hi)) if hi > lo else (float(lo) - 0.5, float(lo) + 0.5)


def plot_distance_view(view: DistanceView, path: Path) -> None:
    """The distance matrix (query rows down, reference columns across), GT band outline and the top-1 path."""
    distances = np.asarray(view.distances, dtype=float)
    positives = np.asarray(view.positives, dtype=bool)
    top1, correct = np.asarray(view.top1, dtype=np.int64), np.asarray(view.correct, dtype=bool)
    n_q, n_r = distances.shape
    steps = block_steps((n_q, n_r))
    drawn = drawable_distances(distances, steps)
    pos_drawn = block_reduce(positives, steps, False, np.any)
    # Extent in original frame numbers: cell (i, j) of the drawn matrix covers rows i*sq.. and columns j*sr..
    h, w = drawn.shape
    extent = (-0.5, w * steps[1] - 0.5, h * steps[0] - 0.5, -0.5)

    aspect = n_q / max(n_r, 1)
    fig = new_figure(7.0, float(np.clip(7.0 * aspect, 4.5, 7.5)) + 0.4)
    ax = fig.add_subplot()
    _draw_matrix(fig, ax, drawn, extent, view.distance_label)
    handles = _draw_positives(ax, pos_drawn, steps, extent)
    handles += _draw_top1(ax, top1, correct, n_q)
    if (~np.isfinite(distances)).all(axis=1).any():
        handles.append(Patch(facecolor=NO_WINDOW_COLOR, edgecolor="#999999", label="no distance"))

    ax.set_xlim(-0.5, n_r - 0.5)
    ax.set_ylim(n_q - 0.5, -0.5)
    ax.set_xlabel(view.reference_label)
    ax.set_ylabel(view.query_label)
    ax.set_title(_distance_title(view.title, steps))
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 4), frameon=False, fontsize=9)
    save_figure(fig, path)


def _draw_matrix(fig: Figure, ax: Axes, drawn: np.ndarray, extent: Extent, label: str) -> None:
    """The (block-reduced) distances as an image with a colour bar saying what they are (``label``); undefined cells
    in the 'no distance' grey."""
    vmin, vmax = color_limits(drawn)
    image = ax.imshow(
        np.ma.masked_invalid(drawn), cmap=_matrix_colormap(), vmin=vmin, vmax=vmax, origin="upper", extent=extent,
        aspect="auto", interpolation="antialiased",
    )
    fig.colorbar(image, ax=ax, label=textwrap.fill(label, 45), shrink=0.9, pad=0.02)


def _draw_positives(ax: Axes, pos_drawn: np.ndarray, steps: tuple[int, int], extent: Extent) -> list[Artist]:
    """A translucent blue overlay (outlined where 2-D) over the GT positives; its legend entry, if there are any."""
    if not pos_drawn.any():
        return []
    h, w = pos_drawn.shape
    overlay = np.zeros((h, w, 4), dtype=np.float32)
    overlay[pos_drawn] = (*_rgb(GT_COLOR), 0.28)
    ax.imshow(overlay, origin="upper", extent=extent, aspect="auto", interpolation="nearest")
    if h > 1 and w > 1:
        xs = np.arange(w) * steps[1] + (steps[1] - 1) / 2
        ys = np.arange(h) * steps[0] + (steps[0] - 1) / 2
        ax.contour(xs, ys, pos_drawn.astype(np.float32), levels=[0.5], colors=[GT_COLOR], linewidths=0.8)
    return [Patch(facecolor=(*_rgb(GT_COLOR), 0.35), edgecolor=GT_COLOR, label="ground-truth positives")]


def _draw_top1(ax: Axes, top1: np.ndarray, correct: np.ndarray, n_q: int) -> list[Artist]:
    """Each query's top-1 reference as a green (correct) or red (wrong) dot; legend entries with their counts."""
    rows = np.arange(n_q)
    has = top1 >= 0
    size = float(np.clip(3000.0 / max(n_q, 1), 1.5, 14.0))
    handles: list[Artist] = []
    # Wrong matches are drawn last and larger: they are the few points worth finding.
    for mask, color, label, scale in (
        (has & correct, CORRECT_COLOR, "top-1 correct", 1.0),
        (has & ~correct, WRONG_COLOR, "top-1 wrong", 2.0),
    ):
        if mask.any():
            ax.scatter(top1[mask], rows[mask], s=size * scale, c=color, marker="o", linewidths=0, zorder=3)
        handles.append(Line2D([], [], ls="", marker="o", ms=6, color=color, label=f"{label} ({int(mask.sum())})"))
    return handles


def _distance_title(title: str, steps: tuple[int, int]) -> str:
    """The view's title wrapped to 70 columns, noting the block size when the matrix was reduced to be drawn."""
    wrapped = textwrap.fill(title, 70)
    if steps != (1, 1):
        wrapped += f"\n(each pixel: minimum over {steps[0]}×{steps[1]} frames)"
    return wrapped


def _matrix_colormap() -> Colormap:
    """Dark = close, light = far, grey where undefined; green/red dots and the blue band stay visible on it."""
    return colormaps["bone"].with_extremes(bad=NO_WINDOW_COLOR)


def _rgb(hex_color: str) -> tuple[float, float, float]:
    """'#rrggbb' as three floats in 0..1."""
    v = hex_color.lstrip("#")
    return tuple(int(v[i : i + 2], 16) / 255 for i in (0, 2, 4))  # type: ignore[return-value]
