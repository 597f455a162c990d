"""The interactive viewer (``seqvpr view``): seqvpr's output folders read back (``seqvpr.viewer.runs``), their
frames' thumbnails (``seqvpr.data.thumbnails``) and one self-contained HTML page (``seqvpr.viewer.page``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any


def view_page(runs: Sequence[str | Path], out: str | Path, progress: Any = None) -> Path:
    """The page of ``runs`` (match folders over one pair, or one localisation, or one map) written to ``out``
    (``out/index.html`` and its thumbnails); its path. ``out`` is apart from every run, except that a run's own
    ``RUN/view`` is where its page goes by default (the run's report links there)."""
    from seqvpr import checks
    from seqvpr.io import check_output_apart
    from seqvpr.viewer.page import write_view
    from seqvpr.viewer.runs import read_views

    runs = checks.paths(runs, "runs")
    out = checks.a_path(out, "out")
    checks.function(progress, "progress")
    own = Path(out).resolve()
    check_output_apart(out, [r for r in runs if (Path(r) / "view").resolve() != own], "the page's folder")
    return write_view(read_views([Path(r) for r in runs]), out, progress)
