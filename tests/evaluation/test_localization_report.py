"""The localisation page: readable measures, frames by status (the colour key's counts), the map view only with
positions, the threshold's source in the score plot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from seqvpr.evaluation import localization_plots, localization_report
from seqvpr.evaluation.localization_report import (
    LocalizationTrace, localization_metric_rows, write_localization_report,
)

STAGES = ("describe", "distance", "sequence", "total")


def make_trace(n: int = 60, positions: bool = True, seconds: bool = False) -> LocalizationTrace:
    rng = np.random.default_rng(0)
    status = np.array(["warming up"] * 4 + list(rng.choice(["localised", "uncertain", "lost"], n - 4)))
    best = np.where(status == "warming up", -1, np.arange(n))
    estimate = np.where(np.isin(status, ["localised", "uncertain"]), best, -1)
    truth = np.arange(n)
    truth[10] = -1  # a frame without ground truth
    correct = rng.random(n) < 0.8
    map_xy = np.c_[np.arange(n) * 2.0, np.zeros(n)]
    return LocalizationTrace(np.arange(17, 17 + n), estimate, best, status, rng.random(n), rng.random((n, 4)) * 5,
                             STAGES, correct, truth, np.arange(n) * 0.25 + 100 if seconds else None,
                             map_xy if positions else None, map_xy + [0.0, 3.0] if positions else None)


def test_categories_split_localized_and_count_every_frame():
    trace = make_trace()
    counts = localization_plots.category_counts(trace.categories())
    assert sum(counts.values()) == len(trace.status)
    localized = sum(v for k, v in counts.items() if k.startswith("localised"))
    assert localized == int((trace.status == "localised").sum())
    for status in ("warming up", "uncertain", "lost"):
        assert counts[status] == int((trace.status == status).sum())


def test_plots_label_the_counts_of_every_status(tmp_path):
    trace = make_trace()
    counts = localization_plots.category_counts(trace.categories())
    expected = [localization_plots.legend_label(k, v) for k, v in counts.items()]
    assert localization_plots.plot_map_view(trace, tmp_path / "map.png") == expected
    assert localization_plots.plot_over_time(trace, 0.5, "default for matching (not calibrated)",
                                             tmp_path / "time.png") == expected


@pytest.mark.parametrize("positions", [True, False])
def test_page_has_the_map_view_only_with_positions(tmp_path, positions):
    index = write_localization_report(tmp_path / "r", title="t", summary="s", trace=make_trace(positions=positions),
                                      threshold=0.25, threshold_source="default for matching (not calibrated)",
                                      metrics=[("Recall@1", "0.500")])
    text = index.read_text(encoding="utf-8")
    assert (tmp_path / "r" / "map.png").exists() == positions and (tmp_path / "r" / "localisation.png").exists()
    assert ("map.png" in text) == positions
    assert "0.25: default for matching (not calibrated)" in text
    assert "trusted" not in text


def test_time_axis_is_seconds_with_timestamps_else_query_frames():
    x, label = make_trace(seconds=True).time_axis()
    assert x[0] == 0.0 and x[1] == 0.25 and "(s)" in label
    x, label = make_trace().time_axis()
    assert x[0] == 17 and label == "query frame"


def test_measures_have_readable_names():
    summary = {"frames": 100, "skipped_by_gating": 0, "threshold": 0.015612, "target_precision": 0.99,
               "recall": {"1": 0.5, "5": 0.75}, "pr_auc": 0.61234, "recall_at_100_precision": 0.2,
               "queries_evaluated": 96, "precision_of_localised": 0.95, "recall_of_localised": 0.3,
               "time_to_correct": [{"frames": 6, "seconds": 1.5}, {"frames": None, "seconds": None}],
               "latency_ms": {"total": {"p50": 1.0, "p95": 2.0, "p99": 3.0}}}
    rows = dict(localization_metric_rows(summary))
    assert rows["Recall@1"] == "0.500" and rows["PR-AUC (estimates ranked by score)"] == "0.612"
    assert rows["Recall at 100 % precision"] == "0.200" and rows["Score threshold"] == "0.01561"
    assert rows["Precision of localised estimates (share whose map frame is correct)"] == "0.950"
    assert rows["Frames to the first correct localised estimate (per start)"] == "6 frames (1.5 s); never"
    assert rows["Latency, total (ms)"] == "p50 1.00, p95 2.00, p99 3.00"
    assert not any("_" in name for name in rows)


def test_a_failed_plot_leaves_no_page(tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise RuntimeError("plot failed")

    monkeypatch.setattr(localization_report, "plot_over_time", boom)
    with pytest.raises(RuntimeError, match="plot failed"):
        write_localization_report(tmp_path / "r", title="t", summary="s", trace=make_trace(), threshold=0.1,
                                  threshold_source="x", metrics=[])
    assert list(Path(tmp_path).iterdir()) == []
