"""The benchmark's tables: the methods at the main length, R@1 over the lengths, and every method at every length
with R@K, R@100%P and frame-level precision, as Markdown and CSV (``results.md``, ``results.csv``)."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path

from seqvpr.experiments.benchmark import BenchmarkConfig, Row
from seqvpr.io import atomic_file_set
from seqvpr.methods import METHODS


def main_table(rows: Sequence[Row], config: BenchmarkConfig) -> str:
    """Markdown: one row per method, R@K columns per dataset, at the main sequence length."""
    names = [spec.name for spec in config.datasets]
    header = "| method | " + " | ".join(f"{name} R@{k}" for name in names for k in config.ks) + " |"
    lines = [header, "|---|" + "---:|" * (len(names) * len(config.ks))]
    for method in config.methods:
        cells = []
        for name in names:
            row = _find(rows, name, method, config.seq_len)
            cells += _cells(row, config.ks)
        label = method if METHODS[method].length is not None else f"{method} (L={config.seq_len})"
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines + _failures(rows))


def length_table(rows: Sequence[Row], config: BenchmarkConfig) -> str:
    """Markdown: R@1 per method at each length of the length table, per dataset (like SeqMatchNet's Table 4)."""
    names = [spec.name for spec in config.datasets]
    methods = [m for m in config.methods if METHODS[m].length is None]
    header = "| method | " + " | ".join(f"{name} L={n}" for name in names for n in config.lengths) + " |"
    lines = [header, "|---|" + "---:|" * (len(names) * len(config.lengths))]
    for method in methods:
        cells = []
        for name in names:
            for length in config.lengths:
                row = _find(rows, name, method, length)
                cells.append(_cells(row, config.ks[:1])[0])
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def rows_csv(rows: Sequence[Row], ks: Sequence[int]) -> str:
    """All rows as CSV: dataset, method, L, R@K..., PR-AUC, R@100%P, frame precision, queries evaluated, error.
    Frame precision is empty for methods without per-frame correspondences."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["dataset", "method", "L", *[f"R@{k}" for k in ks], "pr_auc", "recall_at_100_precision",
                     "frame_precision", "queries_evaluated", "error"])
    for row in rows:
        e = row.evaluation
        values = [""] * (len(ks) + 4)
        if e is not None:
            figures = [*(e.recall[k] for k in ks), e.pr.auc, e.pr.recall_at_100_precision, e.frame_precision]
            values = [_figure(v, 4) for v in figures] + [e.queries_evaluated]
        writer.writerow([row.dataset, row.method, row.length, *values, row.error])
    return buffer.getvalue()


def detail_table(rows: Sequence[Row], config: BenchmarkConfig) -> str:
    """Markdown: every method at every length it ran, per dataset R@K... / R@100%P / frame precision in one cell
    (the robotics figures beside the retrieval ones; frame precision '–' where a method pairs no frames)."""
    names = [spec.name for spec in config.datasets]
    what = " / ".join([*(f"R@{k}" for k in config.ks), "R@100P", "frames"])
    lines = ["| method | L | " + " | ".join(f"{name}: {what}" for name in names) + " |",
             "|---|---:|" + "---|" * len(names)]
    for method in config.methods:
        lengths = sorted({r.length for r in rows if r.method == method})
        for length in lengths:
            cells = [_detail_cell(_find(rows, name, method, length), config.ks) for name in names]
            shown = METHODS[method].length or length  # single, hmm, graph: their own length, whatever the run's
            lines.append(f"| {method} | {shown} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _detail_cell(row: Row | None, ks: Sequence[int]) -> str:
    if row is None or row.evaluation is None:
        return _cells(row, ks[:1])[0]
    e = row.evaluation
    figures = [*(e.recall[k] for k in ks), e.pr.recall_at_100_precision, e.frame_precision]
    return " / ".join(_figure(v, 3, missing="–") for v in figures)


def _figure(value: float, digits: int, missing: str = "") -> str:
    """A figure at ``digits`` decimals; NaN (a figure the method does not have) as ``missing``."""
    return f"{value:.{digits}f}" if value == value else missing


def write_results(rows: Sequence[Row], config: BenchmarkConfig, out: Path) -> tuple[Path, Path]:
    """results.csv and results.md (the three tables) in ``out`` (beside the trained models), committed as one pair
    (``seqvpr.io.atomic_file_set``): never one run's csv beside another's md."""
    markdown = f"## Methods at L={config.seq_len}\n\n{main_table(rows, config)}\n\n## Sequence length (R@{config.ks[0]})\n\n"
    markdown += length_table(rows, config) + "\n\n## Every length: R@K, R@100%P and frame-level precision\n\n"
    markdown += detail_table(rows, config) + "\n"
    with atomic_file_set(out, ("results.csv", "results.md"), "results.md") as tmp:
        (tmp / "results.csv").write_text(rows_csv(rows, config.ks))
        (tmp / "results.md").write_text(markdown)
    return out / "results.csv", out / "results.md"


def _find(rows: Sequence[Row], dataset: str, method: str, length: int) -> Row | None:
    if method == "single":
        length = next((r.length for r in rows if r.dataset == dataset and r.method == "single"), length)
    return next((r for r in rows if r.dataset == dataset and r.method == method and r.length == length), None)


def _cells(row: Row | None, ks: Sequence[int]) -> list[str]:
    if row is None:
        return ["–"] * len(ks)
    if row.evaluation is None:
        return ["failed" if row.applicable else "n/a"] * len(ks)
    return [f"{row.evaluation.recall[k]:.3f}" for k in ks]


def _failures(rows: Sequence[Row]) -> list[str]:
    failed = [r for r in rows if r.error and (r.applicable or r.length == _main_length(rows, r))]
    return [""] + [f"- {r.dataset} / {r.method} L={r.length}: {r.error}" for r in failed] if failed else []


def _main_length(rows: Sequence[Row], row: Row) -> int:
    """The first length a method was run at on a dataset (the main one): n/a is said once, not per length."""
    return next(r.length for r in rows if r.dataset == row.dataset and r.method == row.method)
