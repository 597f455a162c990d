"""Progress on stderr: a tqdm bar on a terminal, else (a log, CI, nohup, ssh) a progress line at least every
``LINE_SECONDS``; and one summary line per training epoch.

Same name as ``seqvpr.progress``: the command line's progress bars; the library's mechanism there."""

from __future__ import annotations

import sys
from collections.abc import Callable

import click

from seqvpr.progress import LINE_SECONDS, line_progress

__all__ = ["LINE_SECONDS", "TqdmMonitor", "line_progress", "tqdm_progress"]


def tqdm_progress(total: int, label: str) -> Callable[[int], None]:
    """Progress of ``total`` frames on stderr: a tqdm bar on a terminal, else ``line_progress``; returns its update
    function."""
    if not sys.stderr.isatty():
        return line_progress(total, label, echo=lambda text: click.echo(text, err=True))
    from tqdm import tqdm

    bar = tqdm(total=total, desc=label, unit="frame", file=sys.stderr, leave=False)
    return bar.update


class TqdmMonitor:
    """A training monitor: a progress bar per epoch with the running loss (and its parts), and one summary line per
    epoch on stderr."""

    def __init__(self, label: str = "") -> None:
        self.label = label
        self.bar = None
        self.line: Callable[[int], None] | None = None
        self.losses: list[float] = []

    def start_run(self, data, trainable_queries: int) -> None:
        click.echo(
            f"{self.label}train: {data.reference!r} / {data.query!r}\n{self.label}validation: {data.val_reference!r} / "
            f"{data.val_query!r}\n{self.label}positives within {data.positive_radius}, negatives outside "
            f"{data.negative_radius}; {trainable_queries} training queries",
            err=True,
        )

    def start_epoch(self, epoch: int, epochs: int, queries: int) -> None:
        from tqdm import tqdm

        self.losses = []
        label = f"{self.label}epoch {epoch}/{epochs}"
        if sys.stderr.isatty():
            self.bar, self.line = tqdm(total=queries, desc=label, unit="query", file=sys.stderr, leave=False), None
        else:
            self.bar, self.line = None, line_progress(queries, label, unit="queries",
                                                      echo=lambda text: click.echo(text, err=True))

    def advance(self, queries: int, loss: float | None) -> None:
        if loss is not None:
            self.losses.append(loss)
        if self.line is not None:
            self.line(queries)
        if self.bar is not None:
            self.bar.update(queries)
            if loss is not None:
                self.bar.set_postfix(loss=f"{sum(self.losses) / len(self.losses):.4f}")

    def end_epoch(self, record) -> None:
        if self.bar is not None:
            self.bar.close()
        recall = " ".join(f"R@{k} {v:.3f}" for k, v in sorted(record.recall.items()))
        parts = "".join(f", {name} {value:.4f}" for name, value in sorted(record.parts.items()))
        timing = "" if record.epoch == 0 else (
            f"loss {record.loss:.4f}{parts}, {record.triplets} triplets, {record.queries_skipped} queries skipped, "
            f"{record.epoch_seconds:.1f}s (mining {record.mining_seconds:.2f}s); "
        )
        click.echo(f"{self.label}epoch {record.epoch}: {timing}validation {recall}", err=True)
