"""The localisation report: a replayed query, as plain arrays, drawn on the map and over time, with its measures
under readable names and its frames counted by status (the counts of the replay's summary, colour for colour).

``write_localisation_report`` takes a ``LocalisationTrace`` (one entry per query frame), the threshold and where it
came from, and the measures as (name, value) rows (``localisation_metric_rows`` makes them from a replay summary,
what ``seqvpr localize`` writes to run.json). It writes ``index.html`` and its PNGs atomically.
"""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any


from seqvpr.evaluation.localization_plots import (  # noqa: F401  (LocalisationTrace re-exported)
    BY_NAME, LocalizationTrace, category_counts, plot_map_view, plot_over_time,
)
from seqvpr.evaluation.report import figure_html, page_html, summary_html
from seqvpr.io import atomic_folder


#: run.json's measures under the names a reader knows, in the order the page lists them
METRIC_NAMES = {
    "frames": "Query frames replayed",
    "skipped_by_gating": "Frames skipped by keyframe gating",
    "queries_evaluated": "Frames scored against ground truth",
    "pr_auc": "PR-AUC (estimates ranked by score)",
    "recall_at_100_precision": "Recall at 100 % precision",
    "threshold": "Score threshold",
    "target_precision": "Target precision of the calibration",
    "localised_correct": "Localised estimates whose map frame is correct",
    "localised_wrong": "Localised estimates whose map frame is wrong (or that have no true place)",
    "precision_of_localised": "Precision of localised estimates (share whose map frame is correct)",
    "recall_of_localised": "Recall of localised estimates (correct localised / frames with a true place)",
}


def localization_metric_rows(summary: Mapping[str, Any]) -> list[tuple[str, str]]:
    """A replay summary's measures as (readable name, value) rows: counts, Recall@K, PR, the threshold and what it
    reaches, frames to the first correct localised estimate, latency percentiles."""
    rows = [(METRIC_NAMES[key], _format(summary[key])) for key in list(METRIC_NAMES)[:3] if key in summary]
    rows += [(f"Recall@{k}", _format(v)) for k, v in summary.get("recall", {}).items()]
    rows += [(METRIC_NAMES[key], f"{summary[key]:.4g}" if key == "threshold" else _format(summary[key]))
             for key in list(METRIC_NAMES)[3:] if summary.get(key) is not None]
    if summary.get("time_to_correct"):
        rows.append(("Frames to the first correct localised estimate (per start)",
                     "; ".join(_time_to_correct(t) for t in summary["time_to_correct"])))
    for stage, percentiles in summary.get("latency_ms", {}).items():
        rows.append((f"Latency, {stage} (ms)", ", ".join(f"{q} {v:.2f}" for q, v in percentiles.items())))
    return rows


def _format(value: Any) -> str:
    """A measure as shown: three decimals for fractions, whole numbers as they are."""
    return f"{value:.3f}" if isinstance(value, float) else str(value)


def _time_to_correct(entry: Mapping[str, Any]) -> str:
    """'never', or 'N frames' with the seconds when the query has timestamps."""
    if entry.get("frames") is None:
        return "never"
    seconds = entry.get("seconds")
    return f"{entry['frames']} frames" + ("" if seconds is None else f" ({seconds:.1f} s)")


def describe_replay(summary: Mapping[str, Any]) -> str:
    """The page's opening line: what was replayed against which map, with which localiser settings."""
    settings = summary.get("settings") or {}
    shown = ", ".join(f"{k} {v}" for k, v in settings.items() if not isinstance(v, (dict, list)))
    return (f"{summary.get('query')} replayed frame by frame against the map {summary.get('map')} "
            f"({summary.get('frames')} frames; localiser: {shown}).")


# ----------------------------------------------------------------------------------------------- the page


def status_table_html(counts: Mapping[str, int]) -> str:
    """Frames per status (localised split by correctness), each with the colour its frames have in the plots."""
    rows = "\n".join(
        f'<tr><td><span class="swatch" style="background:{BY_NAME[name].color}"></span>{html.escape(name)}</td>'
        f"<td>{count}</td></tr>" for name, count in counts.items()
    )
    return f'<table class="recall status"><thead><tr><th>Status</th><th>Frames</th></tr></thead>\n{rows}\n</table>'


def metrics_table_html(rows: Sequence[tuple[str, str]]) -> str:
    """The (measure, value) rows as a two-column table."""
    body = "\n".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in rows)
    return f'<table class="recall metrics"><thead><tr><th>Measure</th><th>Value</th></tr></thead>\n{body}\n</table>'


STATUS_NOTE = (
    "localised: the localiser stands behind this map frame (score at or above the threshold); uncertain: below it, "
    "no map frame named; lost: below it for a while, no map frame named; both drawn at the best-scoring map frame; "
    "warming up: the window is not full yet after a start (no estimate, not drawn)."
)


#: every run's report points at the interactive page ``seqvpr view RUN`` writes beside it
VIEWER_LINK = ('<h2>Step through it</h2><p><a href="../view/index.html">The interactive view</a>: every frame with '
               "its image, its estimate and the map frame it matched, the timeline to scrub, keys to step through the "
               "failures. <code>seqvpr view RUN</code> writes it (RUN/view/index.html, offline, no server).</p>")


def write_localization_report(
    out_dir: Path, *, title: str, summary: str, trace: LocalizationTrace, threshold: float, threshold_source: str,
    metrics: Sequence[tuple[str, str]],
) -> Path:
    """The localisation page ``out_dir/index.html``: ``summary``, the measures, frames per status, the replay on
    the map (when the map has positions) and over time; written atomically. ``threshold_source`` says where the
    threshold came from (e.g. 'calibrated on winter frames 0:500, radius 1f, target precision 0.99')."""
    with atomic_folder(Path(out_dir), "index.html") as tmp:
        sections = [f"<h1>{html.escape(title)}</h1>", summary_html(summary), "<h2>Measures</h2>",
                    metrics_table_html(metrics), "<h2>Frames by status</h2>",
                    status_table_html(category_counts(trace.categories())),
                    f'<p class="legend">{html.escape(STATUS_NOTE)}</p>']
        sections += _figure_sections(trace, threshold, threshold_source, tmp)
        sections.append(VIEWER_LINK)
        (tmp / "index.html").write_text(page_html(title, sections), encoding="utf-8")
    return Path(out_dir) / "index.html"


def _figure_sections(trace: LocalizationTrace, threshold: float, source: str, folder: Path) -> list[str]:
    """Draw the map view (when the map has positions) and the replay over time into ``folder``; their sections."""
    sections = []
    if trace.map_positions is not None:
        plot_map_view(trace, folder / "map.png")
        sections += ["<h2>On the map</h2>", figure_html("map.png", "estimates on the map", (
            "The map's positions (grey), the query's true positions (blue, where known), and each frame's estimate "
            "at its map frame's position, coloured by status."))]
    plot_over_time(trace, threshold, source, folder / "localisation.png")
    sections += ["<h2>Over time</h2>", figure_html("localisation.png", "estimate, score and latency over time", (
        "Top: the map frame of each estimate against the true one. Middle: the score against the threshold "
        f"({threshold:.4g}: {source}). Bottom: milliseconds per frame."))]
    return sections
